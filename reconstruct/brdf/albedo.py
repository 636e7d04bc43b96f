"""Directional albedo of a reflectance model by Monte Carlo (energy checks of fitted models)."""
from __future__ import annotations

import numpy as np

from .analytic import microfacet_distribution
from .base import BRDF


def directional_albedo(model: BRDF, wo, n_samples: int = 100_000,
                       rng: np.random.Generator | int | None = 0, guide_alpha: float = 0.15):
    """a(wo) = integral over the hemisphere of f_r(wi, wo) cos(theta_i) dwi, with its standard error.

    One-sample multiple importance sampling: half the light directions are cosine-weighted,
    half come from GGX(``guide_alpha``) halfway vectors reflected about ``wo`` (the mirror
    region, where glossy lobes live); each sample is weighted by the mixture density, so the
    estimate is unbiased for any model and has low variance for broad and peaked lobes alike.
    By reciprocity a(wo) is also the fraction of light from ``wo`` that is reflected; a <= 1
    for an energy-conserving model.

    Parameters
    ----------
    model : BRDF
        A uniform model (for one texel of a spatially varying one, pass ``model.take([i])``).
    wo : array_like, (3,) or (M, 3)
        Local unit view directions (z = normal), above the surface.
    n_samples : int
        Light directions per view direction (>= 2).
    rng : numpy.random.Generator or int
        Random source or seed.
    guide_alpha : float
        Width of the GGX guide lobe, > 0.

    Returns
    -------
    albedo, stderr : ndarray, (M, 3)
        RGB directional albedo (unitless) and the standard error of each estimate.
    """
    wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
    if not np.allclose(np.linalg.norm(wo, axis=1), 1.0, atol=1e-6) or np.any(wo[:, 2] <= 0):
        raise ValueError("wo must be unit vectors above the surface (z > 0)")
    if n_samples < 2:
        raise ValueError(f"n_samples must be >= 2, got {n_samples}")
    if not guide_alpha > 0:
        raise ValueError(f"guide_alpha must be > 0, got {guide_alpha}")
    rng = np.random.default_rng(rng)
    albedo = np.empty((len(wo), 3))
    stderr = np.empty((len(wo), 3))
    half = n_samples // 2
    for k, v in enumerate(wo):  # a handful of view directions; samples are vectorised
        u1, u2 = rng.random(half), rng.random(half)
        r, phi = np.sqrt(u1), 2 * np.pi * u2
        w_cos = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], axis=1)
        u1, u2 = rng.random(n_samples - half), rng.random(n_samples - half)
        theta = np.arctan(guide_alpha * np.sqrt(u1 / (1 - u1)))
        phi = 2 * np.pi * u2
        h = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)],
                     axis=1)
        w_ggx = 2 * (h @ v)[:, None] * h - v
        wi = np.concatenate([w_cos, w_ggx])
        hh = wi + v
        hh /= np.linalg.norm(hh, axis=1, keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            pdf = 0.5 * np.clip(wi[:, 2], 0, None) / np.pi + 0.5 * (
                microfacet_distribution(hh[:, 2], guide_alpha, "ggx") * hh[:, 2]
                / (4 * np.abs(hh @ v)))
            f = model.evaluate(wi, np.broadcast_to(v, wi.shape))
            x = np.where(wi[:, 2:3] > 0, f * wi[:, 2:3] / pdf[:, None], 0.0)
        albedo[k] = x.mean(axis=0)
        stderr[k] = x.std(axis=0) / np.sqrt(n_samples)
    return albedo, stderr
