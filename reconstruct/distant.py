"""Deterministic shading under distant light sources: quadrature, no Monte Carlo noise.

Ground truth for the methods that observe an object under directional lights or a whole
environment (reflectance sharing, passive reflectometry): the outgoing radiance of a surface
point with unit normal n seen from direction wo is

    L_o = sum_k f_r(wi_k, wo) * E_k * max(0, n . wi_k),    E_k = L_k * Omega_k

over K distant sources in directions wi_k (a directional light of irradiance E_k, or one texel
of an environment map of radiance L_k and solid angle Omega_k: see
:meth:`reconstruct.envmap.EnvironmentMap.sources`). Sources are not occluded: exact for convex
objects (spheres, hemispheres seen from above); for others, shadows and interreflections are
left out. All directions are unit vectors in one frame, the frame of the normals.
"""
from __future__ import annotations

import numpy as np

from .brdf.base import BRDF
from .frames import normalize, tangent_frames, to_local

#: (point, source) pairs evaluated per chunk: bounds the working memory (~0.5 GB at 2e6).
CHUNK_PAIRS = 2_000_000


def sphere_normals(size) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a sphere seen orthographically in the OpenCV camera frame.

    The camera looks along +z (x right, y down), so visible normals point back at it
    (n_z <= 0). The sphere's outline is the largest circle centred in the image.

    Parameters
    ----------
    size : int or (int, int)
        Image size, square or (H, W).

    Returns
    -------
    normals : ndarray of shape (H, W, 3)
        Unit normals inside the mask, zero outside.
    mask : ndarray of shape (H, W), bool
        Pixels whose centre falls on the sphere.
    """
    h, w = (size, size) if np.ndim(size) == 0 else tuple(size)
    if not all(isinstance(v, (int, np.integer)) and v > 0 for v in (h, w)):
        raise ValueError(f"size must be a positive int or (H, W) of positive ints, got {size!r}")
    r = min(h, w) / 2
    x = (np.arange(w) + 0.5 - w / 2) / r
    y = (np.arange(h) + 0.5 - h / 2) / r
    X, Y = np.meshgrid(x, y)
    rho2 = X * X + Y * Y
    mask = rho2 < 1.0
    normals = np.stack([X, Y, -np.sqrt(np.clip(1.0 - rho2, 0.0, None))], axis=-1)
    normals[~mask] = 0.0
    return normals, mask


def _unit_rows(name: str, v, n: int | None = None) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or (n is not None and len(a) != n):
        want = f"({n}, 3)" if n is not None else "(N, 3)"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds non-finite values")
    norm = np.linalg.norm(a, axis=1)
    if np.any(np.abs(norm - 1.0) > 1e-3):
        i = int(np.argmax(np.abs(norm - 1.0)))
        raise ValueError(f"{name} must be unit vectors; row {i} has length {norm[i]:.4g}")
    return normalize(a)


def shade_distant(brdf: BRDF, normals, directions, radiance, solid_angle=None, *,
                  view_dirs=(0.0, 0.0, -1.0), progress=None) -> np.ndarray:
    """Outgoing radiance of surface points lit by distant sources (see module docstring).

    Parameters
    ----------
    brdf : BRDF
        The material; parameters may be per point (leading axis N, as for ``BRDF.take``).
    normals : ndarray of shape (N, 3)
        Unit surface normals.
    directions : ndarray of shape (K, 3)
        Unit directions towards the sources, in the normals' frame.
    radiance : ndarray of shape (K, 3) or (K,)
        With ``solid_angle``: each source's radiance; without: its irradiance at normal
        incidence (a directional light). RGB or grey.
    solid_angle : ndarray of shape (K,), optional
        Solid angle of each source, sr (an environment texel's).
    view_dirs : ndarray of shape (3,) or (N, 3)
        Unit directions from the surface to the camera; default (0, 0, -1), an orthographic
        camera looking along +z (OpenCV camera frame).
    progress : callable, optional
        ``progress(done, total)`` in points, after each chunk.

    Returns
    -------
    ndarray of shape (N, 3)
        Outgoing radiance, in the units of ``radiance`` (x sr with ``solid_angle``).
    """
    if not isinstance(brdf, BRDF):
        raise TypeError(f"brdf must be a reconstruct.brdf.BRDF, got {type(brdf).__name__}")
    n = _unit_rows("normals", normals)
    d = _unit_rows("directions", directions)
    E = np.asarray(radiance, dtype=np.float64)
    E = np.repeat(E[:, None], 3, axis=1) if E.ndim == 1 else E
    if E.shape != (len(d), 3) or not np.all(np.isfinite(E)) or E.min() < 0:
        raise ValueError(f"radiance must be finite, >= 0, of shape ({len(d)}, 3) or "
                         f"({len(d)},), got shape {np.shape(radiance)}")
    if solid_angle is not None:
        omega = np.asarray(solid_angle, dtype=np.float64)
        if omega.shape != (len(d),) or not np.all(np.isfinite(omega)) or omega.min() < 0:
            raise ValueError(f"solid_angle must be finite, >= 0, of shape ({len(d)},), "
                             f"got shape {omega.shape}")
        E = E * omega[:, None]
    lit = E.max(axis=1) > 0  # dark texels cost nothing
    d, E = d[lit], E[lit]
    v = np.asarray(view_dirs, dtype=np.float64)
    v = _unit_rows("view_dirs", np.broadcast_to(v, n.shape) if v.shape == (3,) else v, len(n))

    frames = tangent_frames(n)
    wo_local = to_local(v, frames)
    out = np.zeros((len(n), 3))
    step = max(1, CHUNK_PAIRS // max(len(d), 1))
    for s in range(0, len(n), step):
        idx = np.arange(s, min(s + step, len(n)))
        cos = n[idx] @ d.T                                  # (n, K)
        ii, kk = np.nonzero(cos > 0)                         # front-facing pairs only
        if len(ii):
            wi = to_local(d[kk], frames[idx[ii]])
            f = brdf.take(idx[ii]).evaluate(wi, wo_local[idx[ii]])
            contrib = f * (cos[ii, kk][:, None] * E[kk])
            for c in range(3):
                out[idx, c] = np.bincount(ii, weights=contrib[:, c], minlength=len(idx))
        if progress is not None:
            progress(int(idx[-1]) + 1, len(n))
    return out
