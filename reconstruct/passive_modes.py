"""A prior of modes of variation for passive reflectometry, and the solve under it.

Romeiro et al. (2008, Sect. 3) regularise with independent zero-mean Gaussian priors on the
bivariate BRDF's derivatives, and name the alternative: "a joint distribution over the entire
bivariate domain ... in terms of a small number of modes of variation". This is that
alternative, learned in log space: x = log(f + offset) on the (t, s) grid is Gaussian, with the
library's mean, its leading principal components (variance = the library's along each), a
per-node remainder (the library's variance the kept modes do not carry) and a free
log-brightness shift (an albedo outside the library's range costs nothing).

Why: one image under a real probe leaves a third of the nodes unobserved (retro, grazing, the
exact mirror direction; ``Adequacy.constrained``). A derivative prior extrapolates them flat;
the modes carry the library's correlations, so what the image sees of the highlight and the
diffuse level sets the Fresnel rise and the dark tail too. In log space a metal's 1000:1
range is a smooth surface, and the errors Eq. 1 measures are relative ones. The remainder
matters: without it every estimate lies in the span of the modes, which does not hold a
material's own reduction (yellow-paint's projection onto 40 modes of the other 99 explains its
image 6x worse than the reduction does), so the fit bends the modes to explain what lies
outside their span and moves the nodes the image does not see with them (docs/zoo.md).

The solve is a maximum a posteriori estimate, Levenberg-Marquardt on the node values x, with
the data term through the normal equations (G = A^T A, h = A^T b) and the prior as its
precision matrix (Woodbury: modes + remainder, the shift's direction left free), so an
iteration costs one Cholesky factorisation of the node count, not O(pixels).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from .passive_lighting import check_grid
from .passive_prior import library_tables

#: Offset of the log mapping, 1/sr: far below a diffuse MERL albedo (0.01-0.3 1/sr), above the
#: dark tails near the horizon (1e-6 to 1e-4, where MERL has no data and the images no light),
#: which it folds together.
LOG_OFFSET = 1e-3
#: Modes kept: onto 40 modes of the other 99 a MERL material's own reduction projects to within
#: 1-4 points of its Eq. 1 error on six of ten (20 modes: 1.4-3.4x its error; docs/zoo.md).
N_MODES = 40
#: The remainder's per-node variance is floored at this fraction of its mean, so that a node
#: every library member agrees on is held strongly, not infinitely.
REMAINDER_FLOOR = 1e-2
#: ... and at this fraction of the library's mean per-node variance. Where the kept modes span
#: the library exactly (a few Lambertians), the remainder is ~1e-31: the precision's Woodbury
#: form then loses the free shift to rounding, and a recovered albedo depended on the CPU's last
#: bits. MERL's smallest remainder is 2e-4 of its mean variance, far above this.
SPAN_FLOOR = 1e-6


@dataclass(frozen=True, eq=False)
class ModesPrior:
    """Gaussian prior on x = log(f + ``offset``) over the flattened (t, s) grid (``i * n_s +
    j``): x = ``mean`` + shift + c @ ``modes`` + e, c_k ~ N(0, ``variances[k]``), e_i ~ N(0,
    ``residual_variances[i]``) independent per node, shift free.

    Attributes
    ----------
    mean : ndarray (n_t n_s,)
        Library mean of log(f + offset), f in 1/sr.
    modes : ndarray (k, n_t n_s)
        Orthonormal rows: the library's principal directions, by decreasing variance.
    variances : ndarray (k,)
        The library's variance along each mode.
    residual_variances : ndarray (n_t n_s,)
        Per node, the library's variance left after the kept modes (> 0).
    grid : (int, int)
        (n_t, n_s).
    offset : float
        1/sr.
    name : str
    n_brdfs : int
        Library size.
    """

    mean: np.ndarray
    modes: np.ndarray
    variances: np.ndarray
    residual_variances: np.ndarray
    grid: tuple
    offset: float = LOG_OFFSET
    name: str = "modes"
    n_brdfs: int = 0

    def values(self, coefficients, shift: float = 0.0) -> np.ndarray:
        """f (n_t n_s,) in 1/sr for coefficients (k,) and a log-brightness ``shift`` (no
        remainder); may dip to -offset (clip for a BRDF)."""
        return np.exp(self.mean + shift + coefficients @ self.modes) - self.offset

    def _woodbury(self):
        """(shift and modes as rows V (1 + k, n), 1 / remainder D^-1 (n,), M = diag(1 / var) +
        V D^-1 V^T with the shift's 1 / var = 0): the pieces of the precision and of the
        split of a deviation into shift, coefficients and remainder."""
        V = np.vstack([np.ones(len(self.mean)), self.modes])
        d_inv = 1.0 / self.residual_variances
        M = np.diag(np.concatenate([[0.0], 1.0 / self.variances])) + (V * d_inv) @ V.T
        return V, d_inv, M

    def precision(self) -> np.ndarray:
        """(n, n) inverse covariance of x - mean with the shift free (its direction, all
        ones, costs nothing)."""
        V, d_inv, M = self._woodbury()
        Q = np.diag(d_inv) - (d_inv[:, None] * V.T) @ np.linalg.solve(M, V * d_inv)
        return (Q + Q.T) / 2

    def split(self, x) -> tuple[float, np.ndarray]:
        """The shift and coefficients (k,) of the most probable split of log values ``x``
        (n,) into mean + shift + c @ modes + remainder."""
        V, d_inv, M = self._woodbury()
        z = np.linalg.solve(M, V @ (d_inv * (np.asarray(x, float) - self.mean)))
        return float(z[0]), z[1:]


def learn_modes(brdfs, grid=(32, 32), *, n_modes: int = N_MODES, offset: float = LOG_OFFSET,
                name: str = "modes") -> ModesPrior:
    """Learn a ``ModesPrior`` from a BRDF library (each colour channel a sample).

    Parameters
    ----------
    brdfs : sequence of BRDF or Bivariate
        Isotropic materials (e.g. MERL), reduced as ``passive_prior.library_tables`` does.
    grid : (int, int)
    n_modes : int
        Principal components kept (at most samples - 1).
    offset : float
        Of the log mapping, 1/sr (> 0).
    name : str

    Raises
    ------
    ValueError
        Fewer than two materials, something not a BRDF, a bad ``n_modes`` or ``offset``.
    """
    if not (isinstance(offset, (int, float)) and offset > 0):
        raise ValueError(f"offset must be a number > 0 (1/sr), got {offset!r}")
    tables = library_tables(brdfs, grid)
    x = np.log(np.moveaxis(tables, -1, 1).reshape(3 * len(tables), -1) + offset)
    if not (isinstance(n_modes, (int, np.integer)) and 1 <= n_modes < len(x)):
        raise ValueError(f"n_modes must be an int in [1, {len(x) - 1}] for {len(tables)} "
                         f"materials (3 channels each), got {n_modes!r}")
    mean = x.mean(axis=0)
    # principal axes from the (samples x samples) Gram matrix: far smaller than nodes^2
    var, u = np.linalg.eigh((x - mean) @ (x - mean).T)
    var, u = var[::-1][:n_modes], u[:, ::-1][:, :n_modes]
    modes = u.T @ (x - mean) / np.sqrt(var)[:, None]
    rest = (x - mean) - ((x - mean) @ modes.T) @ modes
    rest_var = np.sum(rest ** 2, axis=0) / (len(x) - 1)
    node_var = np.sum((x - mean) ** 2, axis=0) / (len(x) - 1)
    rest_var = np.maximum(rest_var, max(REMAINDER_FLOOR * np.mean(rest_var),
                                        SPAN_FLOOR * np.mean(node_var), 1e-300))
    return ModesPrior(mean, modes, var / (len(x) - 1), rest_var, check_grid(grid), float(offset),
                      name, len(tables))


@dataclass(frozen=True)
class ModesSolution:
    """One channel's MAP estimate: f (n_t n_s,) in 1/sr (>= 0), the shift and coefficients (k,)
    of its most probable split (``ModesPrior.split``), and whether the iteration met its
    tolerance."""

    f: np.ndarray
    coefficients: np.ndarray
    shift: float
    converged: bool


def solve_modes(prior: ModesPrior, G, h, bb: float, lam: float, *, max_iter: int = 100,
                precision=None, start=None) -> ModesSolution:
    """argmin over x of (f^T G f - 2 h^T f + bb) / bb + lam (x - mean)^T Q (x - mean) with
    f = exp(x) - offset and Q = ``prior.precision()`` (pass it as ``precision`` to reuse it
    across channels): the posterior mode for a data term ||A f - b||^2 given as G = A^T A
    (n, n), h = A^T b (n,), bb = b^T b, with noise variance lam bb.

    Levenberg-Marquardt (Gauss-Newton steps, damping adapted to the cost) from the library
    mean at the brightness that fits the data best, or from ``start`` (n,) f values, 1/sr
    (e.g. an earlier solve's).
    """
    Q = lam * (prior.precision() if precision is None else precision)
    mean, off = prior.mean, prior.offset

    def cost(x):
        f = np.exp(x) - off
        y = x - mean
        return (f @ (G @ f) - 2 * h @ f + bb) / bb + y @ (Q @ y), f

    if start is None:
        f0 = np.exp(mean) - off
        x = mean + np.log(max(h @ f0 / max(f0 @ G @ f0, 1e-300), 1e-12))
    else:
        x = np.log(np.maximum(np.asarray(start, dtype=np.float64), 0.0) + off)
    c0, f = cost(x)
    damp, converged = 1e-3, False
    for _ in range(max_iter):
        g = f + off                                             # d f / d x
        grad = g * (G @ f - h) / bb + Q @ (x - mean)
        H = g[:, None] * G * g[None, :] / bb + Q
        scale = np.diag(H) + 1e-12
        while damp < 1e8:
            try:
                step = -cho_solve(cho_factor(H + damp * np.diag(scale)), grad)
            except np.linalg.LinAlgError:
                damp *= 4
                continue
            c1, f1 = cost(x + step)
            if c1 <= c0:
                break
            damp *= 4
        else:                   # no step lowers the cost: a minimum to machine precision
            converged = True
            break
        gain = c0 - c1
        x, c0, f, damp = x + step, c1, f1, max(damp / 4, 1e-9)
        if gain <= 1e-10 * max(c0, 1e-300):
            converged = True
            break
    shift, coefficients = prior.split(x)
    return ModesSolution(np.maximum(f, 0.0), coefficients, shift, converged)
