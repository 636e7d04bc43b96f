"""The stored lumitexels' training samples as :class:`reconstruct.lensch.TexelBlocks`: what the
methods' per-texel steps read one texel block at a time (:func:`reconstruct.lensch.fit_svbrdf_blocks`)
without ``reconstruct`` knowing Zarr.

The blocks are the arrays' texel chunks, each cut into parts of at most ``max_texels`` (a method
holds more per texel than the assembly did: a part of a chunk is read by decompressing the
chunk and keeping the part's rows); texels are numbered as
:meth:`capture.pipeline.lumitexel_arrays.LumitexelArrays.gather` numbers them (texels without a
training sample left out), so per-texel results line up with the gathered lumitexels'.
Directions are in each texel's local frame (+z = its mesh normal); reflectance ``f_r cos
theta_i`` in the calibration's units (and its polarization-separated parts, where captured, as
stored: float32); weights 1.
"""
from __future__ import annotations

import numpy as np

from reconstruct.lensch import SampleBlock, TexelBlocks

from .lumitexel_arrays import LumitexelArrays

__all__ = ["StoredBlocks"]


class StoredBlocks(TexelBlocks):
    """The training samples of ``arrays``, block by block, at most ``max_texels`` texels a block
    (default: the arrays' chunk); one pass over the training views' sample flags when made, to
    number the texels. ``parts`` are the blocks' texel ranges ``(t0, t1)`` in the arrays."""

    def __init__(self, arrays: LumitexelArrays, max_texels: int | None = None) -> None:
        self.arrays = arrays
        parts = arrays.parts(max_texels)
        kept = arrays.training_texels_per_block(parts)
        firsts = np.concatenate([[0], np.cumsum(kept)])
        self.n_texels = int(firsts[-1])
        self.parts = [parts[c] for c in range(len(parts)) if kept[c]]   # a part without such texels is no block
        self.ranges = [(int(firsts[c]), int(firsts[c + 1])) for c in range(len(parts)) if kept[c]]

    def read(self, i: int) -> SampleBlock:
        lt, held = self.arrays.block(*self.parts[i])
        train = ~held
        separated = (lt.diffuse[train], lt.specular[train]) if lt.diffuse is not None else ()   # stored precision
        return SampleBlock(lt.n_texels, lt.texel[train], *(np.asarray(getattr(lt, name)[train], np.float64)
                                                           for name in ("wi", "wo", "reflectance", "weight")), *separated)
