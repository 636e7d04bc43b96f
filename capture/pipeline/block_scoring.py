"""A fitted model scored over texel blocks: its predictions of the training and held-out samples
made one block at a time, the errors accumulated from per-block sums.

:func:`reconstruct.metrics.relative_rms` is ``sqrt(sum (p - m)^2 / sum m^2)``: both sums add up
over blocks, so :class:`ErrorSums` keeps them and nothing per sample. The trimmed figure
(:func:`reconstruct.metrics.trimmed_relative_rms`: without the 1 % of samples with the largest
error) needs the quantile of the per-sample errors over all samples; it keeps two float64 per
sample (the sample's squared error and squared value: 16 bytes against the 64 of a stored
sample). Both equal the figures of the gathered arrays up to the summation order (1e-12
relative on the quick demo).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from reconstruct.lumitexels import Lumitexels

from .lumitexel_arrays import LumitexelArrays

__all__ = ["BlockScores", "ErrorSums", "score_blocks"]


@dataclass
class ErrorSums:
    """Sums of squared residuals and squared measured values over the samples added so far (any
    units: the figures are ratios), and, with ``rows``, per sample the same two for the trimmed
    figure."""

    sse: float = 0.0
    ssq: float = 0.0
    count: int = 0
    rows: bool = True
    _row_sse: list[np.ndarray] = field(default_factory=list, repr=False)
    _row_ssq: list[np.ndarray] = field(default_factory=list, repr=False)

    def add(self, predicted: np.ndarray, measured: np.ndarray) -> None:
        """Add samples: ``predicted`` and ``measured`` (S, C), the same shape."""
        p = np.asarray(predicted, float)
        m = np.asarray(measured, float)
        if p.shape != m.shape:
            raise ValueError(f"predicted has shape {p.shape}, measured {m.shape}: they must match")
        row_sse = np.sum((p - m).reshape(len(m), -1) ** 2, axis=1)
        row_ssq = np.sum(m.reshape(len(m), -1) ** 2, axis=1)
        self.sse += float(row_sse.sum())
        self.ssq += float(row_ssq.sum())
        self.count += len(m)
        if self.rows:
            self._row_sse.append(row_sse)
            self._row_ssq.append(row_ssq)

    @property
    def relative_rms(self) -> float:
        """:func:`reconstruct.metrics.relative_rms` of everything added (NaN when nothing was)."""
        if self.count == 0:
            return float("nan")
        return float(np.sqrt(self.sse / max(self.ssq, 1e-300)))

    def trimmed_relative_rms(self, trim: float = 0.01) -> float:
        """:func:`reconstruct.metrics.trimmed_relative_rms` of everything added (made with
        ``rows=True``)."""
        if not self.rows:
            raise ValueError("trimmed_relative_rms needs the per-sample errors: make ErrorSums(rows=True)")
        if self.count == 0:
            return float("nan")
        err, sq = np.concatenate(self._row_sse), np.concatenate(self._row_ssq)
        keep = err <= np.quantile(err, 1.0 - trim)
        return float(np.sqrt(err[keep].sum() / max(sq[keep].sum(), 1e-300)))


@dataclass
class BlockScores:
    """What :func:`score_blocks` accumulated: the model against the training samples, against
    the held-out samples, and (with a truth) against the true reflectance of the held-out
    samples (of the training samples when none is held out)."""

    training: ErrorSums
    held_out: ErrorSums
    truth: ErrorSums | None


def score_blocks(predict: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray], arrays: LumitexelArrays,
                 *, truth_of: Callable[[Lumitexels], np.ndarray] | None = None,
                 max_texels: int | None = None) -> BlockScores:
    """Score a fitted model over the stored lumitexels one texel block at a time.

    Parameters
    ----------
    predict : callable(texel, wi, wo) -> ndarray (S, 3)
        The model's reflectance ``f_r cos theta_i`` of samples: ``texel`` (S,) in the gathered
        numbering (:attr:`TexelBlock.first_texel`), ``wi``, ``wo`` (S, 3) unit directions in the
        texel's local frame (mesh normal = +z).
    arrays : LumitexelArrays
    truth_of : callable(Lumitexels) -> ndarray (S, 3), optional
        The true reflectance of a block's samples (texels numbered within the block).
    max_texels : int, optional
        Texels a block at most (:meth:`LumitexelArrays.parts`; default the arrays' chunks).
    """
    truth_held, truth_train = (None, None) if truth_of is None else (ErrorSums(rows=False), ErrorSums(rows=False))
    scores = BlockScores(ErrorSums(), ErrorSums(), None)
    for b in arrays.iter_blocks(max_texels):
        lt = b.lumitexels
        p = predict(lt.texel + b.first_texel, lt.wi, lt.wo)
        scores.training.add(p[~b.held], lt.reflectance[~b.held])
        scores.held_out.add(p[b.held], lt.reflectance[b.held])
        if truth_of is not None:
            true_r = np.asarray(truth_of(lt), float)
            truth_held.add(p[b.held], true_r[b.held])
            truth_train.add(p[~b.held], true_r[~b.held])
    if truth_of is not None:   # the held-out samples, the training ones when none is held out
        scores.truth = truth_held if scores.held_out.count else truth_train
    return scores
