"""Reader and writer for the MERL BRDF database's binary format (Matusik et al. 2003).

Layout (little-endian, as BRDFRead.cpp reads it on x86): three int32 node counts
(n_theta_h, n_theta_d, n_phi_d) = (90, 90, 180) for the database, then 3 * n float64 values
(n = the product of the counts), channel-major: all red values, then green, then blue. Within a
channel the index is ``(i_theta_h * n_theta_d + i_theta_d) * n_phi_d + i_phi_d``. Stored values
times the channel scale (1/1500, 1.15/1500, 1.66/1500) give f_r in 1/sr; negative values mark
invalid (unmeasured, below-horizon) entries. Node positions are those of
``brdf.TabulatedIsotropic`` (theta_h warped by a square root, phi_d over [0, pi)).
"""
from __future__ import annotations

import os

import numpy as np

from .brdf.tabulated import TabulatedIsotropic

MERL_SHAPE = (90, 90, 180)
MERL_SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
_HEADER = np.dtype("<i4")
_VALUE = np.dtype("<f8")


def read_merl(path: str | os.PathLike) -> TabulatedIsotropic:
    """Read a MERL ``.binary`` file into a ``TabulatedIsotropic`` model (f_r in 1/sr, RGB).

    Invalid (negative) entries become NaN, which the model skips when interpolating. Node
    counts other than (90, 90, 180) are accepted when the file is consistent with its header.

    Raises
    ------
    ValueError
        If the file is shorter than its header, declares non-positive node counts, or its size
        does not match 12 + 3 * 8 * n bytes.
    """
    path = os.fspath(path)
    raw = np.fromfile(path, dtype=np.uint8)
    if raw.size < _HEADER.itemsize * 3:
        raise ValueError(f"{path}: {raw.size} bytes is too short for a MERL header (12 bytes)")
    dims = tuple(int(d) for d in raw[:12].view(_HEADER))
    if min(dims) < 1:
        raise ValueError(f"{path}: header declares non-positive node counts {dims}")
    n = int(np.prod(dims))
    expected = 12 + 3 * n * _VALUE.itemsize
    if raw.size != expected:
        raise ValueError(f"{path}: header {dims} needs {expected} bytes, file has {raw.size}")
    values = raw[12:].view(_VALUE).astype(np.float64).reshape(3, *dims)
    table = np.moveaxis(values, 0, -1) * MERL_SCALE
    table[table < 0] = np.nan
    return TabulatedIsotropic(table, theta_h_warp="sqrt")


def write_merl(path: str | os.PathLike, model: TabulatedIsotropic) -> None:
    """Write a sqrt-warped ``TabulatedIsotropic`` in the MERL format (NaN entries as -1)."""
    if not isinstance(model, TabulatedIsotropic) or model.theta_h_warp != "sqrt":
        raise ValueError("write_merl needs a TabulatedIsotropic with theta_h_warp='sqrt' "
                         "(the MERL node layout)")
    values = np.moveaxis(model.table / MERL_SCALE, -1, 0)
    values = np.where(np.isnan(values), -1.0, values)
    with open(path, "wb") as fh:
        fh.write(np.asarray(model.shape, dtype=_HEADER).tobytes())
        fh.write(np.ascontiguousarray(values, dtype=_VALUE).tobytes())
