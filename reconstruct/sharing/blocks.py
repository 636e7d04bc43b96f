"""Reflectance sharing's dichromatic fit (Zickler et al. 2005, Sect. 7) over texel blocks: the
per-texel steps one block at a time, the RBFs on a bounded, stated subsample of texels.

What depends on one texel's samples alone runs as a per-block task, a pure function of (one
block's samples) -> per-texel arrays: the normal refit to the diffuse samples (Sect. 7.1,
:func:`reconstruct.sharing.photometric_normals`), the samples about those normals, the albedo
(the median of the texel's diffuse samples), the samples used, and the range of w the 4-D /
5-D choice needs. The RBFs' greedy centre selection (Carr et al.) evaluates the residual at every
sample it is given, so it needs its samples at once: it runs here on the samples of at most
``fit_texels`` texels drawn at random (every texel when there are no more; :attr:`SpatialFit.fit_texels`
says how many), gathered from the blocks. The predictions (:meth:`SpatialFit.predict`) are a
function of each sample alone and the per-texel arrays, which are held whole (tens of bytes a
texel).

Over blocks of any size the fit equals the whole-array one (one block) to rounding, and with
every texel fitted it is :func:`reconstruct.sharing.fit_spatial`'s on the same samples, bit for bit.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..coords import uvw_from_directions
from ..lensch.texel_blocks import SampleBlock, TexelBlocks
from .fits import (MIN_COS, SINGLE_IMAGE_W_SPREAD, SpatialFit, _about_normals, _dichromatic_rbfs, _rbf_space,
                   _samples, _separated, _texel_albedo, _texel_normals, _weight)
from .models import ANGULAR_WEIGHT, _check_angular_weight
from .normals import PhotometricNormals
from .rbf import SharingError

__all__ = ["FIT_TEXELS", "fit_spatial_blocks"]

#: texels whose samples the RBFs are fitted on by default: covers every session so far (the quick
#: demo's 9 498 texels, the full demo's 37 k), so their figures do not change
FIT_TEXELS = 200_000


@dataclass(frozen=True)
class _BlockTexels:
    """One block's per-texel results: ``normals``, the refitted normals of its n texels in their
    local frames (None without the refit), ``albedo`` (n, 3) f_r, ``used`` (n,) the samples the
    fit uses; ``n_samples`` in the block and the used samples' w range (``w_lo``, ``w_hi``;
    +inf, -inf when none)."""

    normals: PhotometricNormals | None
    albedo: np.ndarray
    used: np.ndarray
    n_samples: int
    w_lo: float
    w_hi: float


def _block_texels(blocks: TexelBlocks, i: int, fit_normals: bool, min_cos: float) -> _BlockTexels:
    """The per-texel steps of block ``i`` (a per-block task; module level, so it pickles)."""
    b = blocks.read(i)
    normals, s, dif, spec = _dichromatic(b, None, fit_normals, min_cos, some=False)
    w = uvw_from_directions(s.wi[s.keep], s.wo[s.keep])[:, 2]
    return _BlockTexels(normals, _texel_albedo(dif, b.texel, s.keep, b.n_texels),
                        np.bincount(b.texel, s.keep, b.n_texels).astype(np.int64), len(b.texel),
                        float(w.min(initial=np.inf)), float(w.max(initial=-np.inf)))


def _dichromatic(b: SampleBlock, normals: np.ndarray | None, fit_normals: bool, min_cos: float, *, some: bool):
    """A block's samples as the dichromatic fit reads them: checked, f_r = measured / cos theta_i
    (in the samples' stored precision, as the in-memory route computes it), about the texels'
    ``normals`` (given, (n, 3)) or about normals refitted here (``fit_normals``) or the mesh's.
    Returns (PhotometricNormals or None, samples, diffuse f_r (S, 3), specular f_r (S, 1))."""
    if b.diffuse is None or b.specular is None:
        raise SharingError("blocks: the samples have no diffuse / specular parts (the dichromatic "
                           "fit needs polarization-separated captures)")
    cos = np.maximum(b.wi[:, 2:3], 1e-6).astype(b.diffuse.dtype)
    s = _samples(b.wi, b.wo, None, min_cos, some=some)
    dif, spec = _separated(s, b.diffuse / cos, b.specular / cos)
    fitted = None
    if normals is None and fit_normals:
        fitted = _texel_normals(b.texel, s, dif, b.n_texels)
        normals = fitted.normals
    if normals is not None:
        s, dif, spec = _about_normals(b.texel, s, dif, spec, normals, min_cos)
    return fitted, s, dif, spec


def _serial(fn, args):
    return [fn(*a) for a in args]


def fit_spatial_blocks(blocks: TexelBlocks, xy, *, fit_texels: int = FIT_TEXELS, m_xy: float = 0.3,
                       m_w: float = 0.5, max_centers: int = 2000,
                       angular_weight: float | None = ANGULAR_WEIGHT, fit_normals: bool = False,
                       min_cos: float = MIN_COS, tol=None, smoothing: float = 0.0, rng=0,
                       progress: Callable[[int, int], None] | None = None,
                       map_blocks: Callable[[Callable, list], list] | None = None) -> SpatialFit:
    """:func:`reconstruct.sharing.fit_spatial`'s dichromatic fit (Eq. 7; Eq. 8 when every sample
    has one theta_d) of the samples in ``blocks``, per-texel steps block by block.

    Parameters
    ----------
    blocks : TexelBlocks
        The samples, with their ``diffuse`` and ``specular`` parts (``f_r cos theta_i``, as
        lumitexels hold them), directions in each texel's local frame (+z = its mesh normal).
    xy : array_like, (T, 2)
        Each texel's surface coordinates (``m_xy`` is in units of 1 / these).
    fit_texels : int
        The RBFs are fitted on the samples of at most this many texels, drawn at random among
        those with a used sample (every texel when there are no more).
    m_xy, m_w, max_centers, angular_weight, fit_normals, min_cos, tol, smoothing, rng, progress
        As :func:`~reconstruct.sharing.fit_spatial`'s; ``rng`` also draws the subsample.
    map_blocks : callable(fn, list of argument tuples) -> list, optional
        Runs the per-block tasks (results in order): default one after the other here; the
        pipeline passes its executor's to run them on a cluster.

    Returns
    -------
    SpatialFit
        ``texel_xy`` = ``xy``; ``fit_texels`` the subsample's size; normals (with
        ``fit_normals``) in each texel's local frame.

    Raises
    ------
    SharingError
        ``xy`` mis-shaped or not finite, ``fit_texels`` < 1, a scale not > 0, samples without
        diffuse / specular parts, no usable sample, or an RBF fit's own errors.
    """
    T = blocks.n_texels
    xy = np.asarray(xy, dtype=np.float64)
    if xy.shape != (T, 2) or not np.all(np.isfinite(xy)):
        raise SharingError(f"xy must be finite with shape ({T}, 2) (one row a texel), got {xy.shape}")
    if not (isinstance(fit_texels, (int, np.integer)) and fit_texels >= 1):
        raise SharingError(f"fit_texels must be a positive integer, got {fit_texels!r}")
    for name, v in (("m_xy", m_xy), ("m_w", m_w)):
        if not v > 0:
            raise SharingError(f"{name} must be > 0, got {v!r}")
    _check_angular_weight(angular_weight)
    parts = (map_blocks or _serial)(_block_texels, [(blocks, i, fit_normals, min_cos) for i in range(len(blocks.ranges))])
    used = np.concatenate([p.used for p in parts]) if parts else np.zeros(0, np.int64)
    n_used, n_samples = int(used.sum()), sum(p.n_samples for p in parts)
    if n_used == 0:
        raise SharingError(f"wi: none of the {n_samples} samples is usable (lit with cos theta_i >= "
                           f"min_cos = {min_cos} and seen from above, about the normals fitted)")
    albedo = np.concatenate([p.albedo for p in parts])
    normals = None if not fit_normals else PhotometricNormals(
        *(np.concatenate([getattr(p.normals, f) for p in parts]) for f in ("normals", "fitted", "tilt_deg")))
    single_image = max(p.w_hi for p in parts) - min(p.w_lo for p in parts) < SINGLE_IMAGE_W_SPREAD
    # the global step: the RBFs on a bounded random subsample's samples (drawn only when it is one)
    if T <= fit_texels:
        sub = np.arange(T)
    else:
        with_samples = np.flatnonzero(used > 0)
        sub = np.sort(np.random.default_rng(rng).choice(with_samples, min(fit_texels, len(with_samples)), replace=False))
    g = blocks.gather(sub)
    _, s, dif, spec = _dichromatic(g, None if normals is None else normals.normals[sub], False, min_cos, some=True)
    if not s.keep.any():
        raise SharingError("wi: no sample of the fitted texels is lit and seen about the fitted normals")
    uvw = uvw_from_directions(s.wi, s.wo)
    q, scale = _rbf_space(xy[sub][g.texel], uvw, single_image, m_xy, m_w, angular_weight)
    fits = _dichromatic_rbfs(q, s, dif, spec, _weight(s, None), albedo[sub][g.texel], single_image,
                             dict(scale=scale, max_centers=max_centers, tol=tol, smoothing=smoothing, rng=rng,
                                  progress=progress))
    mode = "dichromatic single-image" if single_image else "dichromatic"
    return SpatialFit(mode, xy, albedo, fits, n_used, n_samples - n_used, normals, fit_texels=len(sub),
                      angular_weight=angular_weight)
