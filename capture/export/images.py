"""Image files of the exported maps: 32-bit float OpenEXR and 16-bit PNG (pure array -> file)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

__all__ = ["write_exr", "write_png16", "read_exr"]


def _check(name: str, image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (1, 3, 4)) or a.size == 0:
        raise ValueError(f"{name}: an image is (H, W), (H, W, 1), (H, W, 3) or (H, W, 4); got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: {int(np.sum(~np.isfinite(a)))} non-finite values")
    return a


def write_exr(path: str | Path, image: np.ndarray) -> Path:
    """Write an (H, W) or (H, W, 3|4) array as a 32-bit float, ZIP-compressed scanline EXR
    (channels ``Y``, ``RGB`` or ``RGBA``); values unchanged (linear, no transfer function)."""
    import OpenEXR
    path = Path(path)
    a = _check(str(path), image).astype(np.float32)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    name = "Y" if a.ndim == 2 else ("RGB" if a.shape[2] == 3 else "RGBA")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {name: np.ascontiguousarray(a)}).write(str(path))
    return path


def read_exr(path: str | Path) -> np.ndarray:
    """The pixels of an EXR written by :func:`write_exr` (float32, (H, W) or (H, W, C))."""
    import OpenEXR
    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        return np.asarray(next(iter(channels.values())).pixels)


def write_png16(path: str | Path, image: np.ndarray, scale: float = 1.0) -> Path:
    """Write ``image / scale`` clipped to [0, 1] as a 16-bit PNG (gray, RGB or RGBA; code
    ``round(65535 v)``). ``scale`` is what a reader multiplies the code / 65535 by."""
    path = Path(path)
    a = _check(str(path), image).astype(np.float64)
    if not scale > 0:
        raise ValueError(f"{path}: scale must be > 0, got {scale}")
    code = np.rint(np.clip(a / scale, 0.0, 1.0) * 65535).astype(np.uint16)
    if code.ndim == 3 and code.shape[2] == 1:
        code = code[..., 0]
    if code.ndim == 3:   # OpenCV writes BGR(A)
        code = code[..., [2, 1, 0, 3][:code.shape[2]]]
    if not cv2.imwrite(str(path), code):
        raise OSError(f"{path}: OpenCV could not write the PNG")
    return path
