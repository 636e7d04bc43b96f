"""Dichromatic reflection: RGB body reflection plus a scalar interface lobe (Shafer 1985)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .base import BRDF, check_param, rgb


@dataclass(frozen=True)
class Dichromatic(BRDF):
    """Sum of an RGB diffuse model and a scalar specular lobe with the colour of the light.

    f_r,k(wi, wo) = d_k(wi, wo) + c_k g(wi, wo),   k in {R, G, B}

    where d is ``diffuse`` (any RGB model: Lambertian, Oren-Nayar, a tabulated body reflection),
    g is ``specular`` made scalar (the mean of its three channels, so give it grey parameters)
    and c = ``specular_color`` is the interface reflection's colour relative to the light:
    white (the default) is the neutral-interface assumption of the dichromatic model, so under a
    source of RGB colour s the pixel is I_k = s_k (d_k + g) cos(theta_i) E — Zickler et al. 2005,
    Eq. 7 with d_k = a_k d_k (albedo times normalised diffuse reflectance); see ``radiance``.

    Parameters
    ----------
    diffuse : BRDF
        RGB body reflection (depolarising).
    specular : BRDF
        Interface reflection; its channel mean is used (1/sr).
    specular_color : float, (3,), (N,) or (N, 3)
        Colour of the interface reflection relative to the light, >= 0 (default white).

    References
    ----------
    S. A. Shafer, "Using color to separate reflection components", Color Res. Appl. 10(4), 1985;
    T. Zickler et al., "Reflectance sharing: image-based rendering from a sparse set of
    images", EGSR 2005, Eq. 7.
    """

    diffuse: BRDF
    specular: BRDF
    specular_color: object = 1.0

    def __post_init__(self):
        for name in ("diffuse", "specular"):
            if not isinstance(getattr(self, name), BRDF):
                raise TypeError(f"Dichromatic.{name} must be a BRDF model, "
                                f"got {type(getattr(self, name)).__name__}")
        check_param("Dichromatic", "specular_color", self.specular_color)

    def _evaluate(self, wi, wo):
        g = self.specular.evaluate(wi, wo).mean(axis=1, keepdims=True)
        return self.diffuse.evaluate(wi, wo) + rgb(self.specular_color) * g

    def radiance(self, wi: np.ndarray, wo: np.ndarray, light_color=1.0,
                 irradiance=1.0) -> np.ndarray:
        """Reflected radiance for a directional / point source (Zickler et al. Eq. 7).

        I_k = s_k (d_k + c_k g) cos(theta_i) E for local unit directions ``wi``/``wo`` (N, 3),
        ``light_color`` s (RGB, e.g. a unit vector) and normal irradiance ``irradiance`` E
        (W/m^2 for a point source: intensity / r^2). Returns (N, 3) radiance in E's units per sr.
        """
        wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
        cos_i = np.clip(wi[:, 2:3], 0.0, None)
        return rgb(light_color) * self.evaluate(wi, wo) * cos_i * rgb(irradiance)

    def take(self, index) -> "Dichromatic":
        """Per-sample parameters of both parts indexed by ``index``."""
        color = np.asarray(self.specular_color)
        return replace(self, diffuse=self.diffuse.take(index), specular=self.specular.take(index),
                       specular_color=color[index] if color.ndim and color.shape[0] > 3
                       else self.specular_color)

    def diffuse_part(self) -> BRDF:
        return self.diffuse.diffuse_part()

    def specular_part(self) -> BRDF:
        # the diffuse model's own interface part (if any) stays specular
        return replace(self, diffuse=self.diffuse.specular_part())
