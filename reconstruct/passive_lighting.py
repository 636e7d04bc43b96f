"""The lighting matrix of passive reflectometry (Romeiro et al. 2008, Eqs. 2-5).

Under distant sources, the radiance a camera sees at a surface point with unit normal n is

    I(n) = sum_k f(s_k, t_k) * L_k * Omega_k * max(0, n . u_k),

with f the unknown bivariate BRDF on a uniform (t, s) grid (``reconstruct.brdf.Bivariate``),
s = 2 theta_d / pi and t = sqrt(2 theta_h / pi) of the pair (u_k, v) (``coords.romeiro_st``).
Interpolating f bilinearly between its four nearest nodes makes I linear in the node values:
I = L f, one row per observed normal, one column per node. Both angles come from dot products,
without a local frame: cos(2 theta_d) = u . v and cos(theta_h) = n . (u + v) / |u + v|, so an
(n, u) pair costs a few array operations and the pairs are never materialised as local
direction pairs. The scatter of every pair's two t-corners onto the nodes is a sparse (CSC)
product that also sums over the s-corners and colours, which numpy's ``bincount`` does ~3x
slower (12 passes instead of one).

Directions, normals and view directions are unit vectors in one frame; sources are not
occluded (exact for convex objects).
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp

#: (normal, source) pairs per chunk: ~25 bytes a pair of temporaries (~6 MB), cache-friendly.
CHUNK_PAIRS = 1 << 18


def _unit_rows(name: str, v, n: int | None = None) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or (n is not None and len(a) != n):
        raise ValueError(f"{name} must have shape ({'N' if n is None else n}, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds non-finite values")
    norm = np.linalg.norm(a, axis=1)
    if len(a) and np.max(np.abs(norm - 1.0)) > 1e-3:
        i = int(np.argmax(np.abs(norm - 1.0)))
        raise ValueError(f"{name} must be unit vectors; row {i} has length {norm[i]:.4g}")
    return a / norm[:, None]


def check_grid(grid) -> tuple[int, int]:
    """``grid`` as (n_t, n_s), each >= 2 nodes; ValueError naming ``grid`` otherwise."""
    try:
        n_t, n_s = (int(g) for g in grid)
    except (TypeError, ValueError):
        raise ValueError(f"grid must be (n_t, n_s), got {grid!r}") from None
    if min(n_t, n_s) < 2:
        raise ValueError(f"grid must have >= 2 nodes per axis, got {grid!r}")
    return n_t, n_s


def check_sources(directions, radiance, solid_angle):
    """Validated distant sources: directions (K, 3) unit, radiance (K, 3) >= 0, solid angles
    (K,) >= 0 sr; errors name the argument."""
    d = _unit_rows("directions", directions)
    E = np.asarray(radiance, dtype=np.float64)
    if E.shape != (len(d), 3) or not np.all(np.isfinite(E)) or (E.size and E.min() < 0):
        raise ValueError(f"radiance must be finite, >= 0, of shape ({len(d)}, 3), got shape "
                         f"{E.shape}")
    omega = np.asarray(solid_angle, dtype=np.float64)
    if omega.shape != (len(d),) or not np.all(np.isfinite(omega)) or (omega.size and
                                                                       omega.min() < 0):
        raise ValueError(f"solid_angle must be finite, >= 0, of shape ({len(d)},), got shape "
                         f"{omega.shape}")
    return d, E, omega


def lighting_matrix(normals, directions, radiance, solid_angle, *, view_dirs=(0.0, 0.0, -1.0),
                    grid=(32, 32), workers=None, progress=None) -> np.ndarray:
    """Lighting matrix L, per colour channel, of distant sources seen by surface points.

    Parameters
    ----------
    normals : ndarray of shape (N, 3)
        Unit normals of the observed points, each facing its camera (n . v > 0).
    directions : ndarray of shape (K, 3)
        Unit directions towards the sources, in the normals' frame.
    radiance : ndarray of shape (K, 3)
        Radiance of each source, RGB (e.g. an environment texel's).
    solid_angle : ndarray of shape (K,)
        Solid angle of each source, sr.
    view_dirs : ndarray of shape (3,) or (N, 3)
        Unit directions from the surface to the camera; default (0, 0, -1): an orthographic
        camera looking along +z (OpenCV camera frame).
    grid : (int, int)
        Nodes (n_t, n_s) of the bivariate table (``reconstruct.brdf.Bivariate``).
    workers : int, optional
        Threads (default: the CPU count, at most 4); every chunk of normals is independent.
    progress : callable, optional
        ``progress(done, total)`` in normals, after each chunk (in order).

    Returns
    -------
    ndarray of shape (3, N, n_t * n_s), float32
        ``L[c] @ table[..., c].ravel()`` is the radiance of each point in channel c (units of
        ``radiance`` x sr x 1/sr) for the bivariate table ``table`` (n_t, n_s, 3); columns are
        flat node indices ``i * n_s + j`` (row-major like ``Bivariate.table``).

    Raises
    ------
    ValueError
        Naming the argument: shapes, non-unit or non-finite vectors, negative radiance or solid
        angle, a normal facing away from its camera.
    """
    n = _unit_rows("normals", normals)
    d, E, omega = check_sources(directions, radiance, solid_angle)
    n_t, n_s = check_grid(grid)
    v = np.asarray(view_dirs, dtype=np.float64)
    constant_view = v.shape == (3,)
    v = _unit_rows("view_dirs", v[None] if constant_view else v, None if constant_view else len(n))
    nv = np.einsum("ij,ij->i", n, np.broadcast_to(v, n.shape))
    if len(n) and nv.min() <= 0:
        raise ValueError(f"normals must face the camera (n . view_dirs > 0); row "
                         f"{int(np.argmin(nv))} does not")
    n_nodes = n_t * n_s
    out = np.zeros((3, len(n), n_nodes), np.float32)
    lit = (E.max(axis=1) > 0) & (omega > 0)  # dark sources add nothing
    dT = np.ascontiguousarray(d[lit].T, dtype=np.float32)
    flux = (E[lit] * omega[lit, None]).astype(np.float32)  # (K, 3) radiance x sr
    uv_const = (v[0] @ d[lit].T).astype(np.float32) if constant_view else None
    n32, v32, nv32 = n.astype(np.float32), v.astype(np.float32), nv.astype(np.float32)
    step = max(1, CHUNK_PAIRS // max(int(lit.sum()), 1))

    def chunk(start):
        sl = slice(start, min(start + step, len(n)))
        m = sl.stop - sl.start
        cos_i = n32[sl] @ dT                                  # (m, K) n . u
        keep = cos_i.max(axis=0) > 0                          # sources some normal here sees
        cos_i = cos_i[:, keep]
        uv = (uv_const[keep][None] if constant_view else v32[sl] @ dT[:, keep])  # u . v
        rows, weights = _chunk_pairs(cos_i, uv, nv32[sl], n_t, n_s)
        cols = np.broadcast_to(np.arange(cos_i.shape[1], dtype=np.int32), cos_i.shape).ravel()
        corners = [sp.coo_matrix((w, (rows, cols)), shape=(m * n_nodes, cos_i.shape[1]))
                   @ flux[keep] for w in weights]                # 4 x (m * n_nodes, 3)
        acc = corners[0].reshape(m, n_t, n_s, 3)               # each at its lower-left node
        acc[:, :, 1:] += corners[1].reshape(m, n_t, n_s, 3)[:, :, :-1]
        acc[:, 1:] += corners[2].reshape(m, n_t, n_s, 3)[:, :-1]
        acc[:, 1:, 1:] += corners[3].reshape(m, n_t, n_s, 3)[:, :-1, :-1]
        out[:, sl] = np.moveaxis(acc, -1, 0).reshape(3, m, n_nodes)
        return sl.stop

    # numpy's ufuncs and scipy's sparse kernels release the GIL: chunks run on threads
    with ThreadPoolExecutor(max_workers=workers or min(os.cpu_count() or 1, 4)) as pool:
        for done in pool.map(chunk, range(0, len(n), step)):
            if progress is not None:
                progress(done, len(n))
    return out


def _chunk_pairs(cos_i, uv, nv, n_t, n_s):
    """Bilinear scatter of one chunk's m x K (normal, source) pairs: ``rows`` (m K,), the flat
    index (normal, lower t-node, lower s-node) of each pair, and four ``weights`` (m K,)
    (cos theta_i times the corner weight) for its corners (t, s), (t, s+1), (t+1, s),
    (t+1, s+1). ``cos_i`` (m, K) = n . u, ``uv`` (m or 1, K) = u . v, ``nv`` (m,) = n . v."""
    m, k = cos_i.shape
    # s = 2 theta_d / pi with cos(2 theta_d) = u . v
    sj = np.arccos(np.clip(uv, -1.0, 1.0)) * np.float32((n_s - 1) / np.pi)
    j0 = np.minimum(sj.astype(np.int32), n_s - 2)
    ws = sj - j0
    # t = sqrt(2 theta_h / pi) with cos(theta_h) = n . (u + v) / |u + v|
    x = cos_i + nv[:, None]
    x *= 1.0 / np.sqrt(np.maximum(2.0 + 2.0 * uv, 1e-12))
    np.clip(x, 0.0, 1.0, out=x)
    ti = np.arccos(x, out=x)
    ti *= np.float32(2 / np.pi)
    np.sqrt(ti, out=ti)
    ti *= n_t - 1
    i0 = np.minimum(ti.astype(np.int32), n_t - 2)
    b = ti - i0
    b *= np.maximum(cos_i, 0.0)                        # cos(theta_i) x upper-t weight
    a = np.maximum(cos_i, 0.0)
    a -= b                                             # cos(theta_i) x lower-t weight
    rows = i0
    rows += np.arange(m, dtype=np.int32)[:, None] * n_t
    rows *= n_s
    rows += j0
    weights = [a - a * ws, a * ws, b - b * ws, b * ws]
    return rows.ravel(), [w.ravel() for w in weights]
