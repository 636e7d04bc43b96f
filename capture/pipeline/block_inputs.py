"""What ``gonio process`` takes from the stored lumitexels when gathering them would exceed
``--memory-limit``: one pass over texel blocks instead of :meth:`LumitexelArrays.gather`.

The pass keeps what is per texel (position, normal, best view, pixel: tens of bytes a texel),
the sample counts, the samples of two views for the report's pictures (training view 0 and the
first held-out view with a sample: the views the gathered route draws, so the pictures are the
same) and, with a simulated lab's truth, the inputs' own error against it and the
:class:`Floor` (the true model scored on the held-out captures), from per-block sums as
:mod:`capture.pipeline.block_scoring` scores a model. Frames and units are the lumitexels':
object frame, mm, reflectance ``f_r cos theta_i`` in the calibration's units.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from reconstruct.lumitexels import LumitexelError, Lumitexels

from .block_scoring import ErrorSums
from .lumitexel_arrays import LumitexelArrays
from .process import select_samples
from .process_report import Floor

__all__ = ["BlockInputs", "TruthFigures", "inputs_over_blocks"]

_TEXEL_FIELDS = ("position", "normal", "best_view", "pixel")


@dataclass(frozen=True)
class TruthFigures:
    """The captured reflectance against the true ``f_r cos`` (held-out samples, the training
    ones when none is held out): relative RMS, median ratio of their channel sums, and the
    :class:`Floor` (None without held-out samples)."""

    measured_vs_truth_rel_rms: float
    measured_vs_truth_median_ratio: float
    floor: Floor | None


@dataclass(frozen=True)
class BlockInputs:
    """The stored lumitexels without their samples gathered.

    ``train`` and ``held`` have every texel with a training sample (the gathered numbering) and
    only the samples of one view each: training view 0 and the first held-out view with a
    sample (the report's pictures draw these). ``n_training_samples`` and ``n_held_samples``
    count all samples; ``truth`` is None without a truth or where it has no materials."""

    train: Lumitexels
    held: Lumitexels
    n_training_samples: int
    n_held_samples: int
    truth: TruthFigures | None


class _TruthSums:
    """Per-block sums of one sample set against the truth (:class:`TruthFigures`' parts)."""

    def __init__(self) -> None:
        self.measured = ErrorSums(rows=False)   # measured as the prediction of the truth
        self.floor = ErrorSums()                # the truth as the prediction of the measured
        self.ratios: list[np.ndarray] = []

    def add(self, measured: np.ndarray, true_r: np.ndarray) -> None:
        """``measured`` as stored (float32: its channel sum as the gathered route sums it)."""
        self.measured.add(measured, true_r)
        self.floor.add(true_r, measured)
        self.ratios.append(measured.sum(axis=1) / np.maximum(true_r.sum(axis=1), 1e-12))


def inputs_over_blocks(arrays: LumitexelArrays, *, max_texels: int | None = None,
                       truth_of: Callable[[Lumitexels], np.ndarray] | None = None) -> BlockInputs:
    """One pass over ``arrays`` in :meth:`LumitexelArrays.parts` of ``max_texels`` texels.

    ``truth_of`` gives the true reflectance (S, 3) of a block's samples (texels numbered within
    the block) and raises ValueError where the truth has no materials (then ``truth`` is None).

    Raises
    ------
    reconstruct.lumitexels.LumitexelError
        No texel has a training sample.
    """
    texel_parts: list[dict[str, np.ndarray]] = []
    train_parts: list[tuple[int, Lumitexels]] = []
    held_parts: list[tuple[int, Lumitexels]] = []
    first_held: int | None = None
    n_train = n_held = 0
    sums = None if truth_of is None else (_TruthSums(), _TruthSums())   # held-out, training
    for b in arrays.iter_blocks(max_texels):
        lt, held = b.lumitexels, b.held
        texel_parts.append({name: getattr(lt, name) for name in _TEXEL_FIELDS})   # not the block's samples
        n_train += int((~held).sum())
        n_held += int(held.sum())
        train_parts.append((b.first_texel, select_samples(lt, ~held & (lt.view == 0))))
        if held.any():   # the first held-out view with a sample: an earlier block had none of a smaller one
            k = int(lt.view[held].min())
            if first_held is None or k < first_held:
                first_held, held_parts = k, []
        held_parts.append((b.first_texel, select_samples(lt, held & (lt.view == (-1 if first_held is None else first_held)))))
        if sums is not None:
            try:
                true_r = np.asarray(truth_of(lt), float)
            except ValueError:
                sums = None
            else:
                sums[0].add(lt.reflectance[held], true_r[held])
                sums[1].add(lt.reflectance[~held], true_r[~held])
    if sum(len(p["position"]) for p in texel_parts) == 0:
        raise LumitexelError("no reflectance samples: no surface point is both seen and lit")
    truth = None
    if sums is not None:
        s = sums[0] if n_held else sums[1]
        truth = TruthFigures(s.measured.relative_rms, float(np.median(np.concatenate(s.ratios))),
                             Floor(s.floor.relative_rms, s.floor.trimmed_relative_rms()) if n_held else None)
    return BlockInputs(_join(texel_parts, train_parts, arrays.separated),
                       _join(texel_parts, held_parts, arrays.separated), n_train, n_held, truth)


def _join(texel_parts: list[dict[str, np.ndarray]], sample_parts: list[tuple[int, Lumitexels]],
          separated: bool) -> Lumitexels:
    """Every block's texels, and the given blocks' samples (texels offset by the block's first)."""
    kw = {name: np.concatenate([p[name] for p in texel_parts]) for name in _TEXEL_FIELDS}
    names = ("view", "wi", "wo", "reflectance", "weight", *(("diffuse", "specular") if separated else ()))
    for name in names:
        kw[name] = np.concatenate([getattr(p, name) for _, p in sample_parts])
    kw["texel"] = np.concatenate([p.texel + first for first, p in sample_parts])
    return Lumitexels(**kw)
