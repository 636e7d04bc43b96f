"""Camera raw files: one decoder (:func:`read_raw`) and the Bayer mosaic helpers built on it.

Every part of gonio that reads a raw frame (the HDR merge, the session calibration, the
console's preview, auto-exposure metering) goes through :func:`read_raw`, so black levels,
the colour pattern and the exposure metadata are read one way. Pixels: x right, y down, the
mosaic's top-left photosite is the CFA tile's first letter.
"""
from __future__ import annotations

import io
import os
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import median_filter

from . import _validate
from .errors import InvalidInput

__all__ = ["RawMosaic", "read_raw", "cfa_channels", "demosaic_bilinear", "demosaic_smooth_hue"]

#: TIFF/EXIF tag ISOSpeedRatings (LibRaw reads it only from an EXIF sub-IFD; DNG writers such as
#: ``sims.dng`` put it in IFD0)
_TAG_ISO = 34855


@dataclass(frozen=True)
class RawMosaic:
    """A decoded raw frame, as the camera recorded it.

    Attributes
    ----------
    data : ndarray of shape (H, W), uint16
        Visible sensor values, DN.
    cfa : str
        The 2x2 colour tile from the top-left photosite, row-major, e.g. ``'RGGB'``.
    black_level_cfa : ndarray of shape (2, 2), float32
        Black level of each position of the 2x2 tile, DN (per channel, not their mean).
    white_level : float
        Clipping level, DN.
    exposure_s : float or None
        Exposure time from the file's metadata, seconds (None when the file records none).
    iso : float or None
        ISO speed from the file's metadata (None when the file records none).
    """

    data: np.ndarray
    cfa: str
    black_level_cfa: np.ndarray
    white_level: float
    exposure_s: float | None = None
    iso: float | None = None

    @property
    def black_level(self) -> np.ndarray:
        """Black level of every photosite, DN: ndarray of shape (H, W), float32."""
        h, w = self.data.shape
        return np.tile(self.black_level_cfa, ((h + 1) // 2, (w + 1) // 2))[:h, :w]

    @property
    def channels(self) -> np.ndarray:
        """Colour channel (0 R, 1 G, 2 B) of every photosite: ndarray of shape (H, W), uint8."""
        return cfa_channels(self.cfa, self.data.shape)

    def signal(self) -> np.ndarray:
        """The mosaic as fractions of each photosite's usable range: 0 at its own channel's black
        level, 1 at the white level. ndarray of shape (H, W), float32."""
        black = self.black_level
        return (self.data.astype(np.float32) - black) / (np.float32(self.white_level) - black)


def read_raw(source: str | os.PathLike | bytes | bytearray | memoryview, *,
             name: str | None = None) -> RawMosaic:
    """Decode a camera raw file (DNG, CR2, NEF, ... anything LibRaw reads) into a :class:`RawMosaic`.

    Parameters
    ----------
    source : path or bytes
        The file, or its bytes as the camera sent them.
    name : str, optional
        What to call the file in error messages (default: the path, or ``'raw data'``).

    Returns
    -------
    RawMosaic
        The visible mosaic with its per-channel black levels, white level, CFA tile, exposure
        time and ISO.

    Raises
    ------
    InvalidInput
        The source is empty or not a raw file LibRaw can decode, is not a 2x2 RGB Bayer mosaic,
        or its white level is not above every black level (the message names the file).
    """
    import rawpy

    is_bytes = isinstance(source, (bytes, bytearray, memoryview))
    if not is_bytes and not isinstance(source, (str, os.PathLike)):
        raise InvalidInput(f"source must be a path or the bytes of a raw file, got {type(source).__name__}",
                           argument="source")
    label = name or ("raw data" if is_bytes else os.fspath(source))
    if is_bytes and len(source) == 0:
        raise InvalidInput(f"{label}: source is empty (no raw file bytes)", argument="source")
    try:
        with rawpy.imread(io.BytesIO(bytes(source)) if is_bytes else os.fspath(source)) as raw:
            data = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            pattern = raw.raw_pattern
            desc = raw.color_desc.decode("ascii")
            black = np.asarray(raw.black_level_per_channel, np.float32)
            white = float(raw.white_level)
            other = raw.other
            exposure = float(other.shutter_speed) if other.shutter_speed > 0 else None
            iso = float(other.iso_speed) if other.iso_speed > 0 else None
    except (rawpy.LibRawError, OSError) as err:
        raise InvalidInput(f"{label}: not a raw file LibRaw can decode ({type(err).__name__}: {err})",
                           argument="source") from None
    if pattern is None or np.shape(pattern) != (2, 2) or data.ndim != 2:
        raise InvalidInput(f"{label}: only 2x2 Bayer mosaics are supported (pattern "
                           f"{None if pattern is None else np.asarray(pattern).tolist()}, shape {data.shape})",
                           argument="source")
    cfa = "".join(desc[i] for i in np.asarray(pattern).ravel())
    if sorted(cfa) != ["B", "G", "G", "R"]:
        raise InvalidInput(f"{label}: colour filter {cfa!r} is not an RGB Bayer tile", argument="source")
    black_cfa = black[np.asarray(pattern)]
    if not white > black_cfa.max():
        raise InvalidInput(f"{label}: white level {white:g} is not above the black levels "
                           f"{black_cfa.ravel().tolist()}", argument="source")
    if iso is None:
        iso = _tiff_iso(source if is_bytes else None, None if is_bytes else os.fspath(source))
    return RawMosaic(data, cfa, black_cfa, white, exposure, iso)


def _tiff_iso(data, path) -> float | None:
    """ISO from a TIFF-based raw's IFD0 tag (DNG writers may keep it there, where LibRaw does not
    look); None when absent or not a TIFF."""
    import tifffile

    try:
        with tifffile.TiffFile(io.BytesIO(bytes(data)) if data is not None else path) as tif:
            tag = tif.pages[0].tags.get(_TAG_ISO)
            value = None if tag is None else np.ravel(tag.value)[0]
    except (tifffile.TiffFileError, OSError, ValueError, IndexError):
        return None
    return float(value) if value else None


def cfa_channels(cfa: str, shape: tuple[int, int]) -> np.ndarray:
    """Colour channel of every photosite of a Bayer mosaic.

    Parameters
    ----------
    cfa : str
        The 2x2 tile from the top-left, row-major, e.g. ``'RGGB'``.
    shape : (int, int)
        Mosaic height and width, pixels.

    Returns
    -------
    ndarray of shape (H, W), uint8
        0 for R, 1 for G, 2 for B.
    """
    if not isinstance(cfa, str) or len(cfa) != 4 or set(cfa) - set("RGB"):
        raise InvalidInput(f"cfa must be four letters of R, G, B such as 'RGGB', got {cfa!r}", argument="cfa")
    tile = np.array(["RGB".index(c) for c in cfa], np.uint8).reshape(2, 2)
    h, w = shape
    return np.tile(tile, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


_BILINEAR = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], np.float32)


def demosaic_bilinear(mosaic, channels) -> np.ndarray:
    """Bilinear demosaic for any 2x2 Bayer layout.

    Each channel keeps its own samples and averages its nearest same-colour neighbours elsewhere
    (normalised convolution, so a linear ramp is reproduced exactly away from the border).

    Parameters
    ----------
    mosaic : ndarray of shape (H, W)
        Linear mosaic values (any unit, e.g. DN/s from the HDR merge).
    channels : ndarray of shape (H, W)
        Channel of each photosite (0 R, 1 G, 2 B), e.g. :func:`cfa_channels` or
        :attr:`RawMosaic.channels`.

    Returns
    -------
    ndarray of shape (H, W, 3), float32
        Linear RGB in the unit of ``mosaic``.
    """
    mosaic = _validate.image(mosaic, "mosaic", ndim=2).astype(np.float32, copy=False)
    colors = np.asarray(channels)
    if colors.shape != mosaic.shape:
        raise InvalidInput(f"channels must have the mosaic's shape {mosaic.shape}, got {colors.shape}",
                           argument="channels")
    out = np.empty(mosaic.shape + (3,), np.float32)
    for c in range(3):  # three channels, not pixels
        m = (colors == c).astype(np.float32)
        num = cv2.filter2D(mosaic * m, -1, _BILINEAR, borderType=cv2.BORDER_REFLECT)
        den = cv2.filter2D(m, -1, _BILINEAR, borderType=cv2.BORDER_REFLECT)
        out[..., c] = np.where(m > 0, mosaic, num / np.maximum(den, 1e-6))
    return out


def demosaic_smooth_hue(mosaic, channels, *, window: int = 5) -> np.ndarray:
    """Demosaic for images whose brightest detail is smaller than the 2 x 2 Bayer tile.

    A light source smaller than a photosite (a window of the room in a 20 px mirror ball) is
    seen by the one photosite it falls on: bilinear interpolation gives it that channel alone,
    at twice (green) or four times (red, blue) its share of the light after interpolation, and
    the others nothing. On the quick demo's light probe one pixel carried a third of the map's
    light, and the map came out green (its irradiance 40-78 % off per channel). Here luminance
    keeps every photosite's own reading, and the hue (the log ratio of each channel to green)
    varies more slowly: it is the median over a ``window`` x ``window`` neighbourhood of the
    bilinear result (Cok's constant-hue assumption, with a median so that an isolated bright
    photosite takes its surroundings' hue rather than its own aliased one). Each pixel's
    channels are then its reading times the hue's ratio of each channel to its own.

    Parameters
    ----------
    mosaic : ndarray of shape (H, W)
        Linear mosaic values (any unit, e.g. DN/s from the HDR merge); values <= 0 stay <= 0.
    channels : ndarray of shape (H, W)
        Channel of each photosite (0 R, 1 G, 2 B).
    window : int
        Odd side of the hue's median window, pixels (>= 3).

    Returns
    -------
    ndarray of shape (H, W, 3), float32
        Linear RGB in the unit of ``mosaic``; each photosite's own channel is its reading.
    """
    window = _validate.integer(window, "window", minimum=3)
    if window % 2 == 0:
        raise InvalidInput(f"window must be odd, got {window}", argument="window")
    rgb = demosaic_bilinear(mosaic, channels)
    top = float(rgb.max())
    floor = 1e-9 * top if top > 0 else 1.0
    log = np.log(np.maximum(rgb, floor))
    hue = np.exp(median_filter(log - log[..., 1:2], size=(window, window, 1), mode="reflect"))
    ch = np.asarray(channels, np.intp)[..., None]
    reading = np.take_along_axis(rgb, ch, axis=2)  # the photosite's own channel, as measured
    return (reading * hue / np.take_along_axis(hue, ch, axis=2)).astype(np.float32)
