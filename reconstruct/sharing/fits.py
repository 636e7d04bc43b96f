"""Reflectance sharing fits: spatially varying (Sect. 6), dichromatic with albedo (Sect. 7,
Eq. 7) and single image (Sect. 7.4, Eq. 8), after Zickler et al. 2005 (the homogeneous fit of
Sect. 5 is ``isotropic.py``); the sample checks all fits share.

Inputs are reflectance samples: local unit directions ``wi`` (to the light) and ``wo`` (to the
camera), normal = +z, and ``brdf`` = f_r in 1/sr (radiance / (irradiance cos theta_i)).
Samples near the terminator carry huge, noisy f_r (the division by a tiny cos theta_i): every
fit drops samples with cos theta_i < ``min_cos`` and weights the greedy residual of the rest by
cos theta_i (the paper's radiance residual, Sect. 5), so callers can pass all samples. Samples
marked invalid (``valid`` False: saturated, shadowed, occluded) are dropped and may hold NaN.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from ..brdf import BRDF, Dichromatic, Lambertian
from ..coords import uvw_from_directions
from .models import ANGULAR_WEIGHT, SpatialRbfBRDF, _check_angular_weight, angular_points
from .normals import PhotometricNormals, photometric_normals, reframe
from .rbf import SharingError, fit_rbf

#: Default cos(theta_i) below which samples are dropped (theta_i > 87 deg).
MIN_COS = 0.05
#: w spread below which all samples count as one image (one theta_d): Eq. 8 applies.
SINGLE_IMAGE_W_SPREAD = 1e-3


@dataclass(frozen=True)
class _Samples:
    wi: np.ndarray
    wo: np.ndarray
    keep: np.ndarray      # (S,) bool: used by the fit
    cos_i: np.ndarray     # (S,)


def _directions(name: str, a, n: int | None = None) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or (n is not None and len(arr) != n):
        raise SharingError(f"{name} must have shape ({n if n is not None else 'S'}, 3), "
                           f"got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise SharingError(f"{name} contains NaN or infinite values")
    if np.any(np.abs(np.linalg.norm(arr, axis=1) - 1.0) > 1e-3):
        raise SharingError(f"{name} must hold unit vectors")
    return arr


def _values(name: str, a, n: int, keep: np.ndarray, channels=(1, 3)) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    arr = arr[:, None] if arr.ndim == 1 else arr
    if arr.ndim != 2 or len(arr) != n or arr.shape[1] not in channels:
        raise SharingError(f"{name} must have shape ({n},) or ({n}, 3), got {np.shape(a)}")
    bad = ~np.isfinite(arr).all(axis=1) & keep
    if np.any(bad):
        raise SharingError(f"{name} contains NaN or infinite values at {int(bad.sum())} samples "
                           "marked valid (mark saturated or missing samples with valid=False)")
    return np.where(keep[:, None], arr, 0.0)


def _samples(wi, wo, valid, min_cos: float, *, some: bool = True) -> _Samples:
    """The samples checked, with the ones a fit uses marked; ``some``: at least one must be
    (False for one texel block of many, which may hold none)."""
    wi = _directions("wi", wi)
    wo = _directions("wo", wo, len(wi))
    if not 0.0 <= min_cos < 1.0:
        raise SharingError(f"min_cos must be in [0, 1), got {min_cos!r}")
    keep = (wi[:, 2] >= max(min_cos, 1e-9)) & (wo[:, 2] > 0)
    if valid is not None:
        v = np.asarray(valid)
        if v.shape != (len(wi),) or v.dtype != bool:
            raise SharingError(f"valid must be a bool array of shape ({len(wi)},), got "
                               f"{v.dtype} {v.shape}")
        keep &= v
    if some and not keep.any():
        raise SharingError(f"wi: none of the {len(wi)} samples is usable (valid, lit with "
                           f"cos theta_i >= min_cos = {min_cos}, seen from above)")
    return _Samples(wi, wo, keep, wi[:, 2])


def _separated(s: _Samples, diffuse, specular) -> tuple[np.ndarray, np.ndarray]:
    """Diffuse (S, 3) and grey specular (S, 1) f_r, zero where a sample is not used."""
    n = len(s.wi)
    return (_values("diffuse", diffuse, n, s.keep, channels=(3,)),
            _values("specular", specular, n, s.keep).mean(axis=1, keepdims=True))


def _texel_normals(texel, s: _Samples, dif: np.ndarray, n_texels: int) -> PhotometricNormals:
    """Each texel's normal from its diffuse samples (Sect. 7.1), in the samples' frame."""
    return photometric_normals(texel, s.wi, dif * s.cos_i[:, None], n_texels, valid=s.keep)


def _about_normals(texel, s: _Samples, dif, spec, normals: np.ndarray, min_cos: float):
    """The samples re-expressed about per-texel ``normals`` (T, 3): directions, the samples the
    fit uses (lit and seen about the new normal), and f_r (= measured / cos theta_i, so the same
    measurement divided by the new cos theta_i)."""
    wi2, wo2 = reframe(texel, normals, s.wi, s.wo)
    ratio = s.cos_i / np.maximum(wi2[:, 2], 1e-9)
    keep = s.keep & (wi2[:, 2] >= max(min_cos, 1e-9)) & (wo2[:, 2] > 0)
    return _Samples(wi2, wo2, keep, wi2[:, 2]), dif * ratio[:, None], spec * ratio[:, None]


def _texel_albedo(dif: np.ndarray, texel, keep: np.ndarray, n_texels: int) -> np.ndarray:
    """Per-texel diffuse albedo a(x) as f_r (T, 3): the median of its used diffuse samples
    (Sect. 7.1), 0 where it has none."""
    albedo = group_median(dif[keep], texel[keep], n_texels)
    return np.where(np.isfinite(albedo), np.maximum(albedo, 0.0), 0.0)


def _rbf_space(xy: np.ndarray, uvw: np.ndarray, single_image: bool, m_xy: float, m_w: float,
               angular_weight: float | None):
    """The RBF's points q = (x, y, u, v[, w]) (S, 4 or 5), or (x, y) and the polar points
    (S, 5 or 6) with ``angular_weight``, and the diagonal of M (Eq. 6)."""
    angular = angular_points(uvw, angular_weight, with_w=not single_image)
    n_uv = angular.shape[1] - (0 if single_image else 1)
    return (np.hstack([xy, angular]),
            (m_xy, m_xy) + (1.0,) * n_uv + (() if single_image else (m_w,)))


def _dichromatic_rbfs(q, s: _Samples, dif, spec, w, albedo: np.ndarray, single_image: bool, opts) -> dict:
    """Eq. 7's RBFs: g on the specular samples, d on the diffuse ones normalised by their
    texel's albedo ``albedo`` (S, 3) (none in the single-image case, Eq. 8)."""
    k = s.keep
    fits = {"specular": fit_rbf(q[k], spec[k], weight=w[k], **opts)}
    if not single_image:
        lit = k & (albedo.min(axis=1) > 0)  # a black texel's normalised diffuse is undefined
        fits["diffuse"] = fit_rbf(q[lit], dif[lit] / albedo[lit], weight=w[lit], **opts)
    return fits


def _w_varies(uvw: np.ndarray) -> bool:
    return float(np.ptp(uvw[:, 2])) >= SINGLE_IMAGE_W_SPREAD


def _weight(s: _Samples, weight) -> np.ndarray:
    w = s.cos_i * s.keep
    if weight is not None:
        user = np.asarray(weight, dtype=np.float64)
        if user.shape != w.shape or not np.all(np.isfinite(user)) or np.any(user < 0):
            raise SharingError(f"weight must be finite, >= 0, of shape {w.shape}")
        w = w * user
    return w


# ----------------------------------------------------------------------------------------------
# spatially varying
# ----------------------------------------------------------------------------------------------
def group_median(values: np.ndarray, group: np.ndarray, n_groups: int) -> np.ndarray:
    """Per-group median of ``values`` (S, C) for integer labels ``group`` (S,) -> (n_groups, C);
    NaN for empty groups. One sort per channel, no loop over groups."""
    counts = np.bincount(group, minlength=n_groups)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    lo, hi = starts + (counts - 1) // 2, starts + counts // 2
    out = np.full((n_groups, values.shape[1]), np.nan)
    has = counts > 0
    for c in range(values.shape[1]):  # C <= 3 channels
        srt = values[np.lexsort((values[:, c], group)), c]
        out[has, c] = 0.5 * (srt[lo[has]] + srt[hi[has]])
    return out


@dataclass(frozen=True, eq=False)
class SpatialFit:
    """Result of :func:`fit_spatial`.

    Attributes
    ----------
    mode : str
        ``"5d"`` (Eq. 6), ``"single-image"`` (4-D (x, y, u, v), Eq. 8), ``"dichromatic"``
        (Eq. 7) or ``"dichromatic single-image"`` (Eq. 8: Lambertian albedo + 4-D specular).
    texel_xy : ndarray, (T, 2)
        Surface coordinates of the surface points (texels) the samples came from.
    albedo : ndarray, (T, 3) or None
        Dichromatic modes: per-texel diffuse albedo a(x) as f_r (1/sr; the median of the
        texel's diffuse samples, Sect. 7.1).
    fits : dict of str -> RbfFit
        ``"brdf"``, or ``"diffuse"`` (a/albedo-normalised d_k, 3 channels sharing centres) and
        ``"specular"`` (g, 1 channel); absent for the Lambertian diffuse of the single-image case.
    n_used, n_dropped : int
    normals : PhotometricNormals or None
        With ``fit_normals``: each texel's normal in the samples' frame (the given normal is
        +z). The BRDFs (``brdf_at``, ``brdf``) are then about these normals; :meth:`predict`
        takes directions in the samples' frame and applies them.
    fit_texels : int or None
        How many texels' samples the RBFs were fitted on (:func:`fit_spatial_blocks`' random
        subsample, every texel when there are no more); None: every sample given. ``n_used``
        and ``n_dropped`` count every texel's samples (the albedo and normals use them all).
    angular_weight : float or None
        The RBFs' angular coordinates are ``polar_points`` with this weight; None: (u, v, w).
    """

    mode: str
    texel_xy: np.ndarray
    albedo: np.ndarray | None
    fits: dict
    n_used: int
    n_dropped: int
    normals: PhotometricNormals | None = None
    fit_texels: int | None = None
    angular_weight: float | None = None

    def predict(self, texel, wi, wo) -> np.ndarray:
        """Reflectance ``f_r cos theta_i`` (N, C), 1/sr, of texels ``texel`` (N,) for local unit
        directions ``wi``, ``wo`` (N, 3) in the frame the fit's samples were given in (the fitted
        normals, where there are, applied)."""
        texel = np.asarray(texel)
        wi, wo = np.asarray(wi, dtype=np.float64), np.asarray(wo, dtype=np.float64)
        if self.normals is not None:
            wi, wo = reframe(texel, self.normals.normals, wi, wo)
        return self.brdf_at(self.texel_xy[texel], texel).evaluate(wi, wo) * np.maximum(wi[:, 2:3], 0.0)

    def brdf_at(self, xy, texel=None) -> BRDF:
        """A per-point BRDF for surface points ``xy`` (N, 2); the albedo of the dichromatic modes
        comes from ``texel`` (N,) indices into ``texel_xy``, or from the nearest texel."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.albedo is not None:
            if texel is None:
                texel = cKDTree(self.texel_xy).query(xy)[1]
            albedo = self.albedo[np.asarray(texel)]
        a = self.angular_weight
        if self.mode in ("5d", "single-image"):
            return SpatialRbfBRDF(self.fits["brdf"].model, xy, angular_weight=a)
        spec = SpatialRbfBRDF(self.fits["specular"].model, xy, angular_weight=a)
        if self.mode == "dichromatic":
            return Dichromatic(SpatialRbfBRDF(self.fits["diffuse"].model, xy, albedo, a), spec)
        return Dichromatic(Lambertian(np.pi * albedo), spec)

    @property
    def brdf(self) -> BRDF:
        """The per-texel BRDF, row t for ``texel_xy[t]``."""
        return self.brdf_at(self.texel_xy, np.arange(len(self.texel_xy)))

    def report(self) -> str:
        parts = "; ".join(f"{k}: {f.report()}" for k, f in self.fits.items())
        on = "" if self.fit_texels is None else f", RBFs fitted on {self.fit_texels} of {len(self.texel_xy)} texels"
        if self.angular_weight is not None:
            on += f", (u, v, w) in polar form, angular weight {self.angular_weight:g}"
        return (f"spatial RBF ({self.mode}) over {len(self.texel_xy)} texels from {self.n_used} "
                f"samples ({self.n_dropped} dropped{on}). {parts}")


def fit_spatial(xy, wi, wo, brdf, *, texel=None, diffuse=None, specular=None,
                m_xy: float = 0.3, m_w: float = 0.5, max_centers: int = 2000,
                angular_weight: float | None = ANGULAR_WEIGHT, fit_normals: bool = False, single_image: bool | None = None, weight=None, valid=None,
                min_cos: float = MIN_COS, tol=None, smoothing: float = 0.0, rng=0,
                progress: Callable[[int, int], None] | None = None) -> SpatialFit:
    """Spatially varying BRDF by reflectance sharing (Zickler et al. Sects. 6-7).

    The samples live in q = (x, y, u, v, w) with M = diag(m_xy, m_xy, 1, 1, m_w) (Eq. 6),
    (u, v) in the polar form of the homogeneous fit (``angular_weight``). When
    every sample has the same theta_d (one image: one distant light and an orthographic view),
    w is constant and dropped: q = (x, y, u, v) (Eq. 8). With ``diffuse`` and ``specular``
    (polarization-separated f_r) the dichromatic model of Eq. 7 is fitted instead:
    f_k = a_k(x) d_k(q) + g(q), a = per-texel median of the diffuse samples, d fitted to the
    normalised diffuse samples (three channels sharing one centre set, the storage saving the
    paper suggests), g to the specular samples; in the single-image case the diffuse part is
    Lambertian with albedo a (Eq. 8).

    Parameters
    ----------
    xy : array_like, (S, 2)
        Surface coordinates of each sample (the paper: the surface as a graph over [0, 1]^2; or
        the mesh's UVs). ``m_xy`` is in units of 1 / these.
    wi, wo : array_like, (S, 3)
        Local unit directions to the light / camera (normal = +z).
    brdf : array_like, (S, 3) or (S,), or None
        f_r samples (1/sr); None when ``diffuse`` and ``specular`` are given.
    texel : array_like of int, (S,), optional
        Surface point of each sample (for the albedo median); default: equal ``xy`` rows.
    diffuse : array_like, (S, 3), optional
        Diffuse (depolarised) f_r samples; with ``specular``, selects the dichromatic model.
    specular : array_like, (S,) or (S, 3), optional
        Specular f_r samples (grey: the channel mean is used).
    m_xy, m_w : float
        Spatial and w scales of M (the paper: m_xy 0.2-0.4, m_w 0.1-0.5).
    max_centers : int
        Centre budget of each RBF.
    angular_weight : float in (0, 1) or None
        Fit over (x, y) and ``models.polar_points(uvw, angular_weight)``: distances in phi_d at
        fixed theta_h weigh this much of those in sin theta_h, so that the images' highlight
        samples at scattered phi_d pool along theta_h (``isotropic`` module docstring; the
        Sect. 6.1 ramp at 64 px from 10 images: held-out median 0.35 -> 0.25 %; the quick
        demo's dichromatic fit: 1.46 -> 1.25 x the floor, docs/zoo.md); None: over (u, v, w)
        as the paper wrote it.
    fit_normals : bool
        Dichromatic only: first fit each texel's normal to its diffuse samples (Lambertian
        photometric stereo, :func:`reconstruct.sharing.photometric_normals`; Sect. 7.1) and fit
        the RBFs about those normals. For a mesh that lacks the surface's relief: its normals
        move every highlight (on the demo's bumpy sphere: held-out error 0.72 -> 0.47).
    single_image : bool, optional
        Force (True) or forbid (False) the 4-D case; default: by the spread of w.
    weight, valid, min_cos, tol, smoothing, rng, progress
        As :func:`fit_isotropic`.

    Returns
    -------
    SpatialFit

    Raises
    ------
    SharingError
        Mis-shaped or non-finite input, ``brdf`` given together with ``diffuse``/``specular``
        (or only one of those), too few samples, samples on a hyperplane.
    """
    s = _samples(wi, wo, valid, min_cos)
    n = len(s.wi)
    xy = np.asarray(xy, dtype=np.float64)
    if xy.shape != (n, 2) or not np.all(np.isfinite(xy)):
        raise SharingError(f"xy must be finite with shape ({n}, 2), got {xy.shape}")
    for name, v in (("m_xy", m_xy), ("m_w", m_w)):
        if not v > 0:
            raise SharingError(f"{name} must be > 0, got {v!r}")
    _check_angular_weight(angular_weight)
    dichromatic = diffuse is not None or specular is not None
    if dichromatic and (diffuse is None or specular is None):
        raise SharingError("diffuse and specular must be given together (Eq. 7)")
    if dichromatic == (brdf is not None):
        raise SharingError("pass either brdf or diffuse and specular, not both / neither")
    if texel is None:
        texel_xy, texel = np.unique(xy, axis=0, return_inverse=True)
        texel = texel.reshape(-1)
    else:
        texel = np.asarray(texel)
        if texel.shape != (n,) or not np.issubdtype(texel.dtype, np.integer) or texel.min() < 0:
            raise SharingError(f"texel must be non-negative integers of shape ({n},)")
        texel_xy = np.zeros((texel.max() + 1, 2))
        texel_xy[texel] = xy
    if dichromatic:
        dif, spec = _separated(s, diffuse, specular)
    elif fit_normals:
        raise SharingError("fit_normals needs diffuse and specular: the normals come from the "
                           "diffuse (Lambertian) samples")
    normals = None
    if fit_normals:
        normals = _texel_normals(texel, s, dif, len(texel_xy))
        s, dif, spec = _about_normals(texel, s, dif, spec, normals.normals, min_cos)
        if not s.keep.any():
            raise SharingError("wi: no sample is lit and seen about the fitted normals")
    w = _weight(s, weight)
    uvw = uvw_from_directions(s.wi, s.wo)
    if single_image is None:
        single_image = not _w_varies(uvw[s.keep])
    q, scale = _rbf_space(xy, uvw, single_image, m_xy, m_w, angular_weight)
    k = s.keep
    opts = dict(scale=scale, max_centers=max_centers, tol=tol, smoothing=smoothing, rng=rng,
                progress=progress)
    n_used = int(k.sum())
    if not dichromatic:
        values = _values("brdf", brdf, n, k)
        fit = fit_rbf(q[k], values[k], weight=w[k], **opts)
        return SpatialFit("single-image" if single_image else "5d", texel_xy, None,
                          {"brdf": fit}, n_used, n - n_used, angular_weight=angular_weight)
    albedo = _texel_albedo(dif, texel, k, len(texel_xy))
    fits = _dichromatic_rbfs(q, s, dif, spec, w, albedo[texel], single_image, opts)
    mode = "dichromatic single-image" if single_image else "dichromatic"
    return SpatialFit(mode, texel_xy, albedo, fits, n_used, n - n_used, normals,
                      angular_weight=angular_weight)
