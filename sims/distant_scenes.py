"""The reflectance-sharing paper's synthetic problems, rendered deterministically.

Orthographic images (camera along +z, OpenCV frame, ``reconstruct.distant.sphere_normals``)
of a sphere or of a hemisphere seen from its pole (the same visible normals) under directional
lights of unit irradiance, shaded by ``reconstruct.distant.shade_distant``: no Monte Carlo noise,
so the images are ground truth. No occlusion is needed: both objects are convex.

- :func:`theta_d_lights`: Zickler et al. Sect. 5.1 sampling: for an orthographic view and a
  distant light the half-angle theta_d is the same at every pixel (half the light-view angle).
- :func:`hemisphere_lights`: directions spread evenly over a cone about the view (Sect. 6.1).
- :func:`ramp_material`: the hemisphere's Cook-Torrance with roughness varying linearly left to
  right (``sims.objects.RoughnessRamp``), optionally with a diffuse texture (Sect. 7).
- :class:`RingHighlight`: a BRDF none of the analytic models has (an off-specular ring).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruct.brdf import BRDF, CookTorrance
from reconstruct.brdf.base import check_param, rgb
from reconstruct.coords import halfway_difference
from reconstruct.distant import shade_distant, sphere_normals

from .objects import RoughnessRamp

#: Camera direction (surface to camera) of the orthographic views.
VIEW = np.array([0.0, 0.0, -1.0])


def theta_d_lights(theta_d) -> np.ndarray:
    """Light directions (K, 3) giving half-angles ``theta_d`` (K,) radians with :data:`VIEW`:
    the light is 2 theta_d from the view direction, tilted towards +x."""
    t = 2.0 * np.asarray(theta_d, dtype=np.float64).reshape(-1)
    return np.stack([np.sin(t), np.zeros_like(t), -np.cos(t)], axis=1)


def stratified(n: int, high: float = np.pi / 2) -> np.ndarray:
    """Centres of ``n`` equal strata of [0, high]: (n,)."""
    return (np.arange(n) + 0.5) / n * high


def hemisphere_lights(n: int, *, max_angle_deg: float = 70.0, offset: float = 0.5) -> np.ndarray:
    """``n`` unit directions (n, 3) spread evenly (a Fibonacci spiral, equal solid angle) over
    the cone of half-angle ``max_angle_deg`` about :data:`VIEW`; ``offset`` in (0, 1) shifts the
    spiral so that two sets (inputs, held-out) do not coincide."""
    i = np.arange(n) + offset
    cos_max = np.cos(np.radians(max_angle_deg))
    z = 1.0 - (1.0 - cos_max) * i / n
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), -z], axis=1)


@dataclass(frozen=True)
class DistantImages:
    """Images of the visible points of an object under K directional lights.

    Attributes
    ----------
    normals : ndarray, (P, 3)
        Unit normals of the P visible pixels (OpenCV camera frame).
    xy : ndarray, (P, 2)
        The surface as a graph over the image: pixel centres scaled to [0, 1]^2.
    mask : ndarray of bool, (H, W)
        Which pixels the P points are (row-major order).
    directions : ndarray, (K, 3)
        Light directions.
    radiance : ndarray, (K, P, 3)
        Rendered radiance (unit irradiance).
    """

    normals: np.ndarray
    xy: np.ndarray
    mask: np.ndarray
    directions: np.ndarray
    radiance: np.ndarray

    def image(self, k: int) -> np.ndarray:
        """Image ``k`` as (H, W, 3), zero off the object."""
        out = np.zeros(self.mask.shape + (3,))
        out[self.mask] = self.radiance[k]
        return out


def visible_points(size) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(normals (P, 3), xy (P, 2) in [0, 1]^2, mask (H, W)) of the orthographic sphere view."""
    normals, mask = sphere_normals(size)
    rows, cols = np.nonzero(mask)
    h, w = mask.shape
    xy = np.stack([(cols + 0.5) / w, (rows + 0.5) / h], axis=1)
    return normals[mask], xy, mask


def render_distant(brdf: BRDF, size, directions, *, progress=None) -> DistantImages:
    """Render the orthographic sphere / hemisphere view under each light of ``directions``.

    ``brdf`` may have per-point parameters (P rows, in the order of :func:`visible_points`).
    """
    normals, xy, mask = visible_points(size)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    rad = np.stack([shade_distant(brdf, normals, d[k:k + 1], np.ones(1), view_dirs=VIEW)
                    for k in range(len(d))])  # one light per image: K calls over all points
    if progress is not None:
        progress(len(d), len(d))
    return DistantImages(normals, xy, mask, d, rad)


def ramp_material(xy, ramp: RoughnessRamp | None = None, *, texture: bool = False) -> CookTorrance:
    """The hemisphere's per-point Cook-Torrance for surface points ``xy`` (P, 2) in [0, 1]^2:
    roughness linear in x (``ramp.alpha_left`` at x = 0 to ``alpha_right`` at x = 1); with
    ``texture``, a diffuse colour that varies quickly (stripes and a smooth tint: rapid spatial
    variation the albedo of Eq. 7 must carry)."""
    ramp = RoughnessRamp(radius_mm=1.0) if ramp is None else ramp
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    obj = np.zeros((len(xy), 3))
    obj[:, 1] = (2.0 * xy[:, 0] - 1.0) * ramp.radius_mm  # the ramp runs along object y
    base = ramp.brdf_at(obj)
    if not texture:
        return base
    stripes = 0.5 + 0.5 * np.sign(np.sin(2 * np.pi * 6 * (xy[:, 0] + 0.7 * xy[:, 1])))
    kd = np.asarray(ramp.kd) * (0.45 + 0.55 * stripes[:, None])
    kd = kd * np.stack([1 + 0.3 * xy[:, 1], 1 - 0.3 * xy[:, 1], np.ones(len(xy))], axis=1)
    return CookTorrance(kd=kd, f0=ramp.f0, alpha=base.alpha)


@dataclass(frozen=True)
class RingHighlight(BRDF):
    """Lambertian plus an off-specular ring:
    f_r = kd / pi + ks exp(-((theta_h - theta_0) / width)^2).

    The lobe peaks on a ring theta_h = theta_0 about the halfway-vector direction, not at the
    mirror direction: no Ward, Cook-Torrance or Lafortune lobe (all peak at theta_h = 0 or along
    a generalized mirror direction) has this shape.

    Parameters
    ----------
    kd : float or (3,)
        Diffuse albedo, >= 0.
    ks : float
        Ring peak, 1/sr, >= 0.
    theta_0, width : float
        Ring angle and width, radians (> 0).
    """

    kd: object = (0.3, 0.25, 0.2)
    ks: float = 2.0
    theta_0: float = 0.35
    width: float = 0.08

    def __post_init__(self):
        check_param("RingHighlight", "kd", self.kd)
        check_param("RingHighlight", "ks", self.ks)
        check_param("RingHighlight", "theta_0", self.theta_0, low_open=True)
        check_param("RingHighlight", "width", self.width, low_open=True)

    def _evaluate(self, wi, wo):
        theta_h = halfway_difference(wi, wo)[0][:, None]
        ring = np.exp(-((theta_h - self.theta_0) / self.width) ** 2)
        return rgb(self.kd) / np.pi + self.ks * ring
