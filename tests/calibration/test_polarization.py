"""Polarization separation against synthetic diffuse/specular ground truth."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.errors import DegenerateFit, TooFewViews
from calibration.polarization import fit_polarization, separate_parallel_crossed
from reconstruct.metrics import relative_rms


def _truth(rng, shape=(120, 160, 3)):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    D = (0.3 + 0.2 * np.sin(xx / 13.0) ** 2)[..., None] * np.array([1.0, 0.7, 0.4])
    S = np.exp(-((xx - 80) ** 2 + (yy - 60) ** 2) / (2 * 25.0 ** 2))[..., None] * np.array([1.0, 1.0, 1.0])
    return D.astype(np.float32), S.astype(np.float32)


def _observe(D, S, theta_deg, rng, phase_deg=0.0, noise=0.002):
    I = D / 2 + S * np.cos(np.radians(theta_deg - phase_deg)) ** 2
    return I + rng.normal(0, noise, I.shape)


def test_two_image_separation_within_2_percent():
    rng = np.random.default_rng(0)
    D, S = _truth(rng)
    sep = separate_parallel_crossed(_observe(D, S, 0, rng), _observe(D, S, 90, rng), read_sigma=0.002)
    assert relative_rms(sep.diffuse, D) < 0.02
    assert relative_rms(sep.specular, S) < 0.02
    assert sep.specular.min() >= 0
    # the mask finds the lobe and rejects the specular-free corners
    assert sep.specular_mask[60, 80].all() and sep.specular_mask[:5, :5].mean() < 0.01


@pytest.mark.parametrize("angles", [[0, 45, 90, 135], [0, 30, 60, 90, 120, 150], [10, 70, 130]])
def test_n_angle_fit_within_2_percent(angles):
    rng = np.random.default_rng(1)
    D, S = _truth(rng)
    stack = np.stack([_observe(D, S, a, rng, phase_deg=12.0) for a in angles])
    fit = fit_polarization(stack, angles)
    assert fit.diffuse.shape == D.shape and fit.diffuse.dtype == np.float32
    assert relative_rms(fit.diffuse, D) < 0.02
    assert relative_rms(fit.specular, S) < 0.02
    strong = S[..., 0] > 0.5
    assert np.abs(fit.phase_deg[..., 0][strong] - 12.0).max() < 1.0
    dop_true = S / (D + S)
    assert np.abs(fit.dop - dop_true)[strong].max() < 0.02


def test_bad_angle_sets():
    rng = np.random.default_rng(2)
    D, S = _truth(rng, (8, 8))
    with pytest.raises(TooFewViews):
        fit_polarization(np.stack([D, D]), [0, 90])
    with pytest.raises(DegenerateFit, match="distinct"):
        fit_polarization(np.stack([D, D, D]), [0, 180, 360])
    with pytest.raises(ValueError, match="angles_deg"):
        fit_polarization(np.stack([D, D, D]), [0, 45])
    with pytest.raises(ValueError, match="crossed"):
        separate_parallel_crossed(D, D[:4])
