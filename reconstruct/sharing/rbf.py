"""Scattered-data interpolation with the linear radial basis function and greedy centre selection.

The interpolant (Zickler et al. 2005, Eqs. 2-6) in d dimensions is

    g~(x) = c_0 + sum_k c_k x'_k + sum_i lambda_i |x' - x'_i|,    x' = M (x - shift),

with ``M = diag(scale)`` (Eq. 4: radially asymmetric basis functions) and the centres x_i a
subset of the samples chosen greedily after Carr et al. 2001: fit the current centres, evaluate
the residual at every sample (weighted, e.g. by cos theta_i so that it is a radiance residual),
append the worst samples (kept apart from each other, so one block covers several error
regions) as a block of new centres, and repeat to a target accuracy or centre
count. The coefficients solve the symmetric indefinite system of Eq. 3,

    [Psi + rho I   P] [lambda]   [g]
    [P^T           0] [c     ] = [0],    Psi_ij = |x'_i - x'_j|,  P = [1, x'],

directly (LU: scipy's symmetric-indefinite LDL^T path ran ~9x slower at 2000 centres). At the
paper's sizes (<= a few thousand centres) a direct solve costs well under a second, so each
round re-solves with the previous round's centres plus the new block (the centres carry over;
there is no iterative solver to warm-start).

Samples that coincide in the scaled space make the system singular (scipy's RBFInterpolator
then returns coefficients ~1e16 without a word). Here exact duplicates are merged (weighted mean
of their values) before fitting, and a new centre must lie at least ``min_separation`` from every
centre already chosen; a near-duplicate with a different value is therefore never a centre, the
fit approximates it instead.

Samples a little apart can still be repeated measurements of one value (the two orderings of a
reciprocal pair that an image holds a pixel apart, whose measured values differ when the surface
is not quite reciprocal): an interpolant goes through whichever becomes a centre, not their mean.
With ``merge_radius`` > 0, samples that are each other's nearest neighbour within that scaled
distance are merged into one first, at the weight^2-weighted mean of their positions and values
(the least-squares estimate of one value from two weighted residuals), an estimate instead of an
arbitrary pick. Off by default: on the zoo it brings the non-reciprocal RGL vinyl closer to the
reciprocal BRDF nearest it, and flattens highlights about a pixel wide (docs/zoo.md).

Evaluation (``RbfModel.__call__``) runs in blocks: squared distances as one float32 GEMM per
block, ``[a, |a|^2, 1] . [-2c, 1, |c|^2]^T`` into a reused buffer, square root in place, and a
second GEMM with the coefficients: no loop over centres.

References
----------
T. Zickler, S. Enrique, R. Ramamoorthi, P. Belhumeur, "Reflectance sharing: image-based
rendering from a sparse set of images", EGSR 2005, Sects. 4-5;
J. C. Carr et al., "Reconstruction and representation of 3D objects with radial basis
functions", SIGGRAPH 2001, Sect. 3.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.linalg
from scipy.spatial import cKDTree

#: evaluation block (points per GEMM): 1024 x 2000 centres of float32 (8 MB) stay in cache;
#: 8192-row blocks (64 MB) ran ~1.5x slower (2026-11, 2 loaded cores)
EVAL_BLOCK = 1 << 10


#: candidates per new centre a greedy round considers (the worst POOL x block samples);
#: 32 beat 8 (held-out error 6.8 -> 4.3 %, 100 px Cook-Torrance sphere, 1000 centres) and 128
POOL = 32


class SharingError(ValueError):
    """Bad input or an under-determined fit in reflectance sharing; the message names the
    argument."""


def _finite_array(name: str, a, ndim: int, dtype=np.float64) -> np.ndarray:
    arr = np.asarray(a, dtype=dtype)
    if arr.ndim != ndim:
        raise SharingError(f"{name} must have {ndim} dimension(s), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise SharingError(f"{name} contains NaN or infinite values "
                           f"({int(np.sum(~np.isfinite(arr)))} of {arr.size})")
    return arr


@dataclass(frozen=True, eq=False)
class RbfModel:
    """A fitted linear-RBF interpolant with a degree-1 polynomial; call it on new points.

    Attributes
    ----------
    centers : ndarray, (M, D)
        Centre positions in the caller's (unscaled) coordinates.
    coefficients : ndarray, (M, C)
        lambda_i per output channel, in value units per scaled distance.
    polynomial : ndarray, (D + 1, C)
        c_0 (constant) then c_1..c_D, acting on scaled, shifted coordinates.
    scale : ndarray, (D,)
        Diagonal of M (Eq. 4), multiplies coordinates before distances are taken.
    shift : ndarray, (D,)
        Subtracted before scaling (the centres' mean: keeps float32 distances accurate).
    """

    centers: np.ndarray
    coefficients: np.ndarray
    polynomial: np.ndarray
    scale: np.ndarray
    shift: np.ndarray
    _gemm_rhs: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        c = (self.centers - self.shift) * self.scale
        rhs = np.concatenate([-2.0 * c.T, np.ones((1, len(c))), np.sum(c * c, axis=1)[None]])
        object.__setattr__(self, "_gemm_rhs", np.ascontiguousarray(rhs, dtype=np.float32))

    @property
    def n_centers(self) -> int:
        return len(self.centers)

    @property
    def dim(self) -> int:
        return self.centers.shape[1]

    @property
    def n_channels(self) -> int:
        return self.coefficients.shape[1]

    def __call__(self, points, *, block: int = EVAL_BLOCK, workers: int | None = None,
                 progress: Callable[[int, int], None] | None = None) -> np.ndarray:
        """Evaluate at ``points`` (N, D), same coordinates as the centres -> (N, C) float64.

        Distances are computed in float32 (blocked GEMM, see module docstring); the polynomial
        and the accumulation of the block results in float64. Blocks are shared among
        ``workers`` threads (default: the CPU count; numpy releases the GIL in GEMMs and
        ufuncs). With several workers, single-threaded BLAS (``OPENBLAS_NUM_THREADS=1``)
        avoids oversubscription.
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != self.dim:
            raise SharingError(f"points must have shape (N, {self.dim}), got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise SharingError("points contains NaN or infinite values")
        x = (pts - self.shift) * self.scale
        out = x @ self.polynomial[1:] + self.polynomial[0]
        n = len(x)
        starts = list(range(0, n, block))
        n_workers = max(1, min(len(starts), workers or os.cpu_count() or 1))
        lam = self.coefficients.astype(np.float32)
        done = [0]
        lock = threading.Lock()

        def run(my_starts):
            d = x.shape[1]
            lhs = np.empty((min(block, n), d + 2), dtype=np.float32)
            buf = np.empty((min(block, n), self.n_centers), dtype=np.float32)
            for start in my_starts:
                xb = x[start:start + block]
                b = len(xb)
                lhs[:b, :d] = xb
                lhs[:b, d] = np.sum(xb * xb, axis=1)
                lhs[:b, d + 1] = 1.0
                dist = np.matmul(lhs[:b], self._gemm_rhs, out=buf[:b])
                # rounding makes tiny squared distances < 0; |.| fixes them ~2x faster than max
                np.abs(dist, out=dist)
                np.sqrt(dist, out=dist)
                out[start:start + b] += dist @ lam
                if progress is not None:
                    with lock:
                        done[0] += b
                        progress(done[0], n)

        if n_workers == 1:
            run(starts)
        else:
            with ThreadPoolExecutor(max_workers=n_workers) as pool:
                list(pool.map(run, [starts[i::n_workers] for i in range(n_workers)]))
        return out


@dataclass(frozen=True, eq=False)
class RbfFit:
    """Result of :func:`fit_rbf`.

    Attributes
    ----------
    model : RbfModel
        The final interpolant.
    order : ndarray of int, (M,)
        Indices into ``points`` (the deduplicated samples, see below) of the centres in the
        order the greedy selection added them: ``refit(m)`` fits the first m.
    points, values, weight : ndarray, (S', D), (S', C), (S',)
        The merged (deduplicated) samples the fit used.
    history : ndarray, (R, 3)
        Per round: centre count, weighted RMS residual and weighted max |residual| over all
        samples (value units).
    converged : bool
        True when ``tol`` was reached (False when the centre budget ended the selection).
    n_merged : int
        How many input samples were merged into others as exact duplicates.
    smoothing : float
        rho of the solve.
    n_paired : int
        How many mutual-nearest pairs within ``merge_radius`` were merged into one sample each.
    """

    model: RbfModel
    order: np.ndarray
    points: np.ndarray
    values: np.ndarray
    weight: np.ndarray
    history: np.ndarray
    converged: bool
    n_merged: int
    smoothing: float
    n_paired: int = 0

    def refit(self, n_centers: int) -> RbfModel:
        """The interpolant on the first ``n_centers`` greedily chosen centres (error vs count)."""
        if not 1 <= n_centers <= len(self.order):
            raise SharingError(f"n_centers must be in [1, {len(self.order)}], got {n_centers}")
        return _solve(self.points, self.values, self.order[:n_centers], self.model.scale,
                      self.model.shift, self.smoothing)

    def report(self) -> str:
        m, rms, worst = self.history[-1]
        state = "converged" if self.converged else "centre budget reached"
        paired = f", {self.n_paired} near pairs merged" if self.n_paired else ""
        return (f"RBF fit: {int(m)} centres of {len(self.points)} samples ({self.n_merged} "
                f"duplicates merged{paired}), weighted residual RMS {rms:.4g}, max {worst:.4g} "
                f"({state})")


def _merge_duplicates(points, values, weight):
    """Exact duplicate points -> one sample with the weighted mean value (weights summed).
    Weights are > 0 here (zero-weight samples are dropped first)."""
    uniq, inverse = np.unique(points, axis=0, return_inverse=True)
    if len(uniq) == len(points):
        return points, values, weight, 0
    inverse = inverse.reshape(-1)
    wsum = np.bincount(inverse, weight, len(uniq))
    merged = np.stack([np.bincount(inverse, weight * values[:, k], len(uniq))
                       for k in range(values.shape[1])], axis=1) / wsum[:, None]
    return uniq, merged, wsum, len(points) - len(uniq)


def _merge_pairs(points, values, weight, scale, radius):
    """Samples that are each other's nearest neighbour within ``radius`` (distance after
    ``scale``) -> one sample at the weight^2-weighted mean position and value, weight the root
    of the summed squares (so a residual there counts as both did). Pairs only, never chains:
    a sample belongs to at most one merge. Returns the merged arrays and the pair count."""
    dist, nearest = cKDTree(points * scale).query(points * scale, k=2)
    dist, nearest = dist[:, 1], nearest[:, 1]
    i = np.arange(len(points))
    first = (nearest[nearest] == i) & (dist <= radius) & (i < nearest)
    a, b = i[first], nearest[first]
    wa, wb = weight[a, None] ** 2, weight[b, None] ** 2
    points, values, weight = points.copy(), values.copy(), weight.copy()
    points[a] = (wa * points[a] + wb * points[b]) / (wa + wb)
    values[a] = (wa * values[a] + wb * values[b]) / (wa + wb)
    weight[a] = np.sqrt(wa + wb)[:, 0]
    keep = np.ones(len(points), dtype=bool)
    keep[b] = False
    return points[keep], values[keep], weight[keep], len(a)


def _solve(points, values, idx, scale, shift, smoothing) -> RbfModel:
    x = (points[idx] - shift) * scale
    m, d = x.shape
    sq = np.sum(x * x, axis=1)
    psi = np.sqrt(np.maximum(sq[:, None] + sq[None] - 2.0 * x @ x.T, 0.0))
    psi[np.diag_indices(m)] = smoothing
    a = np.zeros((m + d + 1, m + d + 1))
    a[:m, :m] = psi
    a[:m, m] = a[m, :m] = 1.0
    a[:m, m + 1:] = x
    a[m + 1:, :m] = x.T
    rhs = np.zeros((m + d + 1, values.shape[1]))
    rhs[:m] = values[idx]
    try:
        sol = scipy.linalg.solve(a, rhs, check_finite=False)
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError) as exc:
        raise SharingError(f"points: the RBF system of {m} centres is singular ({exc}); "
                           "raise min_separation or smoothing") from exc
    if not np.all(np.isfinite(sol)):
        raise SharingError(f"points: the RBF system of {m} centres is singular; "
                           "raise min_separation or smoothing")
    return RbfModel(points[idx].copy(), sol[:m], sol[m:], scale, shift)


def _spanning_seed(x: np.ndarray) -> np.ndarray:
    """Extreme samples along each axis: they span the data's affine hull for the polynomial."""
    return np.unique(np.concatenate([np.argmin(x, axis=0), np.argmax(x, axis=0)]))


def _pick_block(x, err, chosen_mask, centers_x, n_new, min_sep, spread=0.0):
    """Up to ``n_new`` samples of largest ``err`` (not yet centres) that lie at least
    ``min_sep`` from every centre, and ``max(min_sep, spread)`` from each other (scaled
    coordinates): a block spread over several error regions instead of one cluster of
    neighbouring samples around the worst."""
    cand = np.flatnonzero(~chosen_mask & (err > 0))
    if len(cand) == 0:
        return np.zeros(0, dtype=np.intp)
    cand = cand[np.argsort(-err[cand], kind="stable")[:POOL * n_new]]
    cx = x[cand]
    d2 = (np.sum(cx * cx, axis=1)[:, None] + np.sum(centers_x * centers_x, axis=1)[None]
          - 2.0 * cx @ centers_x.T)
    keep = d2.min(axis=1, initial=np.inf) >= min_sep ** 2
    cand, cx = cand[keep], cx[keep]
    picked: list[int] = []
    # first spread apart; if that leaves the block short, fill it in error order (else the
    # rounds multiply: 72 instead of 9 for 2000 centres from 96k samples)
    for sep in (max(min_sep, spread), min_sep):
        free = np.ones(len(cand), dtype=bool)
        for j in picked:
            free &= np.sum((cx - cx[j]) ** 2, axis=1) >= sep ** 2
        for j in range(len(cand)):  # <= POOL n_new candidates, each step one vector operation
            if len(picked) == n_new:
                break
            if not free[j]:
                continue
            picked.append(j)
            free &= np.sum((cx - cx[j]) ** 2, axis=1) >= sep ** 2
    return cand[np.asarray(picked, dtype=np.intp)]


def _typical_spacing(x: np.ndarray, m: int) -> float:
    """Edge of the cell each of ``m`` centres would own in the bounding box of ``x`` (scaled)."""
    span = np.ptp(x, axis=0)
    span = span[span > 0]
    return float(np.prod(span) / m) ** (1.0 / max(len(span), 1))


def fit_rbf(points, values, *, scale=None, weight=None, max_centers: int = 2000, tol=None,
            smoothing: float = 0.0, rng=0, progress: Callable[[int, int], None] | None = None,
            initial_centers: int = 64, growth: float = 1.25, spread: float = 1.0,
            min_separation: float = 1e-6, merge_radius: float = 0.0) -> RbfFit:
    """Greedy linear-RBF fit (Zickler et al. 2005 Eqs. 2-6; Carr et al. 2001 selection).

    Parameters
    ----------
    points : array_like, (S, D)
        Sample positions (any units; ``scale`` makes the dimensions comparable).
    values : array_like, (S,) or (S, C)
        Sample values; all channels share the centres (one solve with C right-hand sides).
    scale : array_like, (D,), optional
        Diagonal of M (Eq. 4), > 0; default ones.
    weight : array_like, (S,), optional
        Non-negative residual weight per sample (the paper: cos theta_i, so residuals are in
        radiance). Zero-weight samples are ignored entirely. Default ones.
    max_centers : int
        Centre budget (>= D + 2).
    tol : float, optional
        Stop when every weighted |residual| is <= ``tol`` (value units); default: run to the
        budget.
    smoothing : float
        rho >= 0 added to the kernel diagonal (scaled-distance units): 0 interpolates the centres.
    rng : int or numpy.random.Generator
        Seeds the random part of the initial centres.
    progress : callable, optional
        ``progress(n_centres, max_centers)`` after each round.
    initial_centers : int
        Size of the first, random set (plus the extreme sample of each axis).
    growth : float
        Each round adds ``(growth - 1) x`` the current centre count (a block), >= 1.05.
        1.25 measured better than 1.5 (held-out errors on 64-px Cook-Torrance sphere images
        4.3 -> 3.1 %) at
        about the same time.
    spread : float
        New centres of one block keep ``spread`` x the typical centre spacing (bounding-box
        volume / centre count, to the power 1/D) from each other, so a block covers several
        error regions (0: take the worst samples as they come).
    min_separation : float
        Smallest scaled distance between two centres (near-duplicates are never both centres).
    merge_radius : float
        Samples that are each other's nearest neighbour within this scaled distance are merged
        into one (module docstring); 0: only exact duplicates are.

    Returns
    -------
    RbfFit

    Raises
    ------
    SharingError
        Non-finite or mis-shaped input, too few samples for the degree-1 polynomial (D + 2), or
        samples that lie in a hyperplane (the polynomial is then undetermined), each naming the
        argument.
    """
    pts = _finite_array("points", points, 2)
    vals = np.asarray(values, dtype=np.float64)
    vals = _finite_array("values", vals.reshape(len(vals), -1) if vals.ndim == 1 else vals, 2)
    s, d = pts.shape
    if len(vals) != s:
        raise SharingError(f"values must have one row per point ({s}), got {len(vals)}")
    w = np.ones(s) if weight is None else _finite_array("weight", weight, 1)
    if len(w) != s or np.any(w < 0):
        raise SharingError(f"weight must be (S,) = ({s},) and >= 0")
    sc = np.ones(d) if scale is None else _finite_array("scale", scale, 1)
    if sc.shape != (d,) or np.any(sc <= 0):
        raise SharingError(f"scale must be ({d},) positive numbers, got {np.asarray(scale)!r}")
    if not (isinstance(max_centers, (int, np.integer)) and max_centers >= d + 2):
        raise SharingError(f"max_centers must be an integer >= D + 2 = {d + 2}, "
                           f"got {max_centers!r}")
    if tol is not None and not tol >= 0:
        raise SharingError(f"tol must be >= 0, got {tol!r}")
    if not smoothing >= 0:
        raise SharingError(f"smoothing must be >= 0, got {smoothing!r}")
    if not spread >= 0:
        raise SharingError(f"spread must be >= 0, got {spread!r}")
    if not merge_radius >= 0:
        raise SharingError(f"merge_radius must be >= 0, got {merge_radius!r}")
    if not growth >= 1.05:
        raise SharingError(f"growth must be >= 1.05, got {growth!r}")
    keep = w > 0
    pts, vals, w = pts[keep], vals[keep], w[keep]
    pts, vals, w, n_merged = _merge_duplicates(pts, vals, w)
    n_paired = 0
    if merge_radius > 0 and len(pts) > 1:
        pts, vals, w, n_paired = _merge_pairs(pts, vals, w, sc, merge_radius)
    if len(pts) < d + 2:
        raise SharingError(f"points: {len(pts)} distinct samples with weight > 0; the linear RBF "
                           f"with a degree-1 polynomial in {d} dimensions needs at least {d + 2}")
    shift = pts.mean(axis=0)
    x = (pts - shift) * sc
    rank = np.linalg.matrix_rank(x - x.mean(axis=0), tol=1e-9 * max(1.0, np.abs(x).max()))
    if rank < d:
        raise SharingError(f"points lie in a {rank}-dimensional affine subspace of R^{d}: the "
                           "degree-1 polynomial is undetermined (e.g. all samples from one "
                           "light and view: drop the constant coordinate)")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    budget = min(max_centers, len(pts))
    seed = _spanning_seed(x)
    rest = np.setdiff1d(np.arange(len(pts)), seed)
    n_rand = max(0, min(initial_centers, budget) - len(seed))
    first = np.zeros(len(pts))
    first[gen.choice(rest, min(n_rand, len(rest)), replace=False)] = 1.0
    first[seed] = 2.0  # the spanning samples first, then the random ones, all kept apart
    order = _pick_block(x, first, np.zeros(len(pts), bool), x[:0], min(budget, int(
        np.count_nonzero(first))), min_separation)
    chosen = np.zeros(len(pts), dtype=bool)
    chosen[order] = True
    history, converged = [], False
    while True:
        model = _solve(pts, vals, order, sc, shift, smoothing)
        err = np.abs(vals - model(pts)).max(axis=1) * w
        history.append((len(order), np.sqrt(np.mean(err ** 2)), err.max()))
        if progress is not None:
            progress(len(order), budget)
        if tol is not None and err.max() <= tol:
            converged = True
            break
        n_new = min(budget - len(order), max(1, int(round((growth - 1.0) * len(order)))))
        if n_new <= 0:
            break
        new = _pick_block(x, err, chosen, x[order], n_new, min_separation,
                          spread * _typical_spacing(x, len(order) + n_new))
        if len(new) == 0:
            converged = True  # every remaining sample is a (near-)duplicate of a centre
            break
        order = np.concatenate([order, new])
        chosen[new] = True
    return RbfFit(model, order, pts, vals, w, np.asarray(history), converged, n_merged,
                  float(smoothing), n_paired)
