"""The Log tab: the runner's events and the console's own actions, filterable by level and kind."""
from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Horizontal, Vertical
from textual.widgets import Input, RichLog, Select

from ..events import Event, EventKind

#: kinds the console adds besides the runner's EventKind values
CONSOLE_KINDS = ("device", "camera", "estop", "console")
_LEVEL_STYLE = {logging.DEBUG: "dim", logging.INFO: "", logging.WARNING: "yellow",
                logging.ERROR: "bold red"}
_EVENT_LEVEL = {EventKind.FAULT: logging.ERROR, EventKind.ABORTED: logging.WARNING,
                EventKind.RETRY: logging.WARNING, EventKind.PAUSED: logging.WARNING,
                EventKind.LOW_DISK: logging.WARNING, EventKind.TARGET: logging.WARNING,
                EventKind.MOVED: logging.DEBUG}


@dataclass(frozen=True)
class LogEntry:
    """One line of the console log. ``kind`` is an EventKind value or one of CONSOLE_KINDS."""

    level: int
    kind: str
    message: str
    device: str | None = None
    time: float = field(default_factory=time.time)

    @classmethod
    def from_event(cls, event: Event) -> "LogEntry":
        where = f"step {event.step}: " if event.step is not None else ""
        return cls(level=_EVENT_LEVEL.get(event.kind, logging.INFO), kind=event.kind.value,
                   message=where + (event.message or event.kind.value), device=event.device,
                   time=event.time)

    def render(self) -> Text:
        stamp = time.strftime("%H:%M:%S", time.localtime(self.time))
        text = Text(f"{stamp} ", style="dim")
        text.append(f"{logging.getLevelName(self.level)[:4]:4} ", style=_LEVEL_STYLE[self.level])
        text.append(f"{self.kind:<15}", style="cyan")
        if self.device:
            text.append(f"[{self.device}] ", style="magenta")
        text.append(self.message, style=_LEVEL_STYLE[self.level])
        return text


class LogPane(Vertical):
    """Keeps the last ``max_entries`` entries; the view shows those passing the filters."""

    LEVELS = [("debug+", logging.DEBUG), ("info+", logging.INFO), ("warning+", logging.WARNING),
              ("error", logging.ERROR)]

    def __init__(self, *, max_entries: int = 5000, **kwargs) -> None:
        super().__init__(**kwargs)
        self.entries: deque[LogEntry] = deque(maxlen=max_entries)

    def compose(self) -> ComposeResult:
        with Horizontal(id="log-filters"):
            yield Select(self.LEVELS, value=logging.INFO, allow_blank=False, id="log-level",
                         prompt="level")
            kinds = [k.value for k in EventKind] + list(CONSOLE_KINDS)
            yield Select([(k, k) for k in kinds], prompt="all kinds", id="log-kind")
            yield Input(placeholder="text filter", id="log-text")
        yield RichLog(id="log-view", wrap=True, max_lines=None, markup=False)

    # -- filters ------------------------------------------------------------------------------
    @property
    def min_level(self) -> int:
        return self.query_one("#log-level", Select).value

    @property
    def kind(self) -> str | None:
        value = self.query_one("#log-kind", Select).value
        return None if value is Select.NULL else value

    def passes(self, entry: LogEntry) -> bool:
        text = self.query_one("#log-text", Input).value.lower()
        return (entry.level >= self.min_level and (self.kind is None or entry.kind == self.kind)
                and (not text or text in entry.message.lower()
                     or text in (entry.device or "").lower()))

    @property
    def visible(self) -> list[LogEntry]:
        """Entries passing the current filters, oldest first."""
        return [e for e in self.entries if self.passes(e)]

    def add(self, entry: LogEntry) -> None:
        self.entries.append(entry)
        if self.is_mounted and self.passes(entry):
            self.query_one(RichLog).write(entry.render())

    def _refilter(self) -> None:
        view = self.query_one(RichLog)
        view.clear()
        for entry in self.visible:
            view.write(entry.render())

    def on_show(self) -> None:
        # RichLog drops writes made while its tab was hidden (no size yet): redraw when shown
        self._refilter()

    def on_select_changed(self, event: Select.Changed) -> None:
        event.stop()
        self._refilter()

    def on_input_changed(self, event: Input.Changed) -> None:
        event.stop()
        self._refilter()
