"""The exemplar fill of passive reflectometry's unconstrained nodes (``reconstruct.
passive_exemplars``): the nearest member and its fitted slope and offset, k by leave-one-out
on a library of known clusters, and the fill inside ``passive_reflectometry``. (On MERL:
benchmarks/zoo.py ``--exemplars``, docs/zoo.md.)"""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from reconstruct.brdf import Bivariate, Lambertian, OrenNayar
from reconstruct.distant import shade_distant, sphere_normals
from reconstruct.passive import PassiveInputError, PassiveWarning, passive_reflectometry
from reconstruct.passive_exemplars import (ExemplarLibrary, choose_k, fill_unconstrained,
                                           nearest_exemplars)
from reconstruct.passive_modes import learn_modes


def test_nearest_exemplar_is_the_member_a_table_was_made_from():
    """A log table made from member 3 as 1.5 x + 0.2 (channel 0), 0.8 x - 1 (1), x (2): the
    nearest member is 3 at distance 0 (1e-10), its fitted table is the made one (1e-10) even
    where the node weights are 0, and the next member is further by far."""
    rng = np.random.default_rng(5)
    library = rng.normal(-2, 1, size=(7, 3, 40))
    a, b = np.array([1.5, 0.8, 1.0]), np.array([0.2, -1.0, 0.0])
    x = a[:, None] * library[3] + b[:, None]
    w = np.where(np.arange(40) < 25, rng.uniform(0.2, 1.0, 40), 0.0)
    ex = nearest_exemplars(x, w, library, 2)
    assert ex.index[0] == 3 and ex.distance[0] < 1e-10 and ex.distance[1] > 0.1
    np.testing.assert_allclose(ex.fitted[0], x, atol=1e-10)
    assert ex.weights.sum() == pytest.approx(1.0) and ex.weights[0] > 0.999


def test_choose_k_finds_the_cluster_size():
    """Six clusters of four members (a centre plus noise of 0.05 RMS, clusters 1 apart, log
    units): predicting a member's unseen nodes from the others' is best with its three
    siblings averaged (k = 3): fewer keep more noise, more reach another cluster."""
    rng = np.random.default_rng(6)
    centres = rng.normal(0, 1, size=(6, 3, 60))
    library = np.repeat(centres, 4, axis=0) + rng.normal(0, 0.05, size=(24, 3, 60))
    w = np.where(np.arange(60) < 40, 1.0, 0.0)
    assert choose_k(library, w, candidates=(1, 2, 3, 5, 8)) == 3


def test_fill_replaces_only_the_unconstrained_nodes_with_the_exemplars():
    """k = 1 from a library holding the truth's table: the constrained nodes keep the
    recovered values exactly; the others get the truth's (1e-9 relative)."""
    rng = np.random.default_rng(7)
    tables = rng.uniform(0.05, 1.0, size=(5, 4, 6, 3))
    library = ExemplarLibrary.from_brdfs([Bivariate(t) for t in tables], (4, 6), k=1)
    coverage = rng.uniform(0.2, 2.0, size=(4, 6))
    constrained = np.ones((4, 6), bool)
    constrained[:, 4:] = False
    coverage[~constrained] = 0.01
    f = tables[2].reshape(-1, 3).copy()
    filled, ex = fill_unconstrained(np.where(constrained.reshape(-1, 1), f, 7.0), coverage,
                                    constrained, library)
    assert ex.index[0] == 2
    np.testing.assert_allclose(filled, f, rtol=1e-9)


def test_passive_fills_the_unconstrained_nodes_from_the_matching_member():
    """An Oren-Nayar sphere (albedo 0.2, 0.4, 0.6, sigma 0.4) under 40 sources about the up
    direction (within ~40 deg); a library of Lambertian and Oren-Nayar materials holding the same roughness at
    another albedo (k = 1): that member is the nearest, and the nodes the environment leaves
    unconstrained get the truth's own reduction from it: to 2 % along the grazing column
    (theta_d 90 deg, none constrained) and at the median node (the retro corner at large
    theta_h inherits the solve's own error there, ~30 % at the constrained nodes beside it);
    the wrong grid or type is refused naming ``exemplars``."""
    members = [Lambertian(a) for a in (0.1, 0.5, 0.9)] + [OrenNayar(0.5, s) for s in (0.1, 0.4)]
    grid = (8, 8)
    prior = learn_modes(members, grid, n_modes=3)
    library = ExemplarLibrary.from_brdfs(members, grid, k=1)
    d = np.random.default_rng(3).normal(0, 0.4, size=(40, 3)) + [0, -1, 0]  # about the
    d /= np.linalg.norm(d, axis=1, keepdims=True)                            # up direction
    sky = (d, np.ones((40, 3)), np.full(40, 2 * np.pi / 40))
    truth = OrenNayar([0.2, 0.4, 0.6], 0.4)
    normals, mask = sphere_normals(32)
    image = np.zeros(normals.shape)
    image[mask] = shade_distant(truth, normals[mask], *sky)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PassiveWarning)
        fit = passive_reflectometry(image, normals, mask, sky, grid=grid, prior=prior,
                                    exemplars=library)
        unseen = ~fit.adequacy.constrained
        assert unseen.sum() >= 8 and fit.exemplars.index[0] == 4
        ratio = fit.brdf.table / Bivariate.from_brdf(truth, *grid).table
        assert unseen[:, -1].all() and np.abs(ratio[:, -1] - 1).max() < 0.02
        assert abs(np.median(ratio[unseen]) - 1) < 0.02
        with pytest.raises(PassiveInputError, match="exemplars were tabulated on grid"):
            passive_reflectometry(image, normals, mask, sky, grid=(6, 6), exemplars=library)
        with pytest.raises(PassiveInputError, match="exemplars must be an ExemplarLibrary"):
            passive_reflectometry(image, normals, mask, sky, grid=grid, prior=prior,
                                  exemplars=[Lambertian(0.1)])
