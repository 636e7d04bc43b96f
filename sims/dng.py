"""Write sensor data as a real, uncompressed DNG that rawpy / LibRaw decodes bit-exactly.

tifffile writes the CFA image with ``photometric='cfa'`` and the DNG tags. LibRaw rejects
zlib-compressed DNGs, so frames are stored uncompressed (like most cameras' "uncompressed DNG").
"""
from __future__ import annotations

import io
from fractions import Fraction

import numpy as np
import tifffile

# colour codes of the TIFF/EP CFAPattern tag
_CFA_CODES = {"R": 0, "G": 1, "B": 2}


def _rational(x: float, denominator: int = 10000) -> tuple[int, int]:
    f = Fraction(x).limit_denominator(denominator)
    return f.numerator, f.denominator


def _srational_matrix(m: np.ndarray) -> tuple[int, ...]:
    out: list[int] = []
    for v in np.asarray(m, dtype=float).ravel():
        out.extend(_rational(float(v)))
    return tuple(out)


def write_dng(raw: np.ndarray, *, cfa_pattern: str = "RGGB", black_level: int | tuple[int, ...] = 0,
              white_level: int = 65535, color_matrix: np.ndarray | None = None,
              as_shot_neutral: tuple[float, float, float] = (1.0, 1.0, 1.0),
              make: str = "gonio", model: str = "SimCam", exposure_s: float | None = None,
              iso: float | None = None, fnumber: float | None = None,
              datetime: str | None = None) -> bytes:
    """Encode a Bayer mosaic as DNG bytes.

    Parameters
    ----------
    raw : ndarray of shape (H, W), uint16
        Raw sensor values (digital numbers), mosaic in ``cfa_pattern`` order from the top-left.
    cfa_pattern : str
        Four letters for the 2x2 tile, row-major, e.g. ``"RGGB"``, ``"GRBG"``, ``"BGGR"``, ``"GBRG"``.
    black_level : int or 4 ints
        Sensor black (offset) level in DN: one for all photosites, or one per position of the
        2x2 tile (row-major, as ``cfa_pattern``).
    white_level : int
        Sensor white (saturation) level in DN.
    color_matrix : ndarray of shape (3, 3), optional
        ColorMatrix1 (XYZ -> camera). Identity by default, so camera RGB is the simulator's RGB.
    as_shot_neutral : 3 floats
        White balance as camera-neutral values (1, 1, 1: no white balance needed).
    exposure_s, iso, fnumber : float, optional
        Recorded in the EXIF-style tags ExposureTime (33434), ISOSpeedRatings (34855), FNumber (33437).

    Returns
    -------
    bytes
        The DNG file.
    """
    raw = np.ascontiguousarray(raw)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise ValueError(f"raw must be a 2-D uint16 mosaic, got shape {raw.shape} dtype {raw.dtype}")
    pattern = cfa_pattern.upper()
    if len(pattern) != 4 or set(pattern) - set("RGB"):
        raise ValueError(f"cfa_pattern must be four letters of R, G, B (e.g. 'RGGB'), got {cfa_pattern!r}")
    if np.size(black_level) not in (1, 4):
        raise ValueError(f"black_level must be one level or four (per 2x2 tile position), got {black_level!r}")
    cm = np.eye(3) if color_matrix is None else np.asarray(color_matrix, dtype=float)
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), True),                        # DNGVersion
        (50707, "B", 4, (1, 4, 0, 0), True),                        # DNGBackwardVersion
        (50708, "s", 0, f"{make} {model}", True),                   # UniqueCameraModel
        (33421, "H", 2, (2, 2), True),                              # CFARepeatPatternDim
        (33422, "B", 4, tuple(_CFA_CODES[c] for c in pattern), True),  # CFAPattern
        (50710, "B", 3, (0, 1, 2), True),                           # CFAPlaneColor
        (50713, "H", 2, (2, 2) if np.size(black_level) == 4 else (1, 1), True),  # BlackLevelRepeatDim
        (50714, "I", np.size(black_level), tuple(int(b) for b in np.ravel(black_level)), True),  # BlackLevel
        (50717, "I", 1, (int(white_level),), True),                 # WhiteLevel
        (50721, "2i", 9, _srational_matrix(cm), True),              # ColorMatrix1
        (50778, "H", 1, (21,), True),                               # CalibrationIlluminant1 = D65
        (50728, "2I", 3, tuple(v for x in as_shot_neutral for v in _rational(x)), True),  # AsShotNeutral
        (271, "s", 0, make, True),                                  # Make
        (272, "s", 0, model, True),                                 # Model
    ]
    if exposure_s is not None:
        tags.append((33434, "2I", 1, _rational(exposure_s, 1_000_000), True))
    if fnumber is not None:
        tags.append((33437, "2I", 1, _rational(fnumber, 100), True))
    if iso is not None:
        tags.append((34855, "H", 1, (int(round(iso)),), True))
    if datetime is not None:
        tags.append((306, "s", 0, datetime, True))
    buf = io.BytesIO()
    with tifffile.TiffWriter(buf, bigtiff=False) as tif:
        tif.write(raw, photometric="cfa", compression=None, subfiletype=0,
                  software=False, extratags=tags, metadata=None)
    return buf.getvalue()
