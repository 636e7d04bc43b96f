"""A prior of modes of variation for passive reflectometry, and the solve under it.

Romeiro et al. (2008, Sect. 3) regularise with independent zero-mean Gaussian priors on the
bivariate BRDF's derivatives, and name the alternative: "a joint distribution over the entire
bivariate domain ... in terms of a small number of modes of variation". This is that
alternative, learned in log space: x = log(f + offset) on the (t, s) grid is Gaussian, with the
library's mean and its leading principal components (variance = the library's along each),
and a free log-brightness shift (an albedo outside the library's range costs nothing).

Why: one image under a real probe leaves a third of the nodes unobserved (retro, grazing, the
exact mirror direction; ``Adequacy.constrained``). A derivative prior extrapolates them flat;
the modes carry the library's correlations, so what the image sees of the highlight and the
diffuse level sets the Fresnel rise and the dark tail too. In log space a metal's 1000:1
range is a smooth surface, and the errors Eq. 1 measures are relative ones.

The solve is a maximum a posteriori estimate, Levenberg-Marquardt on the coefficients, with
the data term through the normal equations (G = A^T A, h = A^T b), so an iteration costs
O(modes x nodes^2), not O(pixels).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .passive_lighting import check_grid
from .passive_prior import library_tables

#: Offset of the log mapping, 1/sr: far below a diffuse MERL albedo (0.01-0.3 1/sr), above the
#: dark tails near the horizon (1e-6 to 1e-4, where MERL has no data and the images no light),
#: which it folds together.
LOG_OFFSET = 1e-3
#: Modes kept: onto 40 modes of the other 99 a MERL material's own reduction projects to within
#: 1-4 points of its Eq. 1 error on six of ten (20 modes: 1.4-3.4x its error; docs/zoo.md).
N_MODES = 40


@dataclass(frozen=True, eq=False)
class ModesPrior:
    """Gaussian prior on x = log(f + ``offset``) over the flattened (t, s) grid (``i * n_s +
    j``): x = ``mean`` + shift + c @ ``modes``, c_k ~ N(0, ``variances[k]``), shift free.

    Attributes
    ----------
    mean : ndarray (n_t n_s,)
        Library mean of log(f + offset), f in 1/sr.
    modes : ndarray (k, n_t n_s)
        Orthonormal rows: the library's principal directions, by decreasing variance.
    variances : ndarray (k,)
        The library's variance along each mode.
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
    grid: tuple
    offset: float = LOG_OFFSET
    name: str = "modes"
    n_brdfs: int = 0

    def values(self, coefficients, shift: float = 0.0) -> np.ndarray:
        """f (n_t n_s,) in 1/sr for coefficients (k,) and a log-brightness ``shift``; may dip
        to -offset (clip for a BRDF)."""
        return np.exp(self.mean + shift + coefficients @ self.modes) - self.offset


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
    return ModesPrior(mean, modes, var / (len(x) - 1), check_grid(grid), float(offset), name,
                      len(tables))


@dataclass(frozen=True)
class ModesSolution:
    """One channel's MAP estimate: f (n_t n_s,) in 1/sr (>= 0), its coefficients (k,), the
    log-brightness shift, and whether the iteration met its tolerance."""

    f: np.ndarray
    coefficients: np.ndarray
    shift: float
    converged: bool


def solve_modes(prior: ModesPrior, G, h, bb: float, lam: float, *, start=None,
                max_iter: int = 100) -> ModesSolution:
    """argmin over (c, shift) of (f^T G f - 2 h^T f + bb) / bb + lam sum c_k^2 / var_k with
    f = ``prior.values(c, shift)``: the posterior mode for a data term ||A f - b||^2 given as
    G = A^T A (n, n), h = A^T b (n,), bb = b^T b, with noise variance lam bb.

    Levenberg-Marquardt (Gauss-Newton steps, damping adapted to the cost), from ``start``
    (a ``ModesSolution``, e.g. the solution for a neighbouring ``lam``) or from the library
    mean at the brightness that fits the data best.
    """
    P = np.concatenate([[0.0], lam / prior.variances])         # the shift is not penalised
    V = np.vstack([np.ones(len(prior.mean)), prior.modes])     # (1 + k, n)

    def cost(z):
        f = np.exp(prior.mean + z @ V) - prior.offset
        return (f @ (G @ f) - 2 * h @ f + bb) / bb + z @ (P * z), f

    if start is None:
        f0 = np.exp(prior.mean) - prior.offset
        z = np.zeros(len(V))
        z[0] = np.log(max(h @ f0 / max(f0 @ G @ f0, 1e-300), 1e-12))
    else:
        z = np.concatenate([[start.shift], start.coefficients])
    c0, f = cost(z)
    damp, converged = 1e-3, False
    for _ in range(max_iter):
        W = V * (f + prior.offset)                              # d f / d z, (1 + k, n)
        grad = W @ (G @ f - h) / bb + P * z
        H = W @ G @ W.T / bb + np.diag(P)
        while damp < 1e8:
            step = np.linalg.solve(H + damp * np.diag(np.diag(H) + 1e-12), -grad)
            c1, f1 = cost(z + step)
            if c1 <= c0:
                break
            damp *= 4
        else:                   # no step lowers the cost: a minimum to machine precision
            converged = True
            break
        gain = c0 - c1
        z, c0, f, damp = z + step, c1, f1, max(damp / 4, 1e-9)
        if gain <= 1e-10 * max(c0, 1e-300):
            converged = True
            break
    return ModesSolution(np.maximum(f, 0.0), z[1:], float(z[0]), converged)
