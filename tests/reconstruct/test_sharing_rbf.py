"""reconstruct.sharing.rbf: the linear RBF interpolant, greedy centres, duplicates, bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator

from reconstruct.sharing import RbfModel, SharingError, fit_rbf


def _smooth(x):
    return np.stack([np.sin(2 * x[:, 0]) + x[:, 1] ** 2, np.cos(x[:, 2]) * x[:, 0]], axis=1)


@pytest.mark.parametrize("seed, dim", [(0, 3), (1, 5)])
def test_all_centres_match_scipy_interpolator(seed, dim):
    """With every sample a centre the fit is the unique interpolant scipy also computes."""
    rng = np.random.default_rng(seed)
    x = rng.random((300, dim))
    y = _smooth(x)
    scale = np.linspace(0.3, 1.0, dim)
    fit = fit_rbf(x, y, scale=scale, max_centers=300, rng=seed)
    ref = RBFInterpolator(x * scale, y, kernel="linear", degree=1)
    xt = rng.random((2000, dim))
    # float32 distances: ~1e-4 of the value range (stated tolerance of the fast evaluation)
    np.testing.assert_allclose(fit.model(xt), ref(xt * scale), atol=2e-4)
    # at a centre the float32 squared distance's rounding (~1e-7 |x|^2) becomes sqrt(1e-7) |x|
    np.testing.assert_allclose(fit.model(x), y, atol=1e-3)  # interpolates its centres


@pytest.mark.parametrize("seed", [2, 3])
def test_affine_function_is_reproduced_exactly(seed):
    """The degree-1 polynomial makes any affine function exact with any centre count."""
    rng = np.random.default_rng(seed)
    x = rng.random((4000, 4))
    a, b = rng.normal(size=4), rng.normal()
    fit = fit_rbf(x, x @ a + b, max_centers=50, rng=seed)
    xt = rng.random((500, 4))
    np.testing.assert_allclose(fit.model(xt)[:, 0], xt @ a + b, atol=1e-5)
    assert np.abs(fit.model.coefficients).max() < 1e-6


def test_blocked_float32_evaluation_matches_float64_formula():
    rng = np.random.default_rng(4)
    c = rng.random((700, 5))
    model = RbfModel(c, rng.normal(size=(700, 3)), rng.normal(size=(6, 3)),
                     np.array([0.3, 0.3, 1, 1, 0.5]), c.mean(axis=0))
    p = rng.random((3000, 5))
    x, cx = (p - model.shift) * model.scale, (c - model.shift) * model.scale
    dist = np.linalg.norm(x[:, None] - cx[None], axis=2)
    want = dist @ model.coefficients + x @ model.polynomial[1:] + model.polynomial[0]
    got = model(p, block=256, workers=2)
    # relative to sum |lambda| |distance| (the float32 rounding scale)
    bound = 1e-5 * (np.abs(dist) @ np.abs(model.coefficients)).max()
    assert np.abs(got - want).max() < bound


@pytest.mark.parametrize("seed", [5, 6])
def test_greedy_reaches_tolerance_and_residual_falls(seed):
    rng = np.random.default_rng(seed)
    x = rng.random((2000, 3))
    y = _smooth(x)
    w = rng.uniform(0.2, 1.0, 2000)
    calls = []
    fit = fit_rbf(x, y, weight=w, tol=5e-3, max_centers=1500, rng=seed,
                  progress=lambda done, total: calls.append((done, total)))
    assert fit.converged
    assert [c[0] for c in calls] == list(fit.history[:, 0].astype(int))
    err = np.abs(fit.model(x) - y).max(axis=1) * w  # recomputed here, not the fit's history
    assert err.max() <= 5e-3
    rms = fit.history[:, 1]
    assert rms[-1] < 0.1 * rms[0]
    assert len(fit.order) < 1500
    # refit with the first centres reproduces the greedy history's residual at that count
    m = int(fit.history[2, 0])
    early = np.abs(fit.refit(m)(x) - y).max(axis=1) * w
    assert early.max() == pytest.approx(fit.history[2, 2], rel=1e-3)


def test_exact_duplicates_are_merged():
    rng = np.random.default_rng(7)
    x = rng.random((400, 3))
    y = _smooth(x)[:, :1]
    xd = np.concatenate([x, x[:100]])
    yd = np.concatenate([y, y[:100] + 0.2])  # conflicting repeated measurements
    fit = fit_rbf(xd, yd, max_centers=400)
    assert fit.n_merged == 100
    np.testing.assert_allclose(fit.model(x[:100]), y[:100] + 0.1, atol=1e-3)  # their mean
    # scipy's interpolator fails silently on the same input (the known RBF failure)
    with np.errstate(all="ignore"):
        try:
            coef = np.abs(RBFInterpolator(xd, yd, kernel="linear", degree=1)._coeffs).max()
        except np.linalg.LinAlgError:
            coef = np.inf
    assert coef > 1e6 > np.abs(fit.model.coefficients).max()


def test_near_duplicates_never_both_centres():
    rng = np.random.default_rng(8)
    x = rng.random((300, 3))
    y = _smooth(x)[:, :1]
    xd = np.concatenate([x, x + 1e-10])
    yd = np.concatenate([y, y + 0.2])
    fit = fit_rbf(xd, yd, max_centers=600, min_separation=1e-6)
    assert fit.n_merged == 0
    assert fit.model.n_centers <= 300
    assert np.abs(fit.model.coefficients).max() < 1e4
    pred = fit.model(x)
    assert np.all((pred > y - 1e-3) & (pred < y + 0.2 + 1e-3))


def test_near_pairs_are_merged_into_their_weighted_mean_and_chains_are_not():
    """Two measurements of one value a little apart (a reciprocal pair's two orderings): with
    ``merge_radius`` the interpolant goes through their weight^2-weighted mean at their
    weighted mean position, the least-squares estimate, instead of whichever became a centre."""
    rng = np.random.default_rng(10)
    x = rng.random((200, 3))
    y = _smooth(x)[:, :1]
    step = 1e-3 * np.array([1.0, 0.0, 0.0])
    w1, w2 = rng.uniform(0.5, 2.0, (2, 200))
    xd = np.concatenate([x, x + step])
    yd = np.concatenate([y, y + 0.2])
    fit = fit_rbf(xd, yd, weight=np.concatenate([w1, w2]), max_centers=400, merge_radius=2e-3)
    assert fit.n_paired == 200 and len(fit.points) == 200 and "200 near pairs" in fit.report()
    a, b = w1[:, None] ** 2, w2[:, None] ** 2
    mean_x = (a * x + b * (x + step)) / (a + b)
    np.testing.assert_allclose(fit.model(mean_x), (a * y + b * (y + 0.2)) / (a + b),
                               atol=1e-3)  # float32 distances; each ordering is >= 0.012 away
    np.testing.assert_allclose(fit.weight, np.sqrt(w1 ** 2 + w2 ** 2))
    # a chain a - b - c (spacings 1 and 1.5 x 1e-3 < radius): a and b are each other's nearest and
    # merge; c's nearest (b) is taken, so c stays a sample of its own
    chain = np.array([[0.5, 0.5, 0.5], [0.501, 0.5, 0.5], [0.5025, 0.5, 0.5]])
    fit = fit_rbf(np.concatenate([x, chain]), np.concatenate([y, [[1.0], [2.0], [3.0]]]),
                  max_centers=300, merge_radius=2e-3)
    assert fit.n_paired == 1
    np.testing.assert_allclose(fit.model(np.array([[0.5005, 0.5, 0.5], chain[2]])),
                               [[1.5], [3.0]], atol=1e-2)  # a steep step: float32 distances


@pytest.mark.parametrize("kwargs, name", [
    (dict(points=np.full((10, 3), np.nan), values=np.ones(10)), "points"),
    (dict(points=np.random.default_rng(0).random((10, 3)), values=[np.nan] * 10), "values"),
    (dict(points=np.random.default_rng(0).random((4, 3)), values=np.ones(4)), "points"),
    (dict(points=np.random.default_rng(0).random((10, 3)), values=np.ones(9)), "values"),
    (dict(points=np.random.default_rng(0).random((10, 3)), values=np.ones(10), scale=[1, 0, 1]),
     "scale"),
    (dict(points=np.random.default_rng(0).random((10, 3)), values=np.ones(10), weight=-np.ones(10)),
     "weight"),
    (dict(points=np.random.default_rng(0).random((10, 3)), values=np.ones(10), merge_radius=-1.0),
     "merge_radius"),
])
def test_bad_input_names_the_argument(kwargs, name):
    with pytest.raises(SharingError, match=name):
        fit_rbf(**kwargs)


def test_hyperplane_samples_are_refused():
    rng = np.random.default_rng(9)
    x = rng.random((100, 3))
    x[:, 2] = 0.5  # all at one w: the w coefficient of the polynomial is undetermined
    with pytest.raises(SharingError, match="points lie in a 2-dimensional"):
        fit_rbf(x, np.ones(100))


def test_duplicates_of_too_few_points_are_refused():
    """Many samples, but only four distinct points: too few for a 3-D degree-1 polynomial."""
    x = np.repeat(np.eye(3)[[0, 1, 2, 0]] + np.arange(4)[:, None] * 0.1, 50, axis=0)
    with pytest.raises(SharingError, match="points: 4 distinct samples"):
        fit_rbf(x, np.ones(len(x)))
