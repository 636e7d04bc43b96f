"""BRDF models backed by RBF interpolants: homogeneous (u, v, w) and spatially varying
(x, y, u, v[, w]).

Both are ``reconstruct.brdf.BRDF`` models, so the renderer, ``reconstruct.distant`` and the
report use them unchanged. Directions are local unit vectors (normal = +z); the angular
coordinates are Zickler et al.'s (u, v, w) of Eq. 1 (``reconstruct.coords.uvw_from_directions``).
A linear RBF can undershoot below zero between samples; the models clamp f_r at 0. A homogeneous
model may interpolate log(f_r + offset) instead of f_r (``RbfBRDF.log_offset``, see
``fits.fit_isotropic``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..brdf.base import BRDF, rgb
from ..coords import uvw_from_directions
from .rbf import RbfModel, SharingError


@dataclass(frozen=True, eq=False)
class RbfBRDF(BRDF):
    """A homogeneous isotropic BRDF f_r(u, v, w) in 1/sr (Zickler et al. Eq. 5).

    Parameters
    ----------
    model : RbfModel
        Interpolant over (u, v, w), D = 3, with 1 (grey) or 3 (RGB) channels.
    log_offset : float, optional
        When set, the interpolant is of g = log(f_r + log_offset) (1/sr inside the log), and
        f_r = exp(g) - log_offset; None: of f_r itself.
    """

    model: RbfModel
    log_offset: float | None = None

    def __post_init__(self):
        if self.model.dim != 3:
            raise SharingError(f"model must be 3-D (u, v, w), got {self.model.dim}-D")
        if self.log_offset is not None and not self.log_offset > 0:
            raise SharingError(f"log_offset must be > 0 or None, got {self.log_offset!r}")

    def _evaluate(self, wi, wo):
        g = self.model(uvw_from_directions(wi, wo))
        if self.log_offset is not None:
            g = np.exp(np.minimum(g, 700.0)) - self.log_offset
        return np.maximum(g, 0.0)

    def take(self, index) -> "RbfBRDF":
        return self


@dataclass(frozen=True, eq=False)
class SpatialRbfBRDF(BRDF):
    """A spatially varying BRDF a(x) d(x, y, u, v[, w]) for N surface points (Eqs. 6-8).

    Parameters
    ----------
    model : RbfModel
        Interpolant over (x, y, u, v, w) (D = 5) or, for the single-image case of Eq. 8,
        (x, y, u, v) (D = 4); 1 or 3 channels.
    xy : ndarray, (N, 2) or (2,)
        Surface coordinates of the points the BRDF describes (row i goes with sample row i of
        ``evaluate``), in the units the model was fitted in.
    albedo : ndarray, (N, 3), (3,) or None
        Multiplicative texture a(x) (the dichromatic model's diffuse albedo); None = 1.
    """

    model: RbfModel
    xy: object
    albedo: object = None

    def __post_init__(self):
        if self.model.dim not in (4, 5):
            raise SharingError(f"model must be 4-D or 5-D, got {self.model.dim}-D")
        xy = np.asarray(self.xy, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(xy)):
            raise SharingError("xy contains NaN or infinite values")
        object.__setattr__(self, "xy", xy)

    def _evaluate(self, wi, wo):
        xy = np.broadcast_to(self.xy, (len(wi), 2))
        q = np.hstack([xy, uvw_from_directions(wi, wo)[:, :self.model.dim - 2]])
        f = np.maximum(self.model(q), 0.0)
        return f if self.albedo is None else f * rgb(self.albedo)

    def take(self, index) -> "SpatialRbfBRDF":
        """The BRDF of the points ``index`` (per-point xy and albedo indexed; shared ones kept)."""
        xy = self.xy[index] if len(self.xy) > 1 else self.xy
        albedo = self.albedo
        if albedo is not None and np.ndim(albedo) == 2 and len(albedo) > 1:
            albedo = np.asarray(albedo)[index]
        return SpatialRbfBRDF(self.model, xy, albedo)
