"""The modes-of-variation prior of passive reflectometry (``reconstruct.passive_modes``): what
``learn_modes`` learns, against numpy's own decomposition, and the MAP solve against known
coefficients. (On MERL: ``test_passive_merl.py``.)"""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from reconstruct.brdf import Bivariate, Lambertian
from reconstruct.distant import shade_distant, sphere_normals
from reconstruct.passive import MODES_NOISE, PassiveInputError, PassiveWarning, passive_reflectometry
from reconstruct.passive_modes import ModesPrior, learn_modes, solve_modes


def test_learn_modes_is_the_log_library_principal_components():
    """Modes orthonormal; the mean is the mean of log(f + offset) over materials and channels;
    each variance is the library's variance along its mode (to 1e-10), in decreasing order."""
    rng = np.random.default_rng(1)
    tables = rng.uniform(0.01, 2.0, size=(6, 5, 4, 3))
    prior = learn_modes([Bivariate(t) for t in tables], (5, 4), n_modes=4, offset=0.01)
    x = np.log(np.moveaxis(tables, -1, 1).reshape(18, 20) + 0.01)
    assert np.allclose(prior.mean, x.mean(axis=0), atol=1e-12)
    assert np.allclose(prior.modes @ prior.modes.T, np.eye(4), atol=1e-10)
    proj = (x - prior.mean) @ prior.modes.T
    assert np.allclose(prior.variances, proj.var(axis=0, ddof=1), rtol=1e-10)
    assert np.all(np.diff(prior.variances) <= 0)
    rest = (x - prior.mean) - proj @ prior.modes
    assert np.allclose(prior.residual_variances, np.maximum(
        rest.var(axis=0, ddof=1), 1e-2 * rest.var(axis=0, ddof=1).mean()), rtol=1e-8)


def test_modes_precision_is_the_inverse_covariance_with_the_shift_free():
    """``ModesPrior.precision`` (Woodbury) against numpy's inverse of the full covariance
    modes^T diag(var) modes + diag(remainder) + S 1 1^T with a shift variance S = 1e8 (to
    1e-6 of its largest entry); the all-ones direction (a brightness shift) costs nothing;
    with next to no remainder variance (1e-12) ``split`` returns the shift and coefficients a
    table was made from."""
    rng = np.random.default_rng(2)
    tables = rng.uniform(0.01, 2.0, size=(8, 4, 5, 3))
    prior = learn_modes([Bivariate(t) for t in tables], (4, 5), n_modes=5, offset=0.01)
    C = prior.modes.T @ np.diag(prior.variances) @ prior.modes + np.diag(prior.residual_variances)
    Q = prior.precision()
    assert np.allclose(Q, np.linalg.inv(C + 1e8 * np.ones((20, 20))), atol=1e-6 * np.abs(Q).max())
    assert np.abs(Q @ np.ones(20)).max() < 1e-9 * np.abs(Q).max()
    c = rng.normal(0, 0.5, 5)
    tight = ModesPrior(prior.mean, prior.modes, prior.variances, np.full(20, 1e-12), (4, 5), 0.01)
    shift, coefficients = tight.split(prior.mean + 0.3 + c @ prior.modes)
    assert shift == pytest.approx(0.3, abs=1e-9) and np.allclose(coefficients, c, atol=1e-9)


@pytest.mark.parametrize("kwargs, match", [({"n_modes": 18}, "n_modes"),
                                           ({"offset": 0.0}, "offset")])
def test_learn_modes_names_bad_arguments(kwargs, match):
    tables = [Bivariate(np.full((4, 4, 3), a)) for a in (0.1, 0.2, 0.3, 0.4, 0.5, 0.6)]
    with pytest.raises(ValueError, match=match):
        learn_modes(tables, (4, 4), **kwargs)


def test_solve_modes_recovers_known_coefficients():
    """Data made from known coefficients and a log-brightness shift of 0.7 through a random
    full-rank A (a remainder variance of 1e-9: next to none outside the modes): with a
    negligible weight the solve returns them (1e-6) and f; with a strong weight the
    coefficients shrink towards 0 but the shift, which is not penalised, stays."""
    rng = np.random.default_rng(4)
    n, k = 30, 5
    modes = np.linalg.qr(rng.normal(size=(n, k)))[0].T
    prior = ModesPrior(rng.normal(-2, 0.3, n), modes, np.full(k, 0.2), np.full(n, 1e-9), (5, 6),
                       1e-3)
    c_true = rng.normal(0, 0.4, k)
    f_true = prior.values(c_true, 0.7)
    A = rng.uniform(0, 1, size=(80, n))
    b = A @ f_true
    sol = solve_modes(prior, A.T @ A, A.T @ b, b @ b, 1e-14)
    assert sol.converged
    assert np.allclose(sol.coefficients, c_true, atol=1e-6) and sol.shift == pytest.approx(0.7)
    assert np.allclose(sol.f, f_true, rtol=1e-6)
    strong = solve_modes(prior, A.T @ A, A.T @ b, b @ b, 1e3)
    assert np.linalg.norm(strong.coefficients) < 0.1 * np.linalg.norm(c_true)


def test_passive_refuses_cross_validation_and_a_foreign_grid_with_modes():
    prior = learn_modes([Lambertian(a) for a in (0.1, 0.3, 0.5, 0.7)], (8, 8), n_modes=3)
    normals = np.zeros((20, 20, 3))
    normals[..., 2] = -1
    args = (np.ones((20, 20, 3)), normals, np.ones((20, 20), bool),
            (np.array([[0.0, 0, -1]]), np.ones((1, 3)), np.ones(1)))
    with pytest.raises(PassiveInputError, match="lam='cv'"):
        passive_reflectometry(*args, grid=(8, 8), prior=prior, lam="cv")
    with pytest.raises(PassiveInputError, match="learned on grid"):
        passive_reflectometry(*args, grid=(16, 16), prior=prior)


def test_modes_weight_is_per_pixel():
    """With a ``ModesPrior`` the default weight is ``MODES_NOISE`` / observations (a fixed noise
    per pixel, as the paper's plain sum over pixels), so a sphere with ~4x the pixels gets ~1/4
    the weight; the recovered albedo of a Lambertian sphere under a sky of 200 sources stays
    within 2 % of the truth at both sizes."""
    prior = learn_modes([Lambertian(a) for a in (0.1, 0.3, 0.5, 0.7)], (8, 8), n_modes=3)
    d = np.random.default_rng(3).normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sky = (d, np.ones((200, 3)), np.full(200, 4 * np.pi / 200))
    truth = Lambertian([0.2, 0.4, 0.6])
    for size in (24, 48):
        normals, mask = sphere_normals(size)
        image = np.zeros(normals.shape)
        image[mask] = shade_distant(truth, normals[mask], *sky)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PassiveWarning)
            fit = passive_reflectometry(image, normals, mask, sky, grid=(8, 8), prior=prior)
        assert fit.lam == pytest.approx(MODES_NOISE / fit.adequacy.n_observations, rel=1e-12)
        assert np.allclose(fit.brdf.table[2:6, 2:6], np.array([0.2, 0.4, 0.6]) / np.pi, rtol=0.02), size
