"""Reflectance lobes that no fitted model of the repository (Lafortune, Ward, Cook-Torrance)
expresses: test materials for the methods, not models to fit.

- :class:`AshikhminShirley`: anisotropic-Phong specular with Schlick Fresnel over the coupled,
  Fresnel-weighted diffuse of Ashikhmin & Shirley 2000 (isotropic exponent here);
- :class:`RetroReflective`: Lambertian with Hapke's opposition surge about the retro
  direction (wo = wi), a cusp no Lafortune retro lobe has;
- :class:`Sheen`: the "Charlie" inverted-Gaussian-like sheen of cloth (Estevez & Kulla 2017)
  over a Lambertian base.

Conventions are those of ``base.py``: local unit directions (z = normal), f_r in 1/sr, RGB.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .base import BRDF, Lambertian, check_param, rgb


@dataclass(frozen=True)
class AshikhminShirley(BRDF):
    """Ashikhmin-Shirley BRDF (isotropic), energy-coupled diffuse and Fresnel specular.

    f_s = (n + 1) / (8 pi) (n . h)^n / ((h . k) max(cos theta_i, cos theta_o)) F(h . k),
    F = Rs + (1 - Rs)(1 - h . k)^5,
    f_d = 28 Rd / (23 pi) (1 - Rs) (1 - (1 - cos theta_i / 2)^5)(1 - (1 - cos theta_o / 2)^5).

    Parameters
    ----------
    rd : float or (3,)
        Diffuse reflectance Rd (RGB), >= 0.
    rs : float or (3,)
        Specular reflectance at normal incidence Rs, in [0, 1].
    exponent : float
        Phong-like exponent n (n_u = n_v), > 0; 1000 is a sharp lobe (~2 deg wide).

    References
    ----------
    M. Ashikhmin, P. Shirley, "An anisotropic Phong BRDF model", J. Graphics Tools 5(2), 2000,
    Eqs. 4-5.
    """

    rd: object = 0.3
    rs: object = 0.05
    exponent: float = 300.0

    def __post_init__(self):
        check_param("AshikhminShirley", "rd", self.rd)
        check_param("AshikhminShirley", "rs", self.rs, high=1.0)
        check_param("AshikhminShirley", "exponent", self.exponent, low_open=True)

    def _evaluate(self, wi, wo):
        h = wi + wo
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        hk = np.sum(h * wi, axis=1, keepdims=True)
        ci, co, rs = wi[:, 2:3], wo[:, 2:3], rgb(self.rs)
        fresnel = rs + (1.0 - rs) * (1.0 - hk) ** 5
        spec = ((self.exponent + 1.0) / (8.0 * np.pi) * h[:, 2:3] ** self.exponent
                / (hk * np.maximum(ci, co)) * fresnel)
        diff = (28.0 * rgb(self.rd) / (23.0 * np.pi) * (1.0 - rs)
                * (1.0 - (1.0 - 0.5 * ci) ** 5) * (1.0 - (1.0 - 0.5 * co) ** 5))
        return diff + spec


@dataclass(frozen=True)
class RetroReflective(BRDF):
    """Lambertian with Hapke's shadow-hiding opposition surge (a retro-reflective cusp):
    f_r = kd / pi (1 + b0 / (1 + tan(g / 2) / h)), g = 2 theta_d the phase angle between the
    light and the viewer (moon dust, regolith, rough matte powders). The peak at g = 0 is a
    cusp with a heavy tail, not the Gaussian-like cos^n(g) of a Lafortune retro lobe.

    Parameters
    ----------
    kd : float or (3,)
        Diffuse albedo, >= 0.
    b0 : float
        Surge amplitude (f at g = 0 is (1 + b0) x the Lambertian level), >= 0.
    h : float
        Angular width parameter, > 0 (0.05: half the surge within ~6 deg of phase).

    References
    ----------
    B. Hapke, "Bidirectional reflectance spectroscopy 4: the extinction coefficient and the
    opposition effect", Icarus 67, 1986, Eq. 16.
    """

    kd: object = (0.35, 0.3, 0.25)
    b0: float = 1.5
    h: float = 0.05

    def __post_init__(self):
        check_param("RetroReflective", "kd", self.kd)
        check_param("RetroReflective", "b0", self.b0)
        check_param("RetroReflective", "h", self.h, low_open=True)

    def _evaluate(self, wi, wo):
        # tan(g / 2) = tan(theta_d) = |wi - wo| / |wi + wo| for unit vectors
        t = np.linalg.norm(wi - wo, axis=1, keepdims=True) / np.linalg.norm(wi + wo, axis=1,
                                                                               keepdims=True)
        return rgb(self.kd) / np.pi * (1.0 + self.b0 / (1.0 + t / self.h))

    def diffuse_part(self) -> BRDF:
        return Lambertian(self.kd)


@dataclass(frozen=True)
class Sheen(BRDF):
    """Lambertian plus the "Charlie" sheen of cloth:
    f_r = kd / pi + ks D(h) / (4 (cos_i + cos_o - cos_i cos_o)),
    D = (2 + 1/r) sin(theta_h)^(1/r) / (2 pi) (a distribution of fibres lying along the surface:
    strongest at grazing halfway vectors), with Neubelt & Pettineo's visibility term.

    Parameters
    ----------
    kd : float or (3,)
        Diffuse albedo, >= 0.
    ks : float or (3,)
        Sheen colour, >= 0.
    roughness : float
        r in (0, 1].

    References
    ----------
    A. Estevez, C. Kulla, "Production friendly microfacet sheen BRDF", Sony Imageworks 2017;
    D. Neubelt, M. Pettineo, "Crafting a next-gen material pipeline for The Order: 1886", 2013.
    """

    kd: object = (0.25, 0.1, 0.1)
    ks: object = (0.9, 0.6, 0.6)
    roughness: float = 0.35

    def __post_init__(self):
        check_param("Sheen", "kd", self.kd)
        check_param("Sheen", "ks", self.ks)
        check_param("Sheen", "roughness", self.roughness, low_open=True, high=1.0)

    def _evaluate(self, wi, wo):
        h = wi + wo
        cos_h = h[:, 2:3] / np.linalg.norm(h, axis=1, keepdims=True)
        sin_h = np.sqrt(np.maximum(1.0 - cos_h ** 2, 0.0))
        inv = 1.0 / self.roughness
        d = (2.0 + inv) * sin_h ** inv / (2.0 * np.pi)
        ci, co = wi[:, 2:3], wo[:, 2:3]
        return rgb(self.kd) / np.pi + rgb(self.ks) * d / (4.0 * (ci + co - ci * co))

    def diffuse_part(self) -> BRDF:
        return Lambertian(self.kd)
