"""Isotropic multi-lobe Lafortune model (Lafortune et al. 1997; Lensch et al. 2003, Eq. 7)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .base import BRDF, Lambertian, check_param, rgb


def _lobes(owner: str, name: str, value) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    a = a.reshape(1) if a.ndim == 0 else a
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{owner}.{name} must be finite")
    return a


@dataclass(frozen=True)
class Lafortune(BRDF):
    """Isotropic Lafortune model with any number of lobes, parameters per lobe and channel.

    f_r(u, v) = rho_d/pi + sum_i max(0, C_x,i (u_x v_x + u_y v_y) + C_z,i u_z v_z)^N_i

    for local light direction u = ``wi`` and view direction v = ``wo`` (Lensch et al. 2003,
    Eq. 7, with the diffuse term written as an albedo: the paper's rho_d is our rho_d / pi).
    The clamp at zero is Lafortune's: a lobe contributes nothing where its cosine is negative.

    Sign conventions (for u, v above the surface):

    - C_x < 0, C_z > 0: forward (specular-like) lobe around the mirror direction of u.
      C_x = -C_z gives the Phong lobe C_z^N cos^N(alpha) about the mirror direction;
      -C_x > C_z moves the peak towards grazing angles (off-specular peak, as in Torrance-Sparrow).
    - C_x > 0, C_z > 0: retro-reflective lobe around u itself.
    - C_x = 0, C_z > 0: lobe about the normal, (C_z^2 cos theta_i cos theta_o)^N (generalised
      diffuse falling off at grazing angles).
    - C_x = C_z = -1 is not a reflection lobe here: the cosine is -wi . wo, a lobe around the
      straight-through direction -wi, visible only near grazing.
    The lobe's magnitude (its albedo) grows with |C|^N; its width shrinks with N.
    The model is reciprocal: the lobe term is symmetric in u and v.

    Parameters
    ----------
    rho_d : float, (3,), (N,) or (N, 3)
        Diffuse albedo (RGB), >= 0.
    cx, cz, n : float or array with the lobe axis first
        Lobe parameters: a scalar is one grey lobe; shape (L,) L grey lobes; (L, 3) L RGB lobes
        (the paper's per-channel fit); (L, N) or (L, N, 3) per sample (spatially varying). All
        three must have the same number of lobes L (or a length-1 lobe axis, shared by all).
        ``cx`` and ``cz`` are unitless with 1/sr^(1/N) folded in; ``n`` (the exponent N) > 0.

    References
    ----------
    E. P. F. Lafortune, S.-C. Foo, K. E. Torrance, D. P. Greenberg, "Non-linear approximation of
    reflectance functions", SIGGRAPH 1997; H. P. A. Lensch et al., "Image-based reconstruction
    of spatial appearance and geometric detail", ACM TOG 22(2), 2003, Eq. 7.
    """

    rho_d: object = 0.5
    cx: object = -1.0
    cz: object = 1.0
    n: object = 20.0

    def __post_init__(self):
        check_param("Lafortune", "rho_d", self.rho_d)
        lobes = {k: _lobes("Lafortune", k, getattr(self, k)) for k in ("cx", "cz", "n")}
        check_param("Lafortune", "n", lobes["n"], low_open=True)
        counts = {k: v.shape[0] for k, v in lobes.items()}
        if len(set(counts.values()) - {1}) > 1:
            raise ValueError(f"Lafortune lobe counts differ (lobe axis first): {counts}")

    @property
    def n_lobes(self) -> int:
        """Number of lobes L."""
        return max(np.atleast_1d(np.asarray(getattr(self, k))).shape[0] for k in ("cx", "cz", "n"))

    @classmethod
    def phong(cls, rho_d=0.0, rho_s=0.5, exponent=20.0) -> "Lafortune":
        """One forward lobe equal to the energy-normalised modified Phong lobe.

        With C_z = -C_x = (rho_s (N + 2) / (2 pi))^(1/N) the lobe is
        rho_s (N + 2)/(2 pi) cos^N(alpha), alpha the angle between ``wo`` and the mirror of ``wi``:
        exactly ``ModifiedPhong(kd=rho_d, ks=rho_s, exponent=N)``.
        ``rho_s`` may be RGB (3,): the lobe then has per-channel C.
        """
        check_param("Lafortune.phong", "rho_s", rho_s)
        check_param("Lafortune.phong", "exponent", exponent, low_open=True)
        c = (np.asarray(rho_s, float) * (exponent + 2) / (2 * np.pi)) ** (1.0 / exponent)
        return cls(rho_d=rho_d, cx=-c[None], cz=c[None], n=np.asarray([exponent], float))

    def _evaluate(self, wi, wo):
        tangential = wi[:, 0:1] * wo[:, 0:1] + wi[:, 1:2] * wo[:, 1:2]
        normal = wi[:, 2:3] * wo[:, 2:3]
        lobes = [np.atleast_1d(np.asarray(getattr(self, k), float)) for k in ("cx", "cz", "n")]
        f = rgb(self.rho_d) / np.pi
        for i in range(self.n_lobes):  # loop over the few lobes, vectorised over samples
            cx, cz, n = (rgb(a[i if len(a) > 1 else 0]) for a in lobes)
            f = f + np.maximum(cx * tangential + cz * normal, 0.0) ** n
        return f

    def take(self, index) -> "Lafortune":
        """Per-sample parameters indexed by ``index`` (axis 0 of rho_d, axis 1 of lobe arrays).

        ``index`` is an integer array or a boolean mask over samples."""
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)

        def sel(v, axis):
            a = np.asarray(v)
            return a.take(index, axis=axis) if a.ndim > axis and a.shape[axis] > 3 else v
        return Lafortune(rho_d=sel(self.rho_d, 0), cx=sel(self.cx, 1), cz=sel(self.cz, 1),
                         n=sel(self.n, 1))

    def diffuse_part(self) -> BRDF:
        return Lambertian(self.rho_d)

    def specular_part(self) -> BRDF:
        return replace(self, rho_d=0.0)
