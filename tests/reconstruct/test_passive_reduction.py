"""``Bivariate.from_brdf``, the bivariate reduction passive reflectometry builds on (Romeiro et
al. 2008, Eq. 1's f-bar): means over the valid phi_d only, no NaN nodes, measured tables'
unknown cells skipped."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.brdf import Bivariate, CookTorrance, OrenNayar, TabulatedIsotropic, Ward
from reconstruct.coords import from_halfway_difference


def brute_mean(brdf, theta_h, theta_d, n=200_000):
    """Mean of ``brdf`` over the phi_d in [0, pi) with both directions above the horizon, by
    dense sampling (independent of the closed-form interval ``from_brdf`` uses)."""
    pd = (np.arange(n) + 0.5) / n * np.pi
    wi, wo = from_halfway_difference(theta_h, 0.0, theta_d, pd)
    ok = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    return brdf.evaluate(wi[ok], wo[ok]).mean(axis=0), ok.mean()


@pytest.mark.parametrize("node", [(25, 22), (29, 12), (12, 29), (6, 6)])
def test_node_is_the_mean_over_valid_phi_d(node):
    """Oren-Nayar varies with phi_d; nodes from fully valid to ~20 % valid phi_d: the node is
    the mean over the valid part to 0.2 % (a mean over all of [0, pi) with zeros below the
    horizon would be up to 5x too low)."""
    truth = OrenNayar(0.7, 0.5)
    table = Bivariate.from_brdf(truth, 32, 32, n_phi=256).table
    theta_h, theta_d = Bivariate.node_angles(32, 32)
    want, valid = brute_mean(truth, theta_h[node[0]], theta_d[node[1]])
    np.testing.assert_allclose(table[node], want, rtol=2e-3)
    assert valid > 0.15


@pytest.mark.parametrize("truth, rtol", [
    (Ward(0.05, 0.3, 0.08), 3e-2), (CookTorrance(0.1, 0.9, 0.2), 5e-3),
    (OrenNayar(0.5, 0.4), 5e-3)])
def test_no_nan_and_grazing_edges_are_inset_means(truth, rtol):
    """Every node is finite; the last node of each axis equals the valid-phi_d mean a quarter
    cell inside the grazing edge (0.5 %; original Ward 3 %: its 1/sqrt(cos_i cos_o) is singular
    at the ends of the valid phi_d interval, where 256 midpoints err by 1.9 %)."""
    table = Bivariate.from_brdf(truth, 16, 16, n_phi=256).table
    assert np.all(np.isfinite(table)) and np.all(table > 0)
    theta_h, theta_d = Bivariate.node_angles(16, 16)
    th_last = theta_h[-1] - 0.25 * (theta_h[-1] - theta_h[-2])
    td_last = theta_d[-1] - 0.25 * (theta_d[-1] - theta_d[-2])
    for (i, j), (th, td) in {(15, 4): (th_last, theta_d[4]), (4, 15): (theta_h[4], td_last),
                             (15, 15): (th_last, td_last)}.items():
        np.testing.assert_allclose(table[i, j], brute_mean(truth, th, td)[0], rtol=rtol)


def test_measured_table_with_invalid_cells_reduces_like_its_source():
    """A MERL-layout table of a Beckmann Cook-Torrance material (NaN below the horizon, zeros
    returned beside NaN cells) reduces to the analytic material's bivariate table: nodes up to
    6 degrees from the grazing edges within 5 %, median 0.05 % (measured 3.8 % / 0.009 %)."""
    truth = CookTorrance(0.2, 0.5, 0.15, distribution="beckmann")
    measured = TabulatedIsotropic.from_brdf(truth, (90, 90, 180))
    assert np.isnan(measured.table).any()
    got = Bivariate.from_brdf(measured).table
    want = Bivariate.from_brdf(truth).table
    rel = (np.abs(got - want) / want)[:30, :30]
    assert np.all(np.isfinite(got))
    assert rel.max() < 0.05 and np.median(rel) < 5e-4, (rel.max(), np.median(rel))


def test_defined_marks_unmeasured_cells():
    """``defined`` is False where a table has only NaN corners (evaluate's 0 is "unknown"),
    and below the horizon; True elsewhere."""
    table = np.full((4, 4, 4, 3), np.nan)
    table[:2] = 1.0  # theta_h nodes 0 and 1 measured (linear warp: 0 and 22.5 degrees)
    model = TabulatedIsotropic(table, theta_h_warp="linear")
    wi, wo = from_halfway_difference(np.radians([10.0, 60.0, 10.0]), 0.0,
                                     np.radians([20.0, 20.0, 85.0]), 0.0)
    np.testing.assert_array_equal(model.defined(wi, wo), [True, False, False])


def test_no_value_anywhere_raises():
    with pytest.raises(ValueError, match="no value anywhere"):
        Bivariate.from_brdf(TabulatedIsotropic(np.full((2, 2, 2, 3), np.nan)))
