"""Tabulated BRDFs: exact trilinear/bilinear interpolation, node values, accuracy on smooth
analytic BRDFs, invalid entries, reciprocity, validation."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from reconstruct.brdf import Bivariate, CookTorrance, TabulatedIsotropic, Ward
from reconstruct.coords import from_halfway_difference, halfway_difference

HALF_PI = np.pi / 2


def hemisphere(rng, n):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2])
    return v


@pytest.fixture
def pairs():
    rng = np.random.default_rng(21)
    return hemisphere(rng, 20000), hemisphere(rng, 20000)


@pytest.mark.parametrize("warp", ["sqrt", "linear"])
def test_trilinear_matches_scipy_regular_grid_interpolator(pairs, warp):
    wi, wo = pairs
    rng = np.random.default_rng(22)
    table = rng.uniform(0.0, 2.0, (6, 5, 8, 3))
    model = TabulatedIsotropic(table, theta_h_warp=warp)
    th, _, td, pd = halfway_difference(wi, wo)
    u = th / HALF_PI
    x = np.clip((np.sqrt(u) if warp == "sqrt" else u) * 6, 0, 5)
    y = np.clip(td / HALF_PI * 5, 0, 4)
    z = np.mod(pd, np.pi) / np.pi * 8
    periodic = np.concatenate([table, table[:, :, :1]], axis=2)  # node 8 == node 0
    rgi = RegularGridInterpolator((np.arange(6), np.arange(5), np.arange(9)), periodic)
    np.testing.assert_allclose(model.evaluate(wi, wo), rgi(np.stack([x, y, z], 1)), rtol=1e-12)


def test_node_values_are_reproduced():
    rng = np.random.default_rng(23)
    table = rng.uniform(0.0, 1.0, (10, 9, 12, 3))
    model = TabulatedIsotropic(table)
    th, td, pd = np.meshgrid(*model.node_angles(), indexing="ij")
    th, td, pd = th.ravel(), td.ravel(), pd.ravel()
    wi, wo = from_halfway_difference(th, 0.3, td, pd)
    # phi_d is undefined at theta_h = 0 (isotropy makes a real table constant there) and at
    # theta_d = 0; a random table is not, so those nodes are left out
    ok = (wi[:, 2] > 0) & (wo[:, 2] > 0) & (th > 0) & (td > 0)
    np.testing.assert_allclose(model.evaluate(wi, wo)[ok], table.reshape(-1, 3)[ok], atol=1e-9)


def test_tabulated_is_reciprocal(pairs):
    wi, wo = pairs
    model = TabulatedIsotropic(np.random.default_rng(24).uniform(0, 1, (8, 8, 16, 3)))
    np.testing.assert_allclose(model.evaluate(wi, wo), model.evaluate(wo, wi), rtol=1e-9)


def test_interpolates_a_smooth_analytic_brdf(pairs):
    """GGX Cook-Torrance (alpha = 0.3) on a (45, 45, 90) table, both cosines > 0.2:
    median relative error < 0.5 %, maximum < 3 % (measured 0.17 % / 1.3 %)."""
    wi, wo = pairs
    truth = CookTorrance(0.2, 0.8, 0.3)
    model = TabulatedIsotropic.from_brdf(truth, (45, 45, 90))
    ok = (wi[:, 2] > 0.2) & (wo[:, 2] > 0.2)
    rel = (np.abs(model.evaluate(wi, wo) - truth.evaluate(wi, wo)) / truth.evaluate(wi, wo))[ok]
    assert np.median(rel) < 5e-3 and rel.max() < 3e-2, (np.median(rel), rel.max())


def test_interpolates_at_merl_resolution(pairs):
    """(90, 90, 180): median < 0.1 %, max < 0.6 % (measured 0.04 % / 0.38 %)."""
    wi, wo = pairs
    truth = CookTorrance(0.2, 0.8, 0.3)
    model = TabulatedIsotropic.from_brdf(truth)
    ok = (wi[:, 2] > 0.2) & (wo[:, 2] > 0.2)
    rel = (np.abs(model.evaluate(wi, wo) - truth.evaluate(wi, wo)) / truth.evaluate(wi, wo))[ok]
    assert np.median(rel) < 1e-3 and rel.max() < 6e-3, (np.median(rel), rel.max())


def test_invalid_entries_are_skipped():
    table = np.ones((4, 4, 4, 3))
    table[..., 0] = 2.0
    table[1, 1, :, 1] = np.nan  # green invalid on a whole phi_d ring
    table[2:, 2:, :, :] = np.nan  # a fully invalid corner block
    model = TabulatedIsotropic(table, theta_h_warp="linear")
    # inside cell (1..2, 1..2): green's valid neighbours are all 1, red all 2
    th, td = 1.5 / 4 * HALF_PI, 1.5 / 4 * HALF_PI
    wi, wo = from_halfway_difference(np.array([th]), 0.0, np.array([td]), 0.7)
    np.testing.assert_allclose(model.evaluate(wi, wo), [[2.0, 1.0, 1.0]], rtol=1e-12)
    # beyond the last valid nodes everything is NaN: zero, never NaN
    wi, wo = from_halfway_difference(np.array([3.2 / 4 * HALF_PI]), 0.0,
                                     np.array([0.2 * HALF_PI]), 0.7)
    table2 = np.full((4, 4, 4, 3), np.nan)
    table2[0] = 1.0
    f = TabulatedIsotropic(table2, theta_h_warp="linear").evaluate(wi, wo)
    assert np.all(np.isfinite(f)) and np.all(f == 0)


def test_from_brdf_marks_below_horizon_nodes_invalid():
    """At phi_d = 0 the pair lies in the incidence plane with wi at theta_h + theta_d from the
    normal: the node is invalid (NaN) exactly when theta_h + theta_d > pi/2."""
    model = TabulatedIsotropic.from_brdf(CookTorrance(0.3, 0.04, 0.3), (12, 12, 24))
    th, td, _ = model.node_angles()
    total = th[:, None] + td[None, :]
    invalid = np.isnan(model.table[:, :, 0, 0])
    assert np.array_equal(invalid[np.abs(total - HALF_PI) > 1e-9],
                          (total > HALF_PI)[np.abs(total - HALF_PI) > 1e-9])
    assert invalid.any() and not invalid.all()


def test_bivariate_interpolates_a_bivariate_brdf(pairs):
    """The bounded Ward lobe depends on (theta_h, theta_d) only, so a 64 x 64 (t, s) table
    reproduces it: median relative error < 1e-4, maximum < 4 % (measured 2e-6 / 2.9 %)."""
    wi, wo = pairs
    truth = Ward(0.2, 0.3, 0.2, variant="bounded")
    model = Bivariate.from_brdf(truth, 64, 64)
    ok = (wi[:, 2] > 0.2) & (wo[:, 2] > 0.2)
    rel = (np.abs(model.evaluate(wi, wo) - truth.evaluate(wi, wo)) / truth.evaluate(wi, wo))[ok]
    assert np.median(rel) < 1e-4 and rel.max() < 4e-2, (np.median(rel), rel.max())


def test_bivariate_bilinear_in_s_t_and_weights(pairs):
    wi, wo = pairs
    rng = np.random.default_rng(25)
    table = rng.uniform(0, 1, (7, 9, 3))
    model = Bivariate(table)
    th, _, td, _ = halfway_difference(wi, wo)
    s, t = td / HALF_PI, np.sqrt(np.minimum(th, HALF_PI) / HALF_PI)
    rgi = RegularGridInterpolator((np.linspace(0, 1, 7), np.linspace(0, 1, 9)), table)
    f = model.evaluate(wi, wo)
    np.testing.assert_allclose(f, rgi(np.stack([t, s], 1)), rtol=1e-12)
    index, weight = model.interpolation_weights(wi, wo)
    assert index.shape == weight.shape == (len(wi), 4)
    np.testing.assert_allclose(weight.sum(1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.einsum("nc,nck->nk", weight, table.reshape(-1, 3)[index]), f,
                               rtol=1e-12)


def test_bivariate_ignores_rotation_about_the_halfway_vector():
    model = Bivariate(np.random.default_rng(26).uniform(0, 1, (8, 8, 3)))
    pd = np.linspace(0, 2 * np.pi, 13)
    wi, wo = from_halfway_difference(0.3, 0.4, 0.5, pd)
    f = model.evaluate(wi, wo)
    np.testing.assert_allclose(f, np.tile(f[:1], (13, 1)), rtol=1e-10)


@pytest.mark.parametrize("factory, match", [
    (lambda: TabulatedIsotropic(np.ones((4, 4, 3))), "TabulatedIsotropic.table must have shape"),
    (lambda: TabulatedIsotropic(-np.ones((2, 2, 2, 3))), "negative"),
    (lambda: TabulatedIsotropic(np.full((2, 2, 2, 3), np.inf)), "infinite"),
    (lambda: TabulatedIsotropic(np.ones((2, 2, 2, 3)), theta_h_warp="log"), "theta_h_warp"),
    (lambda: Bivariate(np.ones((4, 4, 2))), "Bivariate.table must have shape"),
    (lambda: TabulatedIsotropic.from_brdf(Ward(), (4, 4)), "shape must be three"),
    (lambda: Bivariate.from_brdf(Ward(), 0, 4), "n_t, n_s, n_phi"),
])
def test_invalid_tables_raise(factory, match):
    with pytest.raises(ValueError, match=match):
        factory()
