"""A batched Levenberg-Marquardt solver: many small independent least-squares problems at once.

The item axis comes first (parameters (B, P), residuals (B, M), Jacobians (B, M, P)); one
iteration solves a (B, P, P) stack with ``np.linalg.solve``, each item with its own damping, and
only items still iterating are evaluated. Used for the per-channel Lafortune fits (B = 3) and the
per-texel normal fits (B = number of texels).
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from typing import Callable

import numpy as np

#: fun(x, items) -> (residual (b, M), jacobian (b, M, P)) for the items' parameters x (b, P).
ResidualFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class LMResult:
    """Outcome of :func:`levenberg_marquardt` per item.

    Attributes
    ----------
    x : ndarray (B, P)
        Parameters at the end.
    cost : ndarray (B,)
        0.5 * sum of squared residuals at ``x``.
    jac : ndarray (B, M, P) or None
        Jacobian at ``x`` (for covariances; ``fun`` evaluated there once more); None when
        ``keep_jac`` is False.
    converged : ndarray (B,) bool
        The relative cost decrease or the step fell below tolerance (False: iteration cap).
    n_iter : ndarray (B,) int
        Iterations used per item.
    """

    x: np.ndarray
    cost: np.ndarray
    jac: np.ndarray | None
    converged: np.ndarray
    n_iter: np.ndarray


def levenberg_marquardt(fun: ResidualFn, x0: np.ndarray, *, lower=None, upper=None,
                        max_iter: int = 100, ftol: float = 1e-10, xtol: float = 1e-10,
                        mu0: float = 1e-3, keep_jac: bool = True,
                        stall: tuple[int, float] | None = None) -> LMResult:
    """Minimise 0.5 * |r_b(x_b)|^2 for every item b independently (Marquardt's scaled damping).

    Parameters
    ----------
    fun : callable
        ``fun(x, items)`` with ``x`` (b, P) the parameters of ``items`` (b,) int indices into
        the batch, returning residuals (b, M) and their Jacobian (b, M, P).
    x0 : ndarray (B, P)
        Start.
    lower, upper : array broadcastable to (B, P), optional
        Box bounds; steps are clipped into the box (projected LM).
    max_iter : int
        Cap on iterations (each evaluates ``fun`` once on the items still iterating).
    ftol, xtol : float
        An item stops when an accepted step lowers its cost by less than ``ftol`` * cost or moves
        it by less than ``xtol`` * (|x| + xtol), or when its damping exceeds 1e12 (no descent).
    mu0 : float
        Initial damping relative to diag(J^T J).
    keep_jac : bool
        Return the Jacobian at ``x``; False saves one evaluation of ``fun``.
    stall : (int, float), optional
        ``(window, rtol)``: an item also stops (counted converged) when its cost fell by less
        than ``rtol`` x its cost over its last ``window`` iterations, however small each step's
        gain: two-lobe fits crawl along flat valleys (lobes trading energy), ``ftol`` never met.
    """
    x = np.array(x0, dtype=np.float64, copy=True)
    B, P = x.shape
    lo = np.broadcast_to(-np.inf if lower is None else np.asarray(lower, float), (B, P))
    hi = np.broadcast_to(np.inf if upper is None else np.asarray(upper, float), (B, P))
    x = np.clip(x, lo, hi)
    everyone = np.arange(B)
    r, J = fun(x, everyone)
    cost = 0.5 * np.einsum("bm,bm->b", r, r)
    mu = np.full(B, float(mu0))
    converged = np.zeros(B, bool)
    n_iter = np.zeros(B, np.int64)
    active = everyone.copy()
    rA, JA = r, J   # updated in place below: fun returns fresh arrays
    window = 0 if stall is None else int(stall[0])
    ring = np.repeat(cost[:, None], max(window, 1), axis=1)   # cost after iteration k at k % window
    for it in range(1, max_iter + 1):
        if len(active) == 0:
            break
        JT = JA.transpose(0, 2, 1)
        A = JT @ JA  # batched BLAS: much faster than einsum for long residual vectors
        g = (JT @ rA[..., None])[..., 0]
        d = np.einsum("bpp->bp", A)
        d = np.maximum(d, 1e-12 * np.maximum(d.max(axis=1, keepdims=True), 1e-300))
        M = A + (mu[active, None] * d)[:, :, None] * np.eye(P)
        step = -np.linalg.solve(M, g[..., None])[..., 0]
        x_new = np.clip(x[active] + step, lo[active], hi[active])
        r_new, J_new = fun(x_new, active)
        c_new = 0.5 * np.einsum("bm,bm->b", r_new, r_new)
        n_iter[active] += 1
        better = np.isfinite(c_new) & (c_new < cost[active])
        moved = np.abs(x_new - x[active])
        small_step = np.all(moved <= xtol * (np.abs(x[active]) + xtol), axis=1)
        small_gain = better & (cost[active] - c_new <= ftol * cost[active])
        acc = active[better]
        x[acc], cost[acc] = x_new[better], c_new[better]
        mu[acc] = np.maximum(mu[acc] * 0.3, 1e-12)
        rej = active[~better]
        mu[rej] *= 10.0
        done = small_gain | small_step | (mu[active] > 1e12)
        if window:   # active items iterate in step: iteration ``it`` for all of them
            done |= (it >= window) & (cost[active] > (1.0 - stall[1]) * ring[active, it % window])
            ring[active, it % window] = cost[active]
        converged[active[done]] = True
        keep = ~done
        # the next iteration linearises at the current point of the items still iterating
        if better.all():
            rA, JA = r_new, J_new
        else:
            rA[better], JA[better] = r_new[better], J_new[better]
        if not keep.all():
            rA, JA = rA[keep], JA[keep]
        active = active[keep]
    # the Jacobian at x evaluated once more rather than copied at every accepted step
    jac = fun(x, everyone)[1] if keep_jac else None
    return LMResult(x=x, cost=cost, jac=jac, converged=converged, n_iter=n_iter)


def covariance(jac: np.ndarray, cost: np.ndarray, n_residuals) -> np.ndarray:
    """Parameter covariance s^2 (J^T J)^-1 with s^2 = 2 cost / (M - P), per item.

    ``jac`` (B, M, P), ``cost`` (B,), ``n_residuals`` (B,) or int: the residuals that count (M).
    A parameter the data does not constrain gets a huge variance (a tiny ridge keeps the inverse
    finite), never a misleading zero.
    """
    A = jac.transpose(0, 2, 1) @ jac
    P = A.shape[-1]
    dof = np.maximum(np.asarray(n_residuals, float) - P, 1.0)
    s2 = 2.0 * cost / dof
    ridge = 1e-12 * np.maximum(np.einsum("bpp->b", A), 1e-300)
    inv = np.linalg.inv(A + ridge[:, None, None] * np.eye(P))
    return s2[:, None, None] * inv


def nnls_batched(G: np.ndarray, h: np.ndarray, rr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact non-negative least squares for many small problems at once.

    Minimises |A t - r|^2 = rr - 2 h.t + t.G.t over t >= 0 per item, given the normal equations
    G = A^T A (n, B, B), h = A^T r (n, B) and rr = r.r (n,). The optimum is the unconstrained
    solution on its own support, so solving on every support (2^B - 1 of them, B small) and
    keeping the best feasible one is exact, and it is vectorised over items (no per-item solver).

    Returns the weights (n, B) and the residual sum of squares (n,).
    """
    n, B = h.shape
    best_t = np.zeros((n, B))
    best_cost = rr.copy()
    scale = np.maximum(np.einsum("nbb->n", G) / B, 1e-300)
    for k in range(1, B + 1):
        for support in combinations(range(B), k):
            idx = np.array(support)
            Gs = G[:, idx[:, None], idx[None, :]] + (1e-10 * scale)[:, None, None] * np.eye(k)
            ts = np.linalg.solve(Gs, h[:, idx, None])[..., 0]
            cost = rr - np.einsum("nb,nb->n", ts, h[:, idx])
            better = np.all(ts >= 0, axis=1) & (cost < best_cost)
            best_cost[better] = cost[better]
            best_t[better] = 0.0
            best_t[np.ix_(better, idx)] = ts[better]
    return best_t, np.maximum(best_cost, 0.0)
