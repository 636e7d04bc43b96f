"""Argument checks shared by the calibration functions: each raises
:class:`~calibration.errors.InvalidInput` naming the argument, before numpy or OpenCV can fail
deep inside with a message about their own internals."""
from __future__ import annotations

import numpy as np

from .errors import InvalidInput

#: lengths OpenCV accepts for distortion vectors (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]])
_DIST_LENGTHS = (4, 5, 8, 12, 14)


def array(value, name: str, *, shape: tuple | None = None, ndim: tuple | int | None = None,
          finite: bool = True, dtype=np.float64) -> np.ndarray:
    """``value`` as an array of ``dtype``; ``shape`` entries of ``-1`` match any length."""
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError):
        raise InvalidInput(f"{name} must be a numeric array, got {type(value).__name__}",
                           argument=name) from None
    if ndim is not None and arr.ndim not in np.atleast_1d(ndim):
        raise InvalidInput(f"{name} must have {ndim} dimensions, got shape {arr.shape}", argument=name)
    if shape is not None and (arr.ndim != len(shape) or
                              any(want not in (-1, have) for want, have in zip(shape, arr.shape))):
        want = str(tuple("N" if s == -1 else s for s in shape)).replace("'", "")
        raise InvalidInput(f"{name} must have shape {want}, got {arr.shape}", argument=name)
    if finite and arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise InvalidInput(f"{name} contains NaN or infinite values", argument=name)
    return arr


def positive(value, name: str, *, allow_zero: bool = False) -> float:
    """A finite scalar > 0 (or >= 0)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InvalidInput(f"{name} must be a number, got {value!r}", argument=name) from None
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise InvalidInput(f"{name} must be {'>= 0' if allow_zero else 'positive'} and finite, got {value!r}",
                           argument=name)
    return v


def integer(value, name: str, *, minimum: int) -> int:
    """An integer >= ``minimum`` (floats with an integral value accepted)."""
    try:
        v = int(value)
        ok = v == float(value)
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok or v < minimum:
        raise InvalidInput(f"{name} must be an integer >= {minimum}, got {value!r}", argument=name)
    return v


def camera(K, dist) -> tuple[np.ndarray, np.ndarray]:
    """A pinhole matrix (3, 3) with positive focal lengths and an OpenCV distortion vector
    (``None`` -> no distortion)."""
    K = array(K, "K", shape=(3, 3))
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.allclose(K[2], [0, 0, 1]):
        raise InvalidInput("K must be a camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0",
                           argument="K")
    d = np.zeros(5) if dist is None else array(dist, "dist").ravel()
    if d.size not in _DIST_LENGTHS:
        raise InvalidInput(f"dist must hold {', '.join(map(str, _DIST_LENGTHS))} OpenCV coefficients, "
                           f"got {d.size}", argument="dist")
    return K, d


def image(value, name: str, *, ndim: tuple | int = (2, 3), dtype=None, finite: bool = True) -> np.ndarray:
    """A non-empty image: (H, W) or (H, W, C) (``ndim`` narrows it), converted to ``dtype`` when
    given (else its dtype kept), and free of NaN / inf when ``finite``."""
    try:
        img = np.asarray(value)
    except (TypeError, ValueError):
        img = None
    if img is None or img.dtype.kind not in "biuf":
        raise InvalidInput(f"{name} must be a numeric image array, got {type(value).__name__}", argument=name)
    dims = tuple(np.atleast_1d(ndim))
    if img.ndim not in dims or img.shape[0] == 0 or img.shape[1] == 0:
        want = " or ".join({2: "(H, W)", 3: "(H, W, C)"}[d] for d in dims)
        raise InvalidInput(f"{name} must be a non-empty {want} image, got shape {img.shape}", argument=name)
    if dtype is not None:
        img = img.astype(dtype, copy=False)
    if finite and img.dtype.kind == "f" and not np.all(np.isfinite(img)):
        raise InvalidInput(f"{name} contains NaN or infinite values", argument=name)
    return img


def gray(value, name: str, *, weights=None, dtype=np.float64) -> np.ndarray:
    """A single-channel (H, W) view of an (H, W) or (H, W, 3|4) image: the colour channels'
    mean, or their sum weighted by ``weights`` (3,) (alpha dropped), as ``dtype``."""
    img = image(value, name)
    if img.ndim == 3:
        if img.shape[2] not in (3, 4):
            raise InvalidInput(f"{name} must be (H, W) or (H, W, 3), got shape {img.shape}", argument=name)
        rgb = img[..., :3].astype(dtype, copy=False)
        img = rgb.mean(axis=2) if weights is None else rgb @ np.asarray(weights, dtype)
    return img.astype(dtype, copy=False)
