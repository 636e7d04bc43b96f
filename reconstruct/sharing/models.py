"""BRDF models backed by RBF interpolants: homogeneous (u, v, w) and spatially varying
(x, y, u, v[, w]).

Both are ``reconstruct.brdf.BRDF`` models, so the renderer, ``reconstruct.distant`` and the
report use them unchanged. Directions are local unit vectors (normal = +z); the angular
coordinates are Zickler et al.'s (u, v, w) of Eq. 1 (``reconstruct.coords.uvw_from_directions``).
A linear RBF can undershoot below zero between samples; the models clamp f_r at 0. A homogeneous
model may interpolate log(f_r + offset) instead of f_r (``RbfBRDF.log_offset``) and over the
polar points of :func:`polar_points` instead of (u, v, w) (``RbfBRDF.angular_weight``), and,
when it is not reciprocal, f_r cos theta_i / (cos theta_i + horizon) (``RbfBRDF.horizon``), see
``isotropic.fit_isotropic``; a spatial model likewise over (x, y) and the polar points
(``SpatialRbfBRDF.angular_weight``, ``fits.fit_spatial``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..brdf.base import BRDF, rgb
from ..coords import halfway_difference, uvw_from_directions
from .rbf import RbfModel, SharingError


#: Distances around the (u, v) disc (phi_d at fixed theta_h) weigh this much of those along it
#: (:func:`polar_points`; ``isotropic`` module docstring). Held-out medians on the zoo at
#: 0.25 / 0.1 / 0.03: phenolic 5.9 / 4.7 / 4.8 %, gold-metallic-paint 1.4 (0.1) / 2.1 (0.03) %,
#: the others flat.
ANGULAR_WEIGHT = 0.1
#: Weight of the un-doubled phi_d disc that lets a fit tell a pair from its swap
#: (:func:`with_asymmetry`): the polar form's own angular weight, the un-doubled disc scaled as
#: the doubled one. Held-out medians at 0.03 / 0.1 / 0.3: vinyl
#: 2.94 / 2.73 / 3.12 %, matte paint 2.98 / 2.75 % at 0.03 / 0.1 (docs/zoo.md).
ASYMMETRY_WEIGHT = ANGULAR_WEIGHT


def _check_angular_weight(angular_weight) -> None:
    if angular_weight is not None and not 0.0 < angular_weight < 1.0:
        raise SharingError(f"angular_weight must be in (0, 1) or None, got {angular_weight!r}")


def angular_points(uvw: np.ndarray, angular_weight: float | None, with_w: bool = True) -> np.ndarray:
    """The angular coordinates an RBF is fitted over: (u, v, w) (N, 3), or their
    :func:`polar_points` (N, 4) when ``angular_weight`` is set; without the last column (w) when
    not ``with_w`` (one theta_d: Eq. 8)."""
    points = uvw if angular_weight is None else polar_points(uvw, angular_weight)
    return points if with_w else points[:, :-1]


def polar_points(uvw: np.ndarray, angular_weight: float) -> np.ndarray:
    """(u, v, w) (N, 3) -> (a u, a v, sqrt(1 - a^2) r, w) (N, 4), r = sqrt(u^2 + v^2) = sin theta_h.

    The (u, v) disc embedded on a cone in 3-D: a step along theta_h keeps its length, a step
    around the disc (phi_d at fixed theta_h) is scaled by ``a`` = ``angular_weight`` in (0, 1).
    A linear RBF over these points is the paper's M of Eq. 4 written in polar form: distances in
    phi_d weigh ``a`` x those in sin theta_h (``isotropic`` module docstring for why).
    """
    a = float(angular_weight)
    r = np.hypot(uvw[:, 0], uvw[:, 1])
    return np.column_stack([a * uvw[:, 0], a * uvw[:, 1], np.sqrt(1.0 - a * a) * r, uvw[:, 2]])


def with_asymmetry(points: np.ndarray, wi, wo, weight: float) -> np.ndarray:
    """``points`` (N, D), w last, with two columns inserted before w: ``weight`` sin theta_h
    (cos phi_d, sin phi_d), phi_d not doubled. Swapping wi and wo turns phi_d by pi, so a pair
    and its swap, one point in (u, v, w), lie 2 ``weight`` sin theta_h apart: a fit can follow
    data that are not reciprocal (``reciprocity``) and still pool the two orderings near the
    peak, where they meet."""
    theta_h, _, _, phi_d = halfway_difference(wi, wo)
    r = float(weight) * np.sin(theta_h)
    return np.column_stack([points[:, :-1], r * np.cos(phi_d), r * np.sin(phi_d),
                            points[:, -1]])


@dataclass(frozen=True, eq=False)
class RbfBRDF(BRDF):
    """A homogeneous isotropic BRDF f_r(u, v, w) in 1/sr (Zickler et al. Eq. 5).

    Parameters
    ----------
    model : RbfModel
        Interpolant over (u, v, w), D = 3, or over :func:`polar_points` of them, D = 4; with 1
        (grey) or 3 (RGB) channels.
    log_offset : float, optional
        When set, the interpolant is of g = log(v + log_offset) (1/sr inside the log), and
        v = exp(g) - log_offset; None: of v itself. v is f_r, or h with ``horizon``.
    angular_weight : float, optional
        Set (in (0, 1)) when the model is over ``polar_points(uvw, angular_weight)``.
    asymmetry_weight : float, optional
        Set (> 0) when the points carry :func:`with_asymmetry`'s two columns (D + 2): the model
        is not reciprocal. None: f_r(wi, wo) = f_r(wo, wi) by construction.
    horizon : float, optional
        Set (> 0, with ``asymmetry_weight``) when the interpolated value is not f_r but
        h = f_r cos theta_i / (cos theta_i + horizon): f_r well above the horizon, the radiance
        form f_r cos theta_i (over ``horizon``) near it; f_r = h (cos theta_i + horizon) /
        cos theta_i (``isotropic`` module docstring for why).
    """

    model: RbfModel
    log_offset: float | None = None
    angular_weight: float | None = None
    asymmetry_weight: float | None = None
    horizon: float | None = None

    def __post_init__(self):
        _check_angular_weight(self.angular_weight)
        dim, over = (3, "(u, v, w)") if self.angular_weight is None else (4, "polar points")
        if self.asymmetry_weight is not None:
            if not self.asymmetry_weight > 0:
                raise SharingError(f"asymmetry_weight must be > 0 or None, got "
                                   f"{self.asymmetry_weight!r}")
            dim, over = dim + 2, over + " and the un-doubled phi_d"
        if self.model.dim != dim:
            raise SharingError(f"model must be {dim}-D (over {over}), got {self.model.dim}-D")
        if self.log_offset is not None and not self.log_offset > 0:
            raise SharingError(f"log_offset must be > 0 or None, got {self.log_offset!r}")
        if self.horizon is not None and not (0 < self.horizon < np.inf and self.asymmetry_weight):
            raise SharingError(f"horizon must be None, or finite > 0 with an asymmetry_weight (its "
                               f"cos theta_i is not a function of (u, v, w)), got "
                               f"{self.horizon!r}")

    def _evaluate(self, wi, wo):
        points = angular_points(uvw_from_directions(wi, wo), self.angular_weight)
        if self.asymmetry_weight is not None:
            points = with_asymmetry(points, wi, wo, self.asymmetry_weight)
        g = self.model(points)
        if self.log_offset is not None:
            g = np.exp(np.minimum(g, 700.0)) - self.log_offset
        if self.horizon is not None:
            g = g * (1.0 + self.horizon / wi[:, 2:3])
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
        (x, y, u, v) (D = 4); over (x, y) and the :func:`polar_points` (D = 6, or 5 without w)
        when ``angular_weight`` is set; 1 or 3 channels.
    xy : ndarray, (N, 2) or (2,)
        Surface coordinates of the points the BRDF describes (row i goes with sample row i of
        ``evaluate``), in the units the model was fitted in.
    albedo : ndarray, (N, 3), (3,) or None
        Multiplicative texture a(x) (the dichromatic model's diffuse albedo); None = 1.
    angular_weight : float, optional
        Set (in (0, 1)) when the model's angular coordinates are ``polar_points``.
    """

    model: RbfModel
    xy: object
    albedo: object = None
    angular_weight: float | None = None

    def __post_init__(self):
        _check_angular_weight(self.angular_weight)
        dims = (4, 5) if self.angular_weight is None else (5, 6)
        if self.model.dim not in dims:
            raise SharingError(f"model must be {dims[0]}-D or {dims[1]}-D (over (x, y) and "
                               f"{'(u, v, w)' if self.angular_weight is None else 'polar points'})"
                               f", got {self.model.dim}-D")
        xy = np.asarray(self.xy, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(xy)):
            raise SharingError("xy contains NaN or infinite values")
        object.__setattr__(self, "xy", xy)

    def _evaluate(self, wi, wo):
        xy = np.broadcast_to(self.xy, (len(wi), 2))
        angular = angular_points(uvw_from_directions(wi, wo), self.angular_weight)
        q = np.hstack([xy, angular[:, :self.model.dim - 2]])
        f = np.maximum(self.model(q), 0.0)
        return f if self.albedo is None else f * rgb(self.albedo)

    def take(self, index) -> "SpatialRbfBRDF":
        """The BRDF of the points ``index`` (per-point xy and albedo indexed; shared ones kept)."""
        xy = self.xy[index] if len(self.xy) > 1 else self.xy
        albedo = self.albedo
        if albedo is not None and np.ndim(albedo) == 2 and len(albedo) > 1:
            albedo = np.asarray(albedo)[index]
        return SpatialRbfBRDF(self.model, xy, albedo, self.angular_weight)
