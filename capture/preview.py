"""Quick-look rendering of camera frames for a terminal: half-block images and raw histograms.

Pure functions, no UI: the operator console (``capture/tui``) calls them on a worker thread and
draws the result. All pixel work is vectorised numpy; the only Python loop is over runs of equal
colour in the *output* (a few thousand terminal cells at most).

Pipeline for a DNG frame::

    decode_dng(bytes) -> RawMosaic                  calibration.raw.read_raw: CFA values, DN
    bin_cfa(mosaic)   -> (H/2, W/2, 3) float32      linear, 0 = black level, 1 = white level
    fit_cells(...) + downscale(...)                 area-average to the widget's cell grid
    to_display(...)   -> uint8 sRGB                 gamma-encoded for the terminal
    half_block_segments(...) -> rich Segments       one '▀' per cell: fg = upper pixel, bg = lower

``raw_histogram(mosaic)`` counts each colour channel of the raw CFA in DN (before any scaling),
with the fraction of pixels clipped at the black and the white level — the numbers an operator
needs to pick the exposures of a bracket.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from rich.color import Color, ColorType
from rich.color_triplet import ColorTriplet
from rich.segment import Segment
from rich.style import Style

from calibration.errors import InvalidInput
from calibration.raw import RawMosaic, read_raw

#: block characters for one-row bar charts, from empty to full
SPARK = np.array(list(" ▁▂▃▄▅▆▇█"))
CHANNELS = ("R", "G", "B")
UPPER_HALF = "▀"


class PreviewError(ValueError):
    """A frame cannot be previewed (not a raw file rawpy reads, wrong array shape...)."""


def decode_dng(data: bytes) -> RawMosaic:
    """Read a raw file (DNG or any format LibRaw knows) from memory with
    :func:`calibration.raw.read_raw`.

    Raises
    ------
    PreviewError
        If ``data`` is not a raw file LibRaw can open, or is not a 2x2 RGB Bayer mosaic.
    """
    try:
        return read_raw(data, name="frame")
    except InvalidInput as exc:
        raise PreviewError(str(exc)) from None


def bin_cfa(mosaic: RawMosaic) -> np.ndarray:
    """Demosaic-free quick RGB: each 2x2 CFA tile becomes one pixel (R, mean of the Gs, B).

    Parameters
    ----------
    mosaic : RawMosaic

    Returns
    -------
    ndarray of shape (H // 2, W // 2, 3), float32
        Linear, black-subtracted and scaled so that 0 is the black level and 1 the white level
        (values above 1 cannot occur; an odd last row / column is dropped).
    """
    h, w = mosaic.data.shape
    if h < 2 or w < 2:
        raise PreviewError(f"mosaic is {h}x{w} pixels; at least one 2x2 tile is needed")
    hh, ww = h // 2, w // 2
    out = np.zeros((hh, ww, 3), dtype=np.float32)
    counts = np.zeros(3, dtype=np.float32)
    for k, c in enumerate(mosaic.cfa):  # four tile positions (strided views), not pixels
        i, j = divmod(k, 2)
        black = np.float32(mosaic.black_level_cfa[i, j])
        scale = np.float32(1.0 / max(mosaic.white_level - black, 1.0))
        ch = CHANNELS.index(c)
        out[..., ch] += (mosaic.data[i:2 * hh:2, j:2 * ww:2].astype(np.float32) - black) * scale
        counts[ch] += 1
    out /= counts
    return np.clip(out, 0.0, 1.0, out=out)


def fit_cells(image_hw: tuple[int, int], cols: int, rows: int) -> tuple[int, int]:
    """Largest cell grid inside ``cols x rows`` that keeps the image's aspect ratio.

    A terminal cell holds two image pixels stacked (half blocks) and is about twice as tall as
    wide, so one cell is one pixel wide and two pixels tall.

    Parameters
    ----------
    image_hw : (int, int)
        Image height and width, pixels.
    cols, rows : int
        Space available, terminal cells (>= 1).

    Returns
    -------
    (int, int)
        ``(cols, rows)`` to use, each >= 1.
    """
    h, w = image_hw
    if cols < 1 or rows < 1:
        raise PreviewError(f"cols and rows must be >= 1, got {cols}x{rows}")
    if h < 1 or w < 1:
        raise PreviewError(f"image_hw must be positive, got {image_hw}")
    scale = min(cols / w, 2 * rows / h)
    return max(1, min(cols, round(w * scale))), max(1, min(rows, round(h * scale / 2)))


def downscale(image: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """Area-average an image to ``2 * rows`` pixel rows by ``cols`` columns (for half blocks).

    Parameters
    ----------
    image : ndarray of shape (H, W, 3), float
        Linear RGB.
    cols, rows : int
        Target grid in terminal cells (see :func:`fit_cells`).

    Returns
    -------
    ndarray of shape (2 * rows, cols, 3), float32
    """
    image = _check_rgb(image, "image")
    interp = cv2.INTER_AREA if image.shape[0] >= 2 * rows else cv2.INTER_LINEAR
    return cv2.resize(image, (cols, 2 * rows), interpolation=interp)


def to_display(linear: np.ndarray, *, gain: float = 1.0) -> np.ndarray:
    """Encode linear RGB for the screen: ``gain``, clip to [0, 1], sRGB transfer curve, 8 bit.

    Parameters
    ----------
    linear : ndarray of shape (..., 3), float
        Linear values, 1 = white.
    gain : float
        Multiplier applied before encoding (> 0); 1 shows the exposure as captured, so clipped
        highlights look clipped.

    Returns
    -------
    ndarray of shape (..., 3), uint8
    """
    if not gain > 0:
        raise PreviewError(f"gain must be > 0, got {gain}")
    x = np.clip(np.asarray(linear, dtype=np.float32) * np.float32(gain), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def half_block_segments(rgb8: np.ndarray) -> list[list[Segment]]:
    """Terminal lines for an image: each cell is '▀' with the upper pixel as foreground colour
    and the lower pixel as background.

    Parameters
    ----------
    rgb8 : ndarray of shape (2 * rows, cols, 3), uint8
        sRGB pixels; an odd height gets a black last row.

    Returns
    -------
    list of list of rich.segment.Segment
        ``rows`` lines of ``cols`` cells; runs of identical cells share one segment.
    """
    rgb8 = np.asarray(rgb8)
    if rgb8.ndim != 3 or rgb8.shape[2] != 3 or rgb8.dtype != np.uint8:
        raise PreviewError(f"rgb8 must be a (H, W, 3) uint8 array, got shape {rgb8.shape} "
                           f"dtype {rgb8.dtype}")
    if rgb8.shape[0] % 2:
        rgb8 = np.concatenate([rgb8, np.zeros_like(rgb8[:1])], axis=0)
    packed = (rgb8[..., 0].astype(np.uint32) << 16) | (rgb8[..., 1].astype(np.uint32) << 8) \
        | rgb8[..., 2]
    top, bottom = packed[0::2], packed[1::2]
    key = (top.astype(np.uint64) << 24) | bottom  # one number per cell
    rows, cols = key.shape
    # run starts per line, found for all lines at once
    change = np.ones((rows, cols), dtype=bool)
    change[:, 1:] = key[:, 1:] != key[:, :-1]
    styles: dict[int, Style] = {}
    lines = []
    for r in range(rows):
        starts = np.flatnonzero(change[r])
        ends = np.append(starts[1:], cols)
        line = []
        for s, e, k in zip(starts.tolist(), ends.tolist(), key[r, starts].tolist()):
            style = styles.get(k)
            if style is None:
                style = styles[k] = Style.from_color(_truecolor(k >> 24), _truecolor(k & 0xFFFFFF))
            line.append(Segment(UPPER_HALF * (e - s), style))
        lines.append(line)
    return lines


def _truecolor(rgb: int) -> Color:
    # built directly: parsing "#rrggbb" strings cost half of the rendering time
    return Color("", ColorType.TRUECOLOR, triplet=ColorTriplet(rgb >> 16, (rgb >> 8) & 255, rgb & 255))


@dataclass(frozen=True)
class Histogram:
    """Per-channel histogram of a frame with its clipping.

    Attributes
    ----------
    counts : ndarray of shape (3, bins), int64
        Pixel counts of R, G, B over ``edges``.
    edges : ndarray of shape (bins + 1,), float
        Bin edges in the frame's units (DN for raw frames, linear value for images).
    clipped_black_pct, clipped_white_pct : ndarray of shape (3,), float
        Percent of each channel's pixels at or below the black level / at or above the white
        level.
    black, white : float
        The crushed-black level and the clipped-white threshold used, same units as ``edges``.
    """

    counts: np.ndarray
    edges: np.ndarray
    clipped_black_pct: np.ndarray
    clipped_white_pct: np.ndarray
    black: float
    white: float

    def warnings(self, threshold_pct: float = 0.1) -> list[str]:
        """One line per channel and end clipped by more than ``threshold_pct`` percent."""
        out = []
        for name, lo, hi in zip(CHANNELS, self.clipped_black_pct, self.clipped_white_pct):
            if hi > threshold_pct:
                out.append(f"{name} {hi:.1f}% clipped white")
            if lo > threshold_pct:
                out.append(f"{name} {lo:.1f}% crushed black")
        return out

    def sparklines(self, width: int) -> list[str]:
        """One row of block characters per channel, ``width`` characters each.

        Bins are merged to ``width`` columns; heights are log-scaled (log1p of counts) so that
        the thin tails that matter for clipping stay visible.
        """
        if width < 1:
            raise PreviewError(f"width must be >= 1, got {width}")
        bins = self.counts.shape[1]
        starts = np.linspace(0, bins, min(width, bins) + 1).astype(int)[:-1]
        merged = np.log1p(np.add.reduceat(self.counts, starts, axis=1).astype(float))
        top = merged.max()
        level = np.zeros_like(merged, dtype=int) if top == 0 else \
            np.ceil(merged / top * (len(SPARK) - 1)).astype(int)
        cols = np.repeat(np.arange(level.shape[1]), np.diff(np.linspace(0, width, level.shape[1] + 1)
                                                             .astype(int)))
        return ["".join(SPARK[row[cols]]) for row in level]


def raw_histogram(mosaic: RawMosaic, bins: int = 64, *, white_fraction: float = 0.95
                  ) -> Histogram:
    """Histogram of the raw CFA values per colour channel, with clipping at black and white.

    Parameters
    ----------
    mosaic : RawMosaic
    bins : int
        Number of equal bins between the lowest black level and the white level, DN.
    white_fraction : float
        A pixel counts as clipped white at ``black + white_fraction * (white_level - black)``
        or above, in (0, 1]. Below 1 because sensors often saturate under the file's nominal
        WhiteLevel (full well before the ADC's top code), and HDR merges drop near-white pixels
        anyway; 1 counts only pixels at the white level.

    Returns
    -------
    Histogram
        Edges in DN; ``white`` is the clipping threshold used. A pixel counts as crushed at
        ``<= black_level`` of its own CFA position.
    """
    if bins < 1:
        raise PreviewError(f"bins must be >= 1, got {bins}")
    if not 0 < white_fraction <= 1:
        raise PreviewError(f"white_fraction must be in (0, 1], got {white_fraction}")
    lo, hi = float(mosaic.black_level_cfa.min()), float(mosaic.white_level)
    edges = np.linspace(lo, hi, bins + 1)
    # the bin of every possible DN, so each CFA position needs one bincount over its raw values
    bin_of = np.clip(((np.arange(65536) - lo) * (bins / max(hi - lo, 1.0))).astype(np.int64),
                     0, bins - 1)
    counts = np.zeros((3, bins), dtype=np.int64)
    total, crushed, clipped = np.zeros(3), np.zeros(3), np.zeros(3)
    for k, c in enumerate(mosaic.cfa):  # the four positions of the 2x2 tile
        i, j = divmod(k, 2)
        per_dn = np.bincount(mosaic.data[i::2, j::2].ravel(), minlength=65536)
        ch = CHANNELS.index(c)
        counts[ch] += np.bincount(bin_of, weights=per_dn, minlength=bins).astype(np.int64)
        black = float(mosaic.black_level_cfa[i, j])
        white = black + white_fraction * (hi - black)
        total[ch] += per_dn.sum()
        crushed[ch] += per_dn[: int(np.floor(black)) + 1].sum()
        clipped[ch] += per_dn[int(np.ceil(white)):].sum()
    with np.errstate(invalid="ignore", divide="ignore"):
        return Histogram(counts=counts, edges=edges,
                         clipped_black_pct=np.nan_to_num(100 * crushed / total),
                         clipped_white_pct=np.nan_to_num(100 * clipped / total),
                         black=lo, white=float(lo + white_fraction * (hi - lo)))


def image_histogram(image: np.ndarray, bins: int = 64) -> Histogram:
    """Histogram of a linear RGB image (0 = black, 1 = white) per channel.

    Parameters
    ----------
    image : ndarray of shape (H, W, 3), float
    bins : int

    Returns
    -------
    Histogram
        Edges in linear units on [0, 1]; clipped white at ``>= 1``, crushed at ``<= 0``.
    """
    image = _check_rgb(image, "image")
    if bins < 1:
        raise PreviewError(f"bins must be >= 1, got {bins}")
    flat = image.reshape(-1, 3)
    b = np.clip((flat * bins).astype(np.int64), 0, bins - 1)
    counts = np.stack([np.bincount(b[:, c], minlength=bins) for c in range(3)])
    return Histogram(counts=counts, edges=np.linspace(0.0, 1.0, bins + 1),
                     clipped_black_pct=100 * (flat <= 0).mean(axis=0),
                     clipped_white_pct=100 * (flat >= 1).mean(axis=0), black=0.0, white=1.0)


@dataclass(frozen=True)
class Preview:
    """What the console draws for one frame.

    Attributes
    ----------
    linear : ndarray of shape (h, w, 3), float32
        Full quick-look image (binned CFA or the given linear image), kept so a resized widget
        can re-render without decoding again.
    histogram : Histogram
    """

    linear: np.ndarray
    histogram: Histogram

    def render(self, cols: int, rows: int, *, gain: float = 1.0) -> list[list[Segment]]:
        """Half-block lines fitting ``cols x rows`` cells, aspect ratio kept."""
        c, r = fit_cells(self.linear.shape[:2], cols, rows)
        return half_block_segments(to_display(downscale(self.linear, c, r), gain=gain))


def make_preview(source: bytes | np.ndarray, bins: int = 64) -> Preview:
    """Decode a frame once for display.

    Parameters
    ----------
    source : bytes or ndarray of shape (H, W, 3)
        Raw file bytes (DNG...) or a linear float RGB image (1 = white).
    bins : int
        Histogram bins.
    """
    if isinstance(source, (bytes, bytearray, memoryview)):
        mosaic = decode_dng(source)
        return Preview(linear=bin_cfa(mosaic), histogram=raw_histogram(mosaic, bins))
    image = _check_rgb(source, "source")
    return Preview(linear=image, histogram=image_histogram(image, bins))


def _check_rgb(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 1 or image.shape[1] < 1:
        raise PreviewError(f"{name} must have shape (H, W, 3), got {image.shape}")
    if not np.issubdtype(image.dtype, np.floating):
        raise PreviewError(f"{name} must be a float image (linear, 1 = white), got {image.dtype}")
    return image.astype(np.float32, copy=False)
