"""Surface normals from the diffuse samples (photometric stereo), the geometry reflectance sharing
needs (Zickler et al. 2005, Sect. 7.1: "photometric stereo, since it provides the precise surface
normals required for reflectometry").

The method interpolates the BRDF in (u, v, w), coordinates of the halfway vector about the
normal: a normal a few degrees off moves every highlight by as much, and a sharp lobe (Phong
exponent 70: ~7 deg wide) is then predicted where it is not. A mesh that lacks the surface's
relief (bumps, engraving) gives such normals. The polarization-separated diffuse samples are
Lambertian, ``d = rho / pi (n . wi)``, so per texel three or more lights give ``b = rho n / pi``
by linear least squares; the lights the current normal puts in attached shadow (their diffuse is
0, not a negative ``n . wi``) are dropped and the solve repeated. Where the mesh is right, the
fitted normal only follows the noise (and the registration and interreflection errors) of a few
samples: a texel keeps its given normal unless the tilt (two more parameters than an albedo
alone) explains its diffuse samples significantly better, by an F-test.

Directions are in whatever frame the samples are given (for lumitexels: each texel's local frame,
mesh normal = +z); the normals come back in that frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import f as f_distribution

from ..frames import tangent_frames, to_local
from ..photometric_stereo import texel_normal_equations
from .rbf import SharingError

#: shading n . wi below which a sample counts as in attached shadow for the current normal
SHADOW_COS = 0.02
#: smallest eigenvalue of the texel's mean wi wi^T below which its lights do not determine a
#: normal (all nearly in one plane); 0.01 ~ lights spread less than ~6 deg out of that plane
MIN_SPREAD = 0.01


@dataclass(frozen=True, eq=False)
class PhotometricNormals:
    """Result of :func:`photometric_normals`.

    Attributes
    ----------
    normals : ndarray, (T, 3)
        Unit normals in the samples' frame; the given ``prior`` (default +z) where not fitted.
    fitted : ndarray of bool, (T,)
        True where the diffuse samples determined the normal and it explains them significantly
        better than the given one.
    tilt_deg : ndarray, (T,)
        Angle between the fitted normal and the prior (0 where not fitted), degrees.
    """

    normals: np.ndarray
    fitted: np.ndarray
    tilt_deg: np.ndarray

    def report(self) -> str:
        f = self.fitted
        med = float(np.median(self.tilt_deg[f])) if f.any() else float("nan")
        return (f"photometric normals: {int(f.sum())} of {len(f)} texels fitted, median tilt from "
                f"the given normal {med:.2f} deg")


def photometric_normals(texel, wi, diffuse, n_texels: int, *, weight=None, valid=None,
                        max_tilt_deg: float = 45.0, iterations: int = 3,
                        significance: float | None = 0.01) -> PhotometricNormals:
    """Per-texel Lambertian photometric stereo on diffuse reflectance samples.

    Parameters
    ----------
    texel : array_like of int, (S,)
        Texel of each sample, in [0, ``n_texels``).
    wi : array_like, (S, 3)
        Unit direction to the light, in the frame the normals are wanted in (for lumitexels: the
        texel's local frame, so the prior normal is +z).
    diffuse : array_like, (S, 3) or (S,)
        Diffuse reflectance ``f_r cos theta_i`` (radiance / irradiance at normal incidence: what
        a lumitexel holds), any linear units; RGB is summed (one normal for all channels).
    n_texels : int
        Number of texels T.
    weight : array_like, (S,), optional
        Non-negative least-squares weight per sample (default 1).
    valid : array_like of bool, (S,), optional
        False drops a sample (it may hold NaN).
    max_tilt_deg : float
        A fitted normal further than this from +z (the prior) is rejected (noise, or a texel
        whose lights barely determine it).
    iterations : int
        Re-solves after dropping the samples the current normal puts in attached shadow.
    significance : float or None
        Level of the per-texel F-test (tilted normal, 3 parameters, against an albedo about the
        given normal, 1 parameter, on the same samples): a texel whose test is not significant at
        this level keeps +z; it needs at least 4 samples. None accepts every solvable texel.

    Returns
    -------
    PhotometricNormals

    Raises
    ------
    SharingError
        Mis-shaped, out-of-range or non-finite input, naming the argument.
    """
    texel = np.asarray(texel)
    s = len(texel)
    if texel.ndim != 1 or not np.issubdtype(texel.dtype, np.integer):
        raise SharingError(f"texel must be a 1-D integer array, got {texel.dtype} {texel.shape}")
    if not (isinstance(n_texels, (int, np.integer)) and n_texels > 0):
        raise SharingError(f"n_texels must be a positive integer, got {n_texels!r}")
    if s and (texel.min() < 0 or texel.max() >= n_texels):
        raise SharingError(f"texel must lie in [0, n_texels = {n_texels})")
    wi = np.asarray(wi, dtype=np.float64)
    if wi.shape != (s, 3):
        raise SharingError(f"wi must have shape ({s}, 3), got {wi.shape}")
    d = np.asarray(diffuse, dtype=np.float64)
    d = d.sum(axis=1) if d.ndim == 2 else d
    if d.shape != (s,):
        raise SharingError(f"diffuse must have shape ({s},) or ({s}, 3), got {np.shape(diffuse)}")
    keep = np.ones(s, bool) if valid is None else np.asarray(valid)
    if keep.shape != (s,) or keep.dtype != bool:
        raise SharingError(f"valid must be a bool array of shape ({s},)")
    w = np.ones(s) if weight is None else np.asarray(weight, dtype=np.float64)
    if w.shape != (s,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise SharingError(f"weight must be finite, >= 0, of shape ({s},)")
    if not np.all(np.isfinite(wi[keep])) or not np.all(np.isfinite(d[keep])):
        raise SharingError("wi or diffuse contains NaN or infinite values at samples marked valid")
    if not 0 < max_tilt_deg <= 90:
        raise SharingError(f"max_tilt_deg must be in (0, 90], got {max_tilt_deg!r}")
    if significance is not None and not 0 < significance < 1:
        raise SharingError(f"significance must be in (0, 1) or None, got {significance!r}")
    w = np.where(keep & (wi[:, 2] > 0), w, 0.0)   # only lit samples (as the mesh sees them)
    wi, d = np.where(keep[:, None], wi, 0.0), np.where(keep, d, 0.0)
    prior = np.array([0.0, 0.0, 1.0])
    n = np.tile(prior, (n_texels, 1))
    ok = np.zeros(n_texels, bool)
    use = w
    for it in range(iterations + 1):
        cnt = np.bincount(texel, use > 0, n_texels)
        A, b = texel_normal_equations(texel, wi, d, use, n_texels)
        wsum = np.bincount(texel, use, n_texels)
        # the lights must span 3-D: smallest eigenvalue of the weighted mean wi wi^T
        spread = np.linalg.eigvalsh(A / np.maximum(wsum, 1e-300)[:, None, None])[:, 0]
        solvable = (cnt >= 3) & (spread >= MIN_SPREAD)
        g = np.zeros((n_texels, 3))
        g[solvable] = np.linalg.solve(A[solvable], b[solvable][..., None])[..., 0]
        norm = np.linalg.norm(g, axis=1)
        ok = solvable & (norm > 0) & (g[:, 2] > norm * np.cos(np.radians(max_tilt_deg)))
        n = np.where(ok[:, None], g / np.maximum(norm, 1e-300)[:, None], prior)
        if it < iterations:
            use = w * (np.sum(n[texel] * wi, axis=1) > SHADOW_COS)
    if significance is not None:
        ok &= _tilt_significant(texel, wi, d, use, g, cnt, n_texels, significance)
        n = np.where(ok[:, None], n, prior)
    tilt = np.degrees(np.arccos(np.clip(n[:, 2], -1.0, 1.0)))
    return PhotometricNormals(n, ok, np.where(ok, tilt, 0.0))


def _tilt_significant(texel, wi, d, use, g, cnt, n_texels, level) -> np.ndarray:
    """Per texel: does ``d = g . wi`` fit the samples weighted ``use`` significantly better than
    ``d = a wi_z`` (albedo only, the given normal)? F-test with (2, cnt - 3) degrees of freedom."""
    z = wi[:, 2]
    a = np.bincount(texel, use * d * z, n_texels) / np.maximum(np.bincount(texel, use * z * z, n_texels), 1e-300)
    rss0 = np.bincount(texel, use * (d - a[texel] * z) ** 2, n_texels)
    rss1 = np.bincount(texel, use * (d - np.sum(g[texel] * wi, axis=1)) ** 2, n_texels)
    dof = cnt - 3
    with np.errstate(divide="ignore", invalid="ignore"):
        stat = (rss0 - rss1) / 2.0 / (rss1 / np.maximum(dof, 1))
        p = f_distribution.sf(stat, 2, np.maximum(dof, 1))
    return (dof >= 1) & ((rss1 == 0) & (rss0 > 0) | (p < level))


def reframe(texel, normals, *directions):
    """Directions (S, 3) re-expressed in frames whose z is the texel's new normal.

    The sharing models are isotropic (they depend on ``n . wi``, ``n . wo``, ``wi . wo`` only), so
    any tangent serves. ``normals`` (T, 3) are unit vectors in the directions' frame; returns one
    (S, 3) array per direction given.
    """
    frames = tangent_frames(np.asarray(normals, dtype=np.float64))[np.asarray(texel)]
    return tuple(to_local(np.asarray(v, dtype=np.float64), frames) for v in directions)
