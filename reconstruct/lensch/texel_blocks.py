"""Lumitexel samples as consecutive texel blocks: what :func:`~reconstruct.lensch.fit_svbrdf_blocks`
reads, one block at a time, so that only one block's samples are in memory during a per-texel
step (projection, normal fitting, labelling, scoring).

:class:`TexelBlocks` is the interface: ``ranges`` (the blocks' texels ``(t0, t1)``, consecutive
from 0), :meth:`~TexelBlocks.read` (one block's samples) and :meth:`~TexelBlocks.gather` (the
samples of a subsample of texels, for the global steps). :class:`ArrayBlocks` serves arrays in
memory; the pipeline serves the stored Zarr arrays (``capture.pipeline.lumitexel_arrays``)
without this package knowing Zarr.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

__all__ = ["SampleBlock", "TexelBlocks", "ArrayBlocks"]


@dataclass(frozen=True)
class SampleBlock:
    """Samples of ``n_texels`` texels, sorted by texel: ``texel`` (S,) int64 numbered from 0
    within the block, ``wi`` / ``wo`` (S, 3) float64 unit directions to the light / camera in the
    texel's local frame (+z = its normal), ``reflectance`` (S, 3) ``f_r cos theta_i`` (1/sr or
    the calibration's units), ``weight`` (S,) float64; ``diffuse`` / ``specular`` (S, 3), the
    polarization-separated parts of ``reflectance`` in the samples' stored precision, or None
    where the captures were not separated (reflectance sharing's dichromatic fit reads them)."""

    n_texels: int
    texel: np.ndarray
    wi: np.ndarray
    wo: np.ndarray
    reflectance: np.ndarray
    weight: np.ndarray
    diffuse: np.ndarray | None = None
    specular: np.ndarray | None = None


class TexelBlocks(ABC):
    """``n_texels`` texels' samples in consecutive blocks ``ranges`` (texels ``t0:t1``)."""

    n_texels: int
    ranges: list[tuple[int, int]]

    @abstractmethod
    def read(self, i: int) -> SampleBlock:
        """The samples of block ``i`` (texels numbered from ``ranges[i][0]``)."""

    def gather(self, texels: np.ndarray) -> SampleBlock:
        """The samples of the (sorted, unique) ``texels``, numbered 0 .. len(texels) - 1: each
        block read once, only the wanted texels' samples kept."""
        texels = np.asarray(texels, np.int64)
        parts = []
        for i, (t0, t1) in enumerate(self.ranges):
            lo, hi = np.searchsorted(texels, [t0, t1])
            if lo == hi:
                continue
            b = self.read(i)
            want = np.zeros(t1 - t0, bool)
            want[texels[lo:hi] - t0] = True
            keep = want[b.texel]
            local = np.cumsum(want) - 1 + lo   # block texel -> its place among ``texels``
            parts.append((local[b.texel[keep]], b.wi[keep], b.wo[keep], b.reflectance[keep], b.weight[keep],
                          *((b.diffuse[keep], b.specular[keep]) if b.diffuse is not None else ())))
        if not parts:
            z = np.zeros((0, 3))
            return SampleBlock(len(texels), np.zeros(0, np.int64), z, z, z, np.zeros(0))
        return SampleBlock(len(texels), *(np.concatenate(a) for a in zip(*parts)))


class ArrayBlocks(TexelBlocks):
    """Samples in memory (validated, any order) served in blocks of ``block_texels`` texels.

    ``texel`` (S,) int 0..n_texels-1; ``wi``, ``wo``, ``reflectance`` (S, 3); ``weight`` (S,);
    optionally ``diffuse`` and ``specular`` (S, 3). The samples are sorted by texel once (stable:
    a texel's samples keep their order).
    """

    def __init__(self, texel, wi, wo, reflectance, weight, *, n_texels: int, block_texels: int,
                 diffuse=None, specular=None) -> None:
        if (diffuse is None) != (specular is None):
            raise ValueError("ArrayBlocks: diffuse and specular must be given together")
        order = np.argsort(texel, kind="stable")
        self.texel, self.wi, self.wo = np.asarray(texel, np.int64)[order], wi[order], wo[order]
        self.reflectance, self.weight = reflectance[order], weight[order]
        self.diffuse, self.specular = (None, None) if diffuse is None else (diffuse[order], specular[order])
        self.n_texels = n_texels
        self.ranges = [(a, min(a + block_texels, n_texels)) for a in range(0, n_texels, block_texels)]
        self._offsets = np.searchsorted(self.texel, np.arange(n_texels + 1))

    def read(self, i: int) -> SampleBlock:
        t0, t1 = self.ranges[i]
        s = slice(self._offsets[t0], self._offsets[t1])
        return SampleBlock(t1 - t0, self.texel[s] - t0, self.wi[s], self.wo[s], self.reflectance[s], self.weight[s],
                           *((self.diffuse[s], self.specular[s]) if self.diffuse is not None else ()))
