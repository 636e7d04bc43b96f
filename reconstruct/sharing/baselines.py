"""Baselines for the reflectance-sharing comparisons (Zickler et al. 2005, Figs. 2-4 and 6).

- :func:`fit_analytic`: any analytic ``BRDF`` whose parameters are a flat vector, fitted by
  ``scipy.optimize.least_squares`` in the radiance domain (residual (f - f_model) cos theta_i,
  the same weighting as the RBF's greedy residual); :func:`fit_ward` is the isotropic Ward
  instance. (The multi-lobe Lafortune baseline is ``reconstruct.lensch.fit_lafortune``.)
- :func:`fit_per_point`: the "no sharing" method of Fig. 6: a separate angular interpolant at
  each surface point from that point's own samples only (linear RBF over (u, v, w) with a
  constant term), all points solved as one batch of small systems.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.optimize import least_squares

from ..brdf import BRDF, Ward
from ..coords import uvw_from_directions
from .fits import MIN_COS, _samples, _values, _weight
from .rbf import SharingError


@dataclass(frozen=True, eq=False)
class AnalyticFit:
    """Result of :func:`fit_analytic`: the model, its parameter vector, the weighted RMS
    radiance residual (f_r cos theta_i units) and the optimizer's status."""

    brdf: BRDF
    params: np.ndarray
    rms: float
    success: bool
    message: str


def fit_analytic(make: Callable[[np.ndarray], BRDF], x0, wi, wo, brdf, *, bounds=(-np.inf, np.inf),
                 weight=None, valid=None, min_cos: float = MIN_COS) -> AnalyticFit:
    """Least-squares fit of an analytic model ``make(params)`` to f_r samples.

    Parameters
    ----------
    make : callable
        Parameter vector (P,) -> BRDF.
    x0 : array_like, (P,)
        Start.
    wi, wo, brdf, weight, valid, min_cos
        As :func:`reconstruct.sharing.fit_isotropic` (same sample selection).
    bounds : pair of float or (P,) arrays
        ``least_squares`` bounds.
    """
    s = _samples(wi, wo, valid, min_cos)
    f = _values("brdf", brdf, len(s.wi), s.keep, channels=(3,))[s.keep]
    w = np.sqrt(_weight(s, weight)[s.keep])[:, None]
    a, b = s.wi[s.keep], s.wo[s.keep]
    target = f * w

    def residual(p):
        return (make(p).evaluate(a, b) * w - target).ravel()

    res = least_squares(residual, np.asarray(x0, dtype=np.float64), bounds=bounds, x_scale="jac")
    rms = float(np.sqrt(np.mean(res.fun ** 2)))
    return AnalyticFit(make(res.x), res.x, rms, bool(res.success), str(res.message))


def fit_ward(wi, wo, brdf, *, alphas=(0.05, 0.15, 0.4), **kwargs) -> AnalyticFit:
    """Isotropic Ward (Ward 1992): RGB rho_d, grey rho_s, alpha; ``kwargs`` as :func:`fit_analytic`.

    One start per roughness in ``alphas`` (the fit has local minima), the lowest residual wins;
    rho_d starts at pi x the low quartile of f_r, rho_s at 0.05.
    """
    f = np.asarray(brdf, dtype=np.float64)
    good = np.isfinite(f).all(axis=-1) if f.ndim == 2 else np.zeros(0, bool)
    rho_d0 = np.pi * np.percentile(f[good], 25, axis=0) if good.any() else np.full(3, 0.3)

    def make(p):
        return Ward(rho_d=p[:3], rho_s=p[3], alpha=p[4])

    bounds = ([0, 0, 0, 0, 0.01], [np.inf, np.inf, np.inf, np.inf, 1.0])
    fits = [fit_analytic(make, np.concatenate([np.clip(rho_d0, 0.0, 1.0), [0.05, a]]), wi, wo,
                         brdf, bounds=bounds, **kwargs) for a in alphas]
    return min(fits, key=lambda r: r.rms)


@dataclass(frozen=True, eq=False)
class PerPointInterpolant:
    """Per-point angular interpolants (no sharing): for point t,
    f_t(q) = c_t + sum_j lambda_tj |M (q - q_tj)| over that point's K_t samples (padded to K).

    Attributes
    ----------
    centers : ndarray, (T, K, 3)
        (u, v, w) of each point's samples (padding rows are far away and carry lambda = 0).
    coefficients : ndarray, (T, K, 3)
    constant : ndarray, (T, 3)
    scale : ndarray, (3,)
    """

    centers: np.ndarray
    coefficients: np.ndarray
    constant: np.ndarray
    scale: np.ndarray

    def __call__(self, point, wi, wo) -> np.ndarray:
        """f_r (N, 3) at local directions (N, 3) of surface points ``point`` (N,) (clamped >= 0)."""
        q = uvw_from_directions(wi, wo) * self.scale
        dist = np.linalg.norm(self.centers[point] * self.scale - q[:, None], axis=2)  # (N, K)
        f = np.einsum("nk,nkc->nc", dist, self.coefficients[point]) + self.constant[point]
        return np.maximum(f, 0.0)


def fit_per_point(point, wi, wo, brdf, *, n_points: int | None = None, m_w: float = 0.5,
                  valid=None, min_cos: float = MIN_COS) -> PerPointInterpolant:
    """The "no sharing" baseline (Fig. 6): interpolate each point's own samples in (u, v, w).

    Parameters
    ----------
    point : array_like of int, (S,)
        Surface point of each sample.
    wi, wo, brdf, valid, min_cos
        As :func:`reconstruct.sharing.fit_isotropic`.
    n_points : int, optional
        Number of points T (default ``point.max() + 1``); a point without samples is black.
    m_w : float
        Scale of w, as in the sharing fits.
    """
    s = _samples(wi, wo, valid, min_cos)
    f = _values("brdf", brdf, len(s.wi), s.keep, channels=(3,))
    point = np.asarray(point)
    if point.shape != (len(s.wi),) or not np.issubdtype(point.dtype, np.integer):
        raise SharingError(f"point must be integers of shape ({len(s.wi)},)")
    t_count = int(point.max()) + 1 if n_points is None else int(n_points)
    k = s.keep
    pt, q, f = point[k], uvw_from_directions(s.wi[k], s.wo[k]), f[k]
    order = np.argsort(pt, kind="stable")
    pt, q, f = pt[order], q[order], f[order]
    counts = np.bincount(pt, minlength=t_count)
    kmax = max(1, int(counts.max()))
    slot = np.arange(len(pt)) - np.concatenate([[0], np.cumsum(counts)[:-1]])[pt]
    scale = np.array([1.0, 1.0, m_w])
    centers = np.full((t_count, kmax, 3), 1e3)  # padding: far from every query
    centers[pt, slot] = q
    vals = np.zeros((t_count, kmax, 3))
    vals[pt, slot] = f
    real = np.zeros((t_count, kmax), bool)
    real[pt, slot] = True
    x = centers * scale
    psi = np.linalg.norm(x[:, :, None] - x[:, None], axis=3)
    # padded rows become identity rows (lambda = 0) so every system has the same size
    psi = np.where(real[:, :, None] & real[:, None], psi, 0.0)
    psi[:, np.arange(kmax), np.arange(kmax)] = np.where(real, 0.0, 1.0)
    a = np.zeros((t_count, kmax + 1, kmax + 1))
    a[:, :kmax, :kmax] = psi
    a[:, :kmax, kmax] = a[:, kmax, :kmax] = real
    a[counts == 0, kmax, kmax] = 1.0  # no samples: constant 0
    rhs = np.zeros((t_count, kmax + 1, 3))
    rhs[:, :kmax] = vals
    sol = np.linalg.solve(a, rhs)
    return PerPointInterpolant(centers, sol[:, :kmax], sol[:, kmax], scale)
