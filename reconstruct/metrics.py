"""Scores of a recovered model against measurements or ground truth.

The one definition of the relative RMS error every method, test and benchmark reports.
"""
from __future__ import annotations

import numpy as np

__all__ = ["relative_rms", "trimmed_relative_rms"]


def relative_rms(predicted, measured, axis=None):
    """``sqrt(sum (p - m)^2 / sum m^2)``: the RMS error relative to the RMS of ``measured``.

    Parameters
    ----------
    predicted, measured : array_like, same shape
        Any units (the ratio is unitless).
    axis : int or tuple of int, optional
        Sum over these axes only (one figure per remaining index); default: over everything.

    Returns
    -------
    float or ndarray
        NaN for an empty ``measured`` (with ``axis=None``).
    """
    m = np.asarray(measured, float)
    p = np.asarray(predicted, float)
    if p.shape != m.shape:
        raise ValueError(f"predicted has shape {p.shape}, measured {m.shape}: they must match")
    if axis is None:
        if m.size == 0:
            return float("nan")
        return float(np.sqrt(np.sum((p - m) ** 2) / max(np.sum(m ** 2), 1e-300)))
    return np.sqrt(np.sum((p - m) ** 2, axis=axis) / np.maximum(np.sum(m ** 2, axis=axis), 1e-300))


def trimmed_relative_rms(predicted, measured, trim: float = 0.01) -> float:
    """:func:`relative_rms` without the ``trim`` fraction of samples (rows) with the largest
    squared error: the pooled figure of a glossy object is carried by its few worst highlight
    samples (99 % of it by 1 % on the demo object), so it swings with the noise draw; this one
    does not."""
    m = np.asarray(measured, float).reshape(len(measured), -1)
    if m.size == 0:
        return float("nan")
    p = np.asarray(predicted, float).reshape(m.shape)
    err = np.sum((p - m) ** 2, axis=1)
    keep = err <= np.quantile(err, 1.0 - trim)
    return relative_rms(p[keep], m[keep])
