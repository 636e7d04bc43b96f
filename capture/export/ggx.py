"""The exported BRDF: a Lambertian base plus one GGX lobe, fitted per texel to a recovered model.

The model every export writes (texture maps, Mitsuba scene; glTF maps onto it, see
:mod:`capture.export.gltf`) is

    f_r(wi, wo) = kd / pi + ks * D(h; alpha) * G1(wi) * G1(wo) / (4 cos theta_i cos theta_o)

with D the GGX (Trowbridge-Reitz) distribution, G1 = 1 / (1 + Lambda) Smith's separable
masking for GGX and no Fresnel factor (``ks`` absorbs it). ``kd`` is the repository's ``rho_d``
convention: the diffuse albedo, so the diffuse term is ``rho_d / pi``. It is exactly Mitsuba 3's
``diffuse`` + ``roughconductor`` (``material = "none"``: Fresnel 1, GGX, ``sample_visible``
masking G1 G1) summed, which is how the Mitsuba scene renders it.

The fit is linear in ``kd`` and ``ks`` for a fixed ``alpha``: for every ``alpha`` of a grid,
each texel's non-negative least squares in ``f_r cos theta_i`` is a 2 x 2 system per channel
(all texels at once through ``bincount``); each texel keeps the ``alpha`` of least error.
Only dot products with the normal enter, so samples may be given in any local frame together
with the texel's normal in that frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruct.brdf import microfacet_distribution, smith_lambda

__all__ = ["GgxMaps", "ALPHA_GRID", "ggx_reflectance", "fit_ggx", "FORMULA"]

#: weight of a material's own solution in each of its texels' fits, in samples: a texel that
#: never saw its highlight keeps the material's lobe instead of an unconstrained one
PRIOR_SAMPLES = 10.0
#: roughness values tried per texel (GGX alpha, log-spaced: a highlight's width scales with it)
ALPHA_GRID = np.geomspace(0.02, 1.0, 28)

FORMULA = ("f_r(wi, wo) = rho_d / pi + ks * D(h) * G1(wi) * G1(wo) / (4 cos(theta_i) cos(theta_o)); "
           "D(h) = alpha^2 / (pi cos^4(theta_h) (alpha^2 + tan^2(theta_h))^2) (GGX); "
           "G1(w) = 2 / (1 + sqrt(1 + alpha^2 tan^2(theta_w))) (Smith, separable); no Fresnel factor "
           "(ks is the lobe's scale); rho_d is the diffuse albedo (Lambertian term rho_d / pi); "
           "angles about the texel's normal (the normal map's), f_r in 1/sr")


@dataclass(frozen=True)
class GgxMaps:
    """Per-texel parameters of the exported model (see the module docstring).

    Attributes
    ----------
    rho_d : ndarray (T, 3)
        Diffuse albedo (the ``rho_d / pi`` convention), >= 0, in the reconstruction's units
        (1/sr x sr: unitless when the calibration is absolute).
    ks : ndarray (T, 3)
        Scale of the GGX lobe, >= 0.
    alpha : ndarray (T,)
        GGX roughness (``alpha = roughness^2`` in glTF's convention).
    """

    rho_d: np.ndarray
    ks: np.ndarray
    alpha: np.ndarray

    def take(self, texels: np.ndarray) -> "GgxMaps":
        """The parameters of ``texels`` (int array), e.g. one row per sample."""
        return GgxMaps(self.rho_d[texels], self.ks[texels], self.alpha[texels])


def _cosines(n: np.ndarray, wi: np.ndarray, wo: np.ndarray):
    """cos theta_i, cos theta_o, cos theta_h about the unit normals ``n`` (all (S, 3))."""
    h = wi + wo
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    return (np.einsum("ij,ij->i", n, wi), np.einsum("ij,ij->i", n, wo), np.einsum("ij,ij->i", n, h))


def _lobe_cos(cos_i, cos_o, cos_h, alpha) -> np.ndarray:
    """D G1 G1 / (4 cos_i cos_o) * cos_i of the unit lobe (0 below either horizon)."""
    front = (cos_i > 1e-6) & (cos_o > 1e-6)
    ci, co = np.where(front, cos_i, 1.0), np.where(front, cos_o, 1.0)
    ch = np.clip(cos_h, 1e-9, 1.0)
    d = microfacet_distribution(ch, alpha, "ggx")
    g = 1.0 / ((1.0 + smith_lambda(ci, alpha, "ggx")) * (1.0 + smith_lambda(co, alpha, "ggx")))
    return np.where(front, d * g / (4.0 * co), 0.0)


def ggx_reflectance(maps: GgxMaps, n: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """``f_r cos theta_i`` (S, 3) of per-sample parameters ``maps`` (S rows), normals ``n`` and
    unit directions ``wi`` (to the light) / ``wo`` (to the camera), all (S, 3) in one frame."""
    ci, co, ch = _cosines(n, wi, wo)
    diffuse = np.where((ci > 0) & (co > 0), ci, 0.0)[:, None] / np.pi
    return maps.rho_d * diffuse + maps.ks * _lobe_cos(ci, co, ch, maps.alpha)[:, None]


def fit_ggx(texel: np.ndarray, n: np.ndarray, wi: np.ndarray, wo: np.ndarray, target: np.ndarray,
            n_texels: int, weight: np.ndarray | None = None, group: np.ndarray | None = None) -> GgxMaps:
    """Fit :class:`GgxMaps` to samples of recovered reflectance, every texel at once.

    Parameters
    ----------
    texel : ndarray (S,) int
        The texel of each sample, in [0, n_texels).
    n, wi, wo : ndarray (S, 3)
        The texel's unit normal and the sample's unit directions, in one frame per sample.
    target : ndarray (S, 3)
        ``f_r cos theta_i`` the recovered model gives for the sample.
    weight : ndarray (S,), optional
        Least-squares weights (default 1).
    group : ndarray (n_texels,) int, optional
        Material of each texel: one ``alpha`` per material (the one of least error summed over
        its texels), ``rho_d`` and ``ks`` per texel, each pulled towards the material's pooled
        solution by :data:`PRIOR_SAMPLES` pseudo-samples. Default: ``alpha`` per texel, no pull.

    Returns
    -------
    GgxMaps
        The non-negative least-squares ``rho_d``, ``ks`` per channel at each texel's best
        ``alpha`` of :data:`ALPHA_GRID` (texels without samples get zeros and alpha 1).
    """
    texel = np.asarray(texel, np.int64)
    y = np.asarray(target, float)
    if y.shape != (len(texel), 3) or np.asarray(wi).shape != y.shape or np.asarray(wo).shape != y.shape:
        raise ValueError(f"fit_ggx: texel (S,), wi, wo, target (S, 3) must agree; got {texel.shape}, "
                         f"{np.shape(wi)}, {np.shape(wo)}, {y.shape}")
    w = np.ones(len(texel)) if weight is None else np.asarray(weight, float)
    ci, co, ch = _cosines(np.asarray(n, float), np.asarray(wi, float), np.asarray(wo, float))
    d = np.where((ci > 0) & (co > 0), ci, 0.0) / np.pi

    def acc(v):
        return np.bincount(texel, w * v, n_texels)

    sdd = acc(d * d)
    sdy = np.stack([acc(d * y[:, c]) for c in range(3)], axis=1)
    syy = np.stack([acc(y[:, c] ** 2) for c in range(3)], axis=1)
    grouped = group is not None
    group = np.asarray(group, np.int64) if grouped else np.arange(n_texels)
    G = int(group.max()) + 1 if n_texels else 0
    count = np.bincount(group, acc(np.ones(len(texel))), G)

    def pool(v):   # per texel -> per material
        return np.stack([np.bincount(group, v[:, c], G) for c in range(v.shape[1])], axis=1)

    best = np.full(G, np.inf)
    out_kd, out_ks, out_a = np.zeros((n_texels, 3)), np.zeros((n_texels, 3)), np.ones(n_texels)
    for alpha in ALPHA_GRID:
        s = _lobe_cos(ci, co, ch, np.full(len(ci), alpha))
        sds, sss = acc(d * s)[:, None], acc(s * s)[:, None]
        ssy = np.stack([acc(s * y[:, c]) for c in range(3)], axis=1)
        a, b, c = sdd[:, None], sds, sss
        p, q = sdy, ssy
        if grouped:   # pulled towards the material's own solution by PRIOR_SAMPLES pseudo-samples
            A, B, C = pool(a), pool(b), pool(c)
            kd_m, ks_m = _nnls2(A, B, C, pool(p), pool(q))
            per = PRIOR_SAMPLES / np.maximum(count, 1e-300)[:, None]
            la, lc = (A * per)[group], (C * per)[group]
            a, c = a + la, c + lc
            p, q = p + la * kd_m[group], q + lc * ks_m[group]
        kd, ks = _nnls2(a, b, c, p, q)
        sse = (syy - 2 * (kd * sdy + ks * ssy) + kd * kd * sdd[:, None] + 2 * kd * ks * sds
               + ks * ks * sss).sum(axis=1)
        sse = np.bincount(group, sse, G)
        better = sse < best
        best = np.where(better, sse, best)
        pick = better[group]
        out_kd[pick], out_ks[pick], out_a[pick] = kd[pick], ks[pick], alpha
    return GgxMaps(out_kd, out_ks, out_a)


def _nnls2(a, b, c, p, q):
    """Non-negative least squares of the 2 x 2 normal equations [[a, b], [b, c]] x = [p, q],
    elementwise: the unconstrained solution, else the better single-term one."""
    det = a * c - b * b
    ok = det > 1e-12 * np.maximum(a * c, 1e-300)
    x = np.where(ok, (c * p - b * q) / np.where(ok, det, 1.0), 0.0)
    z = np.where(ok, (a * q - b * p) / np.where(ok, det, 1.0), 0.0)
    only_x = np.maximum(p, 0) / np.maximum(a, 1e-300)
    only_z = np.maximum(q, 0) / np.maximum(c, 1e-300)
    # the residual reduction x p + z q of each single-term candidate; the better one wins
    single_x = only_x * p >= only_z * q
    bad = ~ok | (x < 0) | (z < 0)
    x = np.where(bad, np.where(single_x, only_x, 0.0), x)
    z = np.where(bad, np.where(single_x, 0.0, only_z), z)
    return x, z
