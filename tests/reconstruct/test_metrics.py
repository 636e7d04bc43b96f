"""reconstruct.metrics: the one relative RMS, against closed forms."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.metrics import relative_rms, trimmed_relative_rms


def test_relative_rms_closed_form():
    m = np.array([[1.0, 2.0, 2.0]])
    assert relative_rms(m * 1.1, m) == pytest.approx(0.1)          # a 10 % scale error
    assert relative_rms(m + [0.0, 0.0, 3.0], m) == pytest.approx(1.0)  # |e| = 3 = |m|
    assert np.isnan(relative_rms(np.zeros((0, 3)), np.zeros((0, 3))))


def test_relative_rms_per_axis_is_one_figure_per_image():
    truth = np.ones((2, 4, 3))
    pred = truth * np.array([1.2, 0.5])[:, None, None]
    np.testing.assert_allclose(relative_rms(pred, truth, axis=(1, 2)), [0.2, 0.5])


def test_trimmed_drops_the_worst_rows_only():
    m = np.ones((200, 3))
    p = m * 1.1
    p[0] = 100.0                                # one wild sample: 0.5 % of the rows
    assert relative_rms(p, m) > 5
    assert trimmed_relative_rms(p, m) == pytest.approx(0.1)


def test_shapes_must_match():
    with pytest.raises(ValueError, match=r"predicted has shape \(2,\), measured \(3,\)"):
        relative_rms(np.ones(2), np.ones(3))
