"""The lighting matrix of passive reflectometry (Romeiro et al. 2008, Eqs. 2-5).

Under distant sources, the radiance a camera sees at a surface point with unit normal n is

    I(n) = sum_k f(s_k, t_k) * L_k * Omega_k * max(0, n . u_k),

with f the unknown bivariate BRDF on a uniform (t, s) grid (``reconstruct.brdf.Bivariate``),
s = 2 theta_d / pi and t = sqrt(2 theta_h / pi) of the pair (u_k, v) (``coords.romeiro_st``).
Interpolating f bilinearly between its four nearest nodes makes I linear in the node values:
I = L f, one row per observed normal, one column per node. Both angles come from dot products,
without a local frame: cos(2 theta_d) = u . v and cos(theta_h) = n . h with h = (u + v) /
|u + v|. For one view direction (an orthographic camera) s and h belong to the source alone,
so s and its corner weights are computed once per source (folded into the fluxes) and theta_h
is one dot product per pair. Normals are processed in chunks of neighbours (bands of polar
angle, then azimuth), and each chunk only meets the sources inside its normals' cone widened
to a hemisphere: the pairs are each normal's visible hemisphere and a thin rim. The scatter
of a chunk's pairs onto the nodes is one sparse COO x (K, 3 or 6) product (all corners and
colours at once). The dot products are broadcast products, not BLAS calls: threaded BLAS on
such thin (m, 3) x (3, K) products from several threads was 10-50x slower on a loaded box.

Directions, normals and view directions are unit vectors in one frame; sources are not
occluded (exact for convex objects).

A row depends on its normal and view direction alone, so the rows are built over blocks of
observations (:func:`lighting_sums`): each block's rows are reduced at once to the normal
equations' terms (L^T L, L^T I, the column sums, I . I; :class:`LightingSums`), which add over
blocks, so the fit holds the rows of a few blocks at most (the whole matrix, 8000 observations of
a 32 x 32 grid, is 98 MB in float32, and the solve's float64 copy twice that).
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp

#: (normal, source) pairs per chunk (counting half the sources: each normal's hemisphere):
#: ~8 normals of a 32,768-texel map. Measured on the shared 2-core box, 1000 normals x Grace:
#: 2^16-2^17 0.73-0.79 s CPU, 2^18 0.96-0.99 s (megabyte temporaries page-fault on every
#: allocation), 2^14 (one normal a chunk) 1.8 s (Python overhead).
CHUNK_PAIRS = 1 << 17


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
    d, flux = d[lit], E[lit] * omega[lit, None]  # (K, 3) radiance x sr
    if constant_view:
        # s and the halfway vector depend on the source alone: theta_h is one dot product and
        # the s-corner weights fold into the fluxes (6 columns: lower, upper s-node)
        uv = d @ v[0]
        j0, ws = _lower_node(np.arccos(np.clip(uv, -1.0, 1.0)) / np.pi, n_s)
        h = d + v[0]
        h /= np.sqrt(np.maximum(2.0 + 2.0 * uv, 1e-12))[:, None]
        flux = np.concatenate([flux * (1 - ws)[:, None], flux * ws[:, None]], axis=1)
        per_source = np.concatenate([d, -0.5 * h, j0[:, None]], axis=1)
    else:
        per_source = d
    per_source = np.concatenate([per_source, flux], axis=1)   # one gather per chunk
    n_flux = flux.shape[1]
    order = _neighbour_order(n)
    dT_all = np.ascontiguousarray(d.T)
    step = max(1, CHUNK_PAIRS // max(len(d) // 2, 1))
    offsets = [0, n_s] if constant_view else [0, 1, n_s, n_s + 1]  # rows of the cell corners

    def chunk(start):
        rows_out = order[start:start + step]
        m = len(rows_out)
        nc = n[rows_out]
        # the sources some normal of this chunk sees (its normals lie within a small cone):
        # ~half the sphere, so each normal's pairs are its visible hemisphere and a thin rim
        axis = nc.sum(axis=0)
        axis /= max(np.linalg.norm(axis), 1e-12)
        lowest = float(np.min(nc @ axis))                     # cos of the cone's half-angle
        reach = np.sqrt(max(0.0, 1.0 - lowest ** 2)) if lowest > 0 else np.inf
        src = per_source[_dot3(axis[None], dT_all)[0] > -reach - 1e-6]
        k = len(src)
        dT = np.ascontiguousarray(src[:, :3].T)
        weights = np.empty((len(offsets), m, k), np.float32)
        rows = np.empty((len(offsets), m, k), np.int32)
        cos_i = np.maximum(_dot3(nc, dT), 0.0, out=weights[0])  # invisible pairs weigh nothing
        # half = (1 - cos theta_h) / 2, in float64: it is small near the specular peak
        if constant_view:
            half = _dot3(nc, np.ascontiguousarray(src[:, 3:6].T), 0.5)
            base = src[:, 6].astype(np.int32)                 # lower s-node
        else:
            uv = _dot3(v[rows_out], dT)
            half = (cos_i + nv[rows_out, None]) / np.sqrt(np.maximum(2.0 + 2.0 * uv, 1e-12))
            np.subtract(0.5, 0.5 * half, out=half)
            base, ws = _lower_node(np.arccos(np.clip(uv, -1.0, 1.0), out=uv) / np.pi, n_s)
        # t = sqrt(2 theta_h / pi) with theta_h = 2 asin(sqrt(half)): no cancellation (arccos
        # of a float32 cos theta_h near 1 would lose ~half a node next to the peak)
        t = np.clip(half, 0.0, 1.0, out=half).astype(np.float32)
        np.sqrt(t, out=t)
        np.arcsin(t, out=t)
        t *= np.float32(4 / np.pi)
        np.sqrt(t, out=t)
        i0, upper = _lower_node(t, n_t)
        np.multiply(i0, n_s, out=rows[0])
        rows[0] += base
        rows[0] += (np.arange(m, dtype=np.int32) * n_nodes)[:, None]
        for c in range(1, len(offsets)):
            np.add(rows[0], offsets[c], out=rows[c])
        # cos theta_i x the corner weights
        hi = len(offsets) // 2                                # first upper-t block
        np.multiply(cos_i, upper, out=weights[hi])
        weights[0] -= weights[hi]
        if not constant_view:
            ws = ws.astype(np.float32)
            np.multiply(weights[2], ws, out=weights[3])
            weights[2] -= weights[3]
            np.multiply(weights[0], ws, out=weights[1])
            weights[0] -= weights[1]
        A = sp.coo_matrix((weights.ravel(), (rows.ravel(), np.tile(
            np.arange(k, dtype=np.int32), m * len(offsets)))), shape=(m * n_nodes, k))
        acc = (A @ src[:, -n_flux:].astype(np.float32)).reshape(m, n_t, n_s, -1)
        if constant_view:  # the upper-s columns belong one node to the right
            acc[:, :, 1:, :3] += acc[:, :, :-1, 3:]
        out[:, rows_out] = np.moveaxis(acc[..., :3], -1, 0).reshape(3, m, n_nodes)
        return m

    # numpy's ufuncs and scipy's sparse kernels release the GIL: chunks run on threads
    done = 0
    with ThreadPoolExecutor(max_workers=workers or min(os.cpu_count() or 1, 4)) as pool:
        for m in pool.map(chunk, range(0, len(n), step)):
            done += m
            if progress is not None:
                progress(done, len(n))
    return out


#: observations a block of :func:`lighting_sums` builds at once: 1024 rows of a 32 x 32 grid are
#: 12 MB of float32 rows and one channel's 8 MB float64 copy
BLOCK_ROWS = 1024
#: blocks whose sums (24 MB each on a 32 x 32 grid) are computed, and held, at once before they
#: are added (on a cluster: the tasks that run in parallel)
MAP_BATCH = 4


@dataclass(frozen=True)
class LightingSums:
    """The normal equations of I = L f summed over observations, per colour channel c (float64):
    ``gram`` (3, P, P) L_c^T L_c, ``rhs`` (3, P) L_c^T I_c, ``column`` (3, P) the column sums of
    L_c (each node's share of the irradiance the observations received), ``value_sq`` (3,)
    I_c . I_c, and ``rows``, the observations summed. P = n_t n_s nodes; units those of
    :func:`lighting_matrix` and of the values. Sums over disjoint sets of observations add."""

    gram: np.ndarray
    rhs: np.ndarray
    column: np.ndarray
    value_sq: np.ndarray
    rows: int

    def __add__(self, other: "LightingSums") -> "LightingSums":
        return LightingSums(self.gram + other.gram, self.rhs + other.rhs, self.column + other.column,
                            self.value_sq + other.value_sq, self.rows + other.rows)


def block_sums(normals, values, directions, radiance, solid_angle, view_dirs, grid,
               weights=None) -> LightingSums:
    """:class:`LightingSums` of one block of observations: its rows (:func:`lighting_matrix`;
    arguments as there, ``values`` (m, 3) the observed radiance) reduced at once, each
    observation's terms times its ``weights`` (m, 3) per channel if given (``column``
    unweighted). A per-block task: a pure function of its arguments."""
    L = lighting_matrix(normals, directions, radiance, solid_angle, view_dirs=view_dirs, grid=grid)
    I = np.asarray(values, dtype=np.float64)
    weights = None if weights is None else np.asarray(weights, dtype=np.float64)
    P = L.shape[2]
    gram, rhs = np.empty((3, P, P)), np.empty((3, P))
    for c in range(3):   # one channel's float64 copy at a time
        Lc = L[c].astype(np.float64)
        Wc = Lc if weights is None else Lc * weights[:, c, None]
        gram[c] = Wc.T @ Lc
        rhs[c] = Wc.T @ I[:, c]
    wI = I if weights is None else I * weights
    return LightingSums(gram, rhs, L.sum(axis=1, dtype=np.float64), np.einsum("ij,ij->j", wI, I), len(I))


def block_predictions(normals, directions, radiance, solid_angle, view_dirs, grid, table) -> np.ndarray:
    """L f of one block of observations (m, 3) for a bivariate ``table`` (n_t n_s, 3), 1/sr:
    the radiance the table predicts (arguments as :func:`lighting_matrix`'s). A per-block task."""
    L = lighting_matrix(normals, directions, radiance, solid_angle, view_dirs=view_dirs, grid=grid)
    return np.stack([L[c].astype(np.float64) @ table[:, c] for c in range(3)], axis=1)


def lighting_sums(normals, values, directions, radiance, solid_angle, *, view_dirs=(0.0, 0.0, -1.0),
                  grid=(32, 32), block_rows: int = BLOCK_ROWS, weights=None,
                  map_blocks: Callable[[Callable, list], list] | None = None, progress=None) -> LightingSums:
    """The normal equations of the lighting matrix of ``normals`` against ``values``, built over
    blocks of ``block_rows`` observations (:func:`block_sums`): the same, to rounding, as
    ``L = lighting_matrix(...)``, ``L[c].T @ L[c]`` and so on, without holding L.

    Parameters
    ----------
    normals, directions, radiance, solid_angle, view_dirs, grid
        As :func:`lighting_matrix`'s.
    values : ndarray of shape (N, 3)
        Observed radiance of each normal, RGB (finite).
    block_rows : int
        Observations per block (>= 1).
    weights : ndarray of shape (N, 3), optional
        Each observation's weight per channel (>= 0; e.g. inverse noise variances) in the
        Gram, right-hand side and value sums (not in ``column``); default 1.
    map_blocks : callable(fn, list of argument tuples) -> list, optional
        Runs the per-block tasks (:func:`block_sums`, :data:`MAP_BATCH` at a time; results in
        order): default one after the other here, each block's sums added before the next is
        built; the pipeline passes its executor's.
    progress : callable, optional
        ``progress(done, total)`` in observations, after each batch.

    Raises
    ------
    ValueError
        Naming the argument: ``values`` or ``view_dirs`` not one row per normal, a block size
        below 1; and :func:`lighting_matrix`'s.
    """
    n = _unit_rows("normals", normals)
    I = np.asarray(values, dtype=np.float64)
    if I.shape != (len(n), 3) or not np.all(np.isfinite(I)):
        raise ValueError(f"values must be finite with shape ({len(n)}, 3), got {I.shape}")
    if not (isinstance(block_rows, (int, np.integer)) and block_rows >= 1):
        raise ValueError(f"block_rows must be a positive integer, got {block_rows!r}")
    d, E, omega = check_sources(directions, radiance, solid_angle)
    grid = check_grid(grid)
    v = _view_dirs(view_dirs, len(n))
    if weights is not None:
        weights = np.asarray(weights, dtype=np.float64)
        if weights.shape != I.shape or not np.all(np.isfinite(weights)) or weights.min() < 0:
            raise ValueError(f"weights must be finite, >= 0, with shape {I.shape}, got shape "
                             f"{weights.shape}")
    tasks = [(n[a:a + block_rows], I[a:a + block_rows], d, E, omega, v if v.ndim == 1 else v[a:a + block_rows], grid,
              None if weights is None else weights[a:a + block_rows])
             for a in range(0, len(n), block_rows)]
    P = grid[0] * grid[1]
    gram, rhs, column, value_sq = np.zeros((3, P, P)), np.zeros((3, P)), np.zeros((3, P)), np.zeros(3)
    run = map_blocks or (lambda fn, args: [fn(*a) for a in args])
    batch = 1 if map_blocks is None else MAP_BATCH   # a batch's sums held at once, then added in place
    done = 0
    for start in range(0, len(tasks), batch):
        for part in run(block_sums, tasks[start:start + batch]):
            gram += part.gram
            rhs += part.rhs
            column += part.column
            value_sq += part.value_sq
            done += part.rows
        if progress is not None:
            progress(done, len(n))
    return LightingSums(gram, rhs, column, value_sq, done)


def lighting_predictions(normals, table, directions, radiance, solid_angle, *,
                         view_dirs=(0.0, 0.0, -1.0), grid=(32, 32), block_rows: int = BLOCK_ROWS,
                         map_blocks: Callable[[Callable, list], list] | None = None) -> np.ndarray:
    """L f: the radiance (N, 3) a bivariate ``table`` (n_t, n_s, 3) or (n_t n_s, 3), 1/sr,
    predicts at ``normals``, built over blocks of ``block_rows`` observations
    (:func:`block_predictions`) like :func:`lighting_sums`, without holding L. Arguments as
    :func:`lighting_sums`'s; ValueError names a table of the wrong size."""
    n = _unit_rows("normals", normals)
    grid = check_grid(grid)
    f = np.asarray(table, dtype=np.float64).reshape(-1, 3) if np.size(table) == 3 * grid[0] * grid[1] \
        else None
    if f is None or not np.all(np.isfinite(f)):
        raise ValueError(f"table must hold {grid[0]} x {grid[1]} x 3 finite values, got shape "
                         f"{np.shape(table)}")
    d, E, omega = check_sources(directions, radiance, solid_angle)
    v = _view_dirs(view_dirs, len(n))
    tasks = [(n[a:a + block_rows], d, E, omega, v if v.ndim == 1 else v[a:a + block_rows], grid, f)
             for a in range(0, len(n), block_rows)]
    run = map_blocks or (lambda fn, args: [fn(*a) for a in args])
    return np.concatenate(run(block_predictions, tasks)) if tasks else np.zeros((0, 3))


def _view_dirs(view_dirs, n: int) -> np.ndarray:
    """``view_dirs`` as float64, one (3,) for every observation or (n, 3); ValueError otherwise."""
    v = np.asarray(view_dirs, dtype=np.float64)
    if v.shape != (3,) and v.shape != (n, 3):
        raise ValueError(f"view_dirs must have shape (3,) or ({n}, 3), got {v.shape}")
    return v


def _dot3(a, bT, plus=0.0):
    """``plus + a @ bT`` for a (m, 3), bT (3, k) as three broadcast products: no BLAS call,
    whose threads (one team per calling thread) thrash a loaded machine on such thin
    products."""
    out = a[:, :1] * bT[0]
    if plus:
        out += plus
    out += a[:, 1:2] * bT[1]
    out += a[:, 2:3] * bT[2]
    return out


def _neighbour_order(n):
    """An order of the unit vectors ``n`` (N, 3) in which consecutive ones are close: bands
    of polar angle ~4 deg wide, each by azimuth."""
    band = np.floor(np.arccos(np.clip(n[:, 2], -1.0, 1.0)) / np.radians(4))
    return np.lexsort((np.arctan2(n[:, 1], n[:, 0]), band))


def _lower_node(x, n_nodes):
    """Lower node index (int32) and upper-node weight of coordinates ``x`` in [0, 1] on
    ``n_nodes`` uniform nodes."""
    xs = x * np.asarray(n_nodes - 1, x.dtype)
    i0 = np.minimum(xs.astype(np.int32), n_nodes - 2)
    xs -= i0.astype(x.dtype)
    return i0, xs
