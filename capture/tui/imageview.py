"""Preview widgets: the last frame in half blocks, and one histogram per exposure of a bracket."""
from __future__ import annotations

from dataclasses import dataclass

from rich.segment import Segment
from rich.text import Text
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual import work
from textual.app import ComposeResult
from textual.binding import Binding
from textual.reactive import reactive
from textual.strip import Strip
from textual.widget import Widget
from textual.widgets import Label, Static

from ..preview import Preview

_CHANNEL_STYLE = ("bold red", "bold green", "bold dodger_blue1")


@dataclass(frozen=True)
class PreviewFrame:
    """A decoded frame with what the operator needs to know about it.

    ``label`` names it (``test shot``, ``step 12``); ``exposure_s`` / ``iso`` as the camera
    reported them; ``filename`` the camera's name.
    """

    preview: Preview
    label: str
    exposure_s: float | None = None
    iso: float | None = None
    filename: str = ""

    @property
    def exposure_text(self) -> str:
        if self.exposure_s is None:
            return "?"
        t = self.exposure_s
        shutter = f"1/{1 / t:.0f} s" if 0 < t < 0.5 else f"{t:g} s"
        return shutter + (f" ISO {self.iso:g}" if self.iso else "")


class HalfBlockImage(Widget):
    """Draws a :class:`~capture.preview.Preview` with '▀' cells.

    The cells are built on a worker thread (a 120x40 region of a detailed image costs tens of
    milliseconds, mostly creating one rich Style per colour pair) whenever the preview, the
    size or the gain changes; until they arrive the previous lines stay on screen.
    """

    DEFAULT_CSS = """
    HalfBlockImage { width: 1fr; height: 1fr; min-height: 4; }
    """

    gain: reactive[float] = reactive(1.0)

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self._preview: Preview | None = None
        self._lines: list[list[Segment]] = []
        self._key: tuple | None = None      # what self._lines show
        self._wanted: tuple | None = None   # what is being rendered

    @property
    def preview(self) -> Preview | None:
        return self._preview

    @property
    def rendered(self) -> bool:
        """True once the lines on screen show the current preview, size and gain."""
        return self._key is not None and self._key == self._current_key()

    def show(self, preview: Preview | None) -> None:
        """Display ``preview`` (None clears the widget)."""
        self._preview = preview
        if preview is None:
            self._lines, self._key = [], None
        self.refresh()

    def watch_gain(self) -> None:
        self.refresh()

    def _current_key(self) -> tuple:
        return (id(self._preview), self.size.width, self.size.height, self.gain)

    def _ensure_lines(self) -> None:
        key = self._current_key()
        if self._preview is None or key in (self._key, self._wanted) or min(key[1:3]) < 1:
            return
        self._wanted = key
        self._render_lines(self._preview, key)

    @work(thread=True, exclusive=True, group="half-blocks")
    def _render_lines(self, preview: Preview, key: tuple) -> None:
        lines = preview.render(key[1], key[2], gain=key[3])
        self.app.call_from_thread(self._rendered, key, lines)

    def _rendered(self, key: tuple, lines: list[list[Segment]]) -> None:
        if key == self._wanted:  # not superseded by a newer frame or size
            self._lines, self._key = lines, key
            self.refresh()

    def render_line(self, y: int) -> Strip:
        self._ensure_lines()
        width = self.size.width
        if y >= len(self._lines):
            return Strip.blank(width, self.rich_style)
        line = Strip(self._lines[y])
        pad = (width - line.cell_length) // 2  # centre horizontally
        if pad > 0:
            line = Strip([Segment(" " * pad, self.rich_style), *self._lines[y]])
        return line.extend_cell_length(width, self.rich_style).crop(0, width)


class HistogramView(Static):
    """Histogram of one frame: a coloured sparkline per channel and clipping warnings."""

    DEFAULT_CSS = """
    HistogramView { height: auto; padding: 0 1; }
    """

    def __init__(self, frame: PreviewFrame, *, threshold_pct: float = 0.1, **kwargs) -> None:
        super().__init__(**kwargs)
        self.frame = frame
        self.threshold_pct = threshold_pct

    @property
    def warnings(self) -> list[str]:
        return self.frame.preview.histogram.warnings(self.threshold_pct)

    def render(self) -> Text:
        hist = self.frame.preview.histogram
        width = max(8, self.size.width - 4)
        text = Text(f"{self.frame.exposure_text}  {self.frame.label}\n", style="bold")
        for name, style, row in zip("RGB", _CHANNEL_STYLE, hist.sparklines(width)):
            text.append(f"{name} ", style=style)
            text.append(row + "\n", style=style.replace("bold ", ""))
        warnings = self.warnings
        if warnings:
            text.append("⚠ " + ", ".join(warnings), style="bold yellow on dark_red")
        else:
            text.append("no clipping", style="green")
        return text


class PreviewPane(Vertical):
    """The Preview tab: the image on the left, the bracket's histograms on the right."""

    BINDINGS = [Binding("plus,equals_sign", "gain(2)", "Gain ×2", key_display="+"),
                Binding("minus", "gain(0.5)", "Gain ÷2")]

    def action_gain(self, factor: float) -> None:
        """Display gain (a power of two, 1/64 .. 64); the histograms stay on the raw values."""
        image = self.query_one(HalfBlockImage)
        image.gain = min(max(image.gain * factor, 1 / 64), 64)
        self.query_one("#preview-gain", Label).update(f"display gain ×{image.gain:g}")

    def compose(self) -> ComposeResult:
        with Horizontal(id="preview-top"):
            yield Label("no frame yet: take a test shot (Devices, t) or start a session",
                        id="preview-info")
            yield Label("display gain ×1", id="preview-gain")
        with Horizontal(id="preview-body"):
            yield HalfBlockImage(id="preview-image")
            yield VerticalScroll(id="histograms")

    async def show_bracket(self, frames: list[PreviewFrame]) -> None:
        """Show the last of ``frames`` as the image and one histogram per frame."""
        if not frames:
            return
        last = frames[-1]
        self.query_one(HalfBlockImage).show(last.preview)
        h, w = last.preview.linear.shape[:2]
        name = f" {last.filename}" if last.filename else ""
        self.query_one("#preview-info", Label).update(
            f"{last.label}{name}: {last.exposure_text}, quick look {w}x{h} (2x2 binned)")
        box = self.query_one("#histograms", VerticalScroll)
        await box.remove_children()
        await box.mount_all([HistogramView(f, classes="histogram") for f in frames])
