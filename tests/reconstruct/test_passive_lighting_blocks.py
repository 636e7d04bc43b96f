"""Passive reflectometry's lighting matrix over blocks of observations (issue 21): the rows of a
block equal the whole build's rows, and the normal equations summed over blocks (run as on a
cluster: pickled, in reverse order) equal those of the whole matrix to 1e-9, with and without
per-observation weights, and so do the predicted radiances L f. Random sources and
normals, an orthographic and a perspective (per-point view) camera."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from reconstruct.passive_lighting import (block_sums, lighting_matrix, lighting_predictions,
                                         lighting_sums)

GRID = (12, 9)


def _problem(n_normals=300, n_sources=800, seed=4):
    g = np.random.default_rng(seed)
    n = g.normal(size=(n_normals, 3))
    n[:, 2] = -np.abs(n[:, 2]) - 0.3   # facing an orthographic camera along +z
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = g.normal(size=(n_sources, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    views = n * 0.3 + np.array([0.1, -0.2, -1.0])
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    return (n, g.uniform(0, 1, (n_normals, 3)), d, g.uniform(0, 2, (n_sources, 3)),
            g.uniform(0.5, 1.5, n_sources) * 4 * np.pi / n_sources, views)


def _as_on_a_cluster(fn, args):
    out = [pickle.loads(pickle.dumps(fn(*pickle.loads(pickle.dumps(a))))) for a in reversed(args)]
    return out[::-1]


@pytest.mark.parametrize("perspective", [False, True])
def test_lighting_rows_and_normal_equations_over_blocks_equal_the_whole_build(perspective):
    n, values, d, E, omega, views = _problem()
    view = views if perspective else (0.0, 0.0, -1.0)
    L = lighting_matrix(n, d, E, omega, view_dirs=view, grid=GRID)
    # a row depends on its normal alone: a block's rows are the whole build's, bit for bit
    rows = slice(37, 74)
    block = lighting_matrix(n[rows], d, E, omega, view_dirs=views[rows] if perspective else view, grid=GRID)
    np.testing.assert_array_equal(block, L[:, rows])
    for block_rows in (37, len(n)):
        s = lighting_sums(n, values, d, E, omega, view_dirs=view, grid=GRID, block_rows=block_rows,
                          map_blocks=_as_on_a_cluster)
        assert s.rows == len(n)
        for c in range(3):
            Lc = L[c].astype(np.float64)
            np.testing.assert_allclose(s.gram[c], Lc.T @ Lc, rtol=1e-9, atol=1e-12 * np.abs(Lc.T @ Lc).max())
            np.testing.assert_allclose(s.rhs[c], Lc.T @ values[:, c], rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(s.column[c], Lc.sum(axis=0), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(s.value_sq, (values ** 2).sum(axis=0), rtol=1e-12)


def test_lighting_sums_name_bad_input():
    n, values, d, E, omega, views = _problem(20, 50)
    with pytest.raises(ValueError, match=r"values must be finite with shape \(20, 3\)"):
        lighting_sums(n, values[:19], d, E, omega, grid=GRID)
    with pytest.raises(ValueError, match=r"view_dirs must have shape \(3,\) or \(20, 3\)"):
        lighting_sums(n, values, d, E, omega, view_dirs=views[:5], grid=GRID)
    with pytest.raises(ValueError, match="block_rows must be a positive integer"):
        lighting_sums(n, values, d, E, omega, grid=GRID, block_rows=0)
    # one block's sums add: two halves make the whole
    halves = [block_sums(n[s], values[s], d, E, omega, (0.0, 0.0, -1.0), GRID) for s in (slice(0, 8), slice(8, 20))]
    whole = block_sums(n, values, d, E, omega, (0.0, 0.0, -1.0), GRID)
    total = halves[0] + halves[1]
    assert total.rows == 20
    np.testing.assert_allclose(total.gram, whole.gram, rtol=1e-12, atol=1e-15 * np.abs(whole.gram).max())


def test_weighted_sums_and_predictions_over_blocks_equal_the_whole_matrix():
    """Per-observation, per-channel weights W: the blocks' sums are L^T W L, L^T W I and
    I^T W I of the whole matrix (column sums unweighted) to 1e-9; ``lighting_predictions`` is
    L f for a random table, over blocks run as on a cluster; bad weights and tables are named."""
    n, values, d, E, omega, views = _problem()
    w = np.random.default_rng(7).uniform(0, 2, values.shape)
    L = lighting_matrix(n, d, E, omega, view_dirs=views, grid=GRID)
    s = lighting_sums(n, values, d, E, omega, view_dirs=views, grid=GRID, block_rows=37, weights=w,
                      map_blocks=_as_on_a_cluster)
    table = np.random.default_rng(8).uniform(0, 1, (*GRID, 3))
    pred = lighting_predictions(n, table, d, E, omega, view_dirs=views, grid=GRID, block_rows=37,
                                map_blocks=_as_on_a_cluster)
    for c in range(3):
        Lc = L[c].astype(np.float64)
        G = (Lc * w[:, c, None]).T @ Lc
        np.testing.assert_allclose(s.gram[c], G, rtol=1e-9, atol=1e-12 * np.abs(G).max())
        np.testing.assert_allclose(s.rhs[c], Lc.T @ (w[:, c] * values[:, c]), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(s.column[c], Lc.sum(axis=0), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(pred[:, c], Lc @ table[..., c].ravel(), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s.value_sq, (w * values ** 2).sum(axis=0), rtol=1e-12)
    with pytest.raises(ValueError, match=r"weights must be finite, >= 0, with shape \(300, 3\)"):
        lighting_sums(n, values, d, E, omega, grid=GRID, weights=-w)
    with pytest.raises(ValueError, match="table must hold 12 x 9 x 3"):
        lighting_predictions(n, table[:5], d, E, omega, grid=GRID)
