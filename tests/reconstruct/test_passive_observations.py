"""Passive reflectometry's observations as the paper draws them (``visible_hemisphere_normals``:
uniform on the visible hemisphere, the 80 deg limit) and the reweighted solve under a
``ModesPrior`` (``reweight``: pixels the bivariate table cannot follow count for less)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from reconstruct.brdf import Lambertian, OrenNayar
from reconstruct.distant import shade_distant, sphere_normals
from reconstruct.passive import (PassiveInputError, PassiveWarning, learn_modes,
                                 passive_reflectometry, visible_hemisphere_normals)


@pytest.mark.parametrize("view", [(0.0, 0.0, -1.0), (0.6, 0.0, 0.8)])
def test_hemisphere_normals_are_uniform_in_area_within_the_view_limit(view):
    """8,000 on the hemisphere, 80 deg kept: 8000 (1 - cos 80 deg) = 6,611 unit normals, none
    beyond 80 deg of the view; uniform in area: each of five equal-area bands of the view
    angle holds a fifth (to 2 normals), the mean of n . v is (1 + cos 80 deg) / 2 and the mean
    across the view is ~0 (1e-3), as for a uniform density on the cap. A 48 px sphere's pixels
    are not (cos-weighted: its 1,764 within 80 deg put a mean n . v of 0.67, not 0.59)."""
    c80 = np.cos(np.radians(80))
    n = visible_hemisphere_normals(8000, view_dir=view)
    v = np.asarray(view)
    assert len(n) == pytest.approx(8000 * (1 - c80), abs=1)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-12)
    cos = n @ v
    assert cos.min() >= c80 - 1e-12
    counts = np.histogram(cos, bins=np.linspace(c80, 1, 6))[0]
    assert np.abs(counts - len(n) / 5).max() <= 2, counts
    assert cos.mean() == pytest.approx((1 + c80) / 2, abs=1e-3)
    assert np.linalg.norm((n - cos[:, None] * v).mean(axis=0)) < 1e-3
    pixels, mask = sphere_normals(48)
    pc = -pixels[mask][:, 2]
    assert pc[pc >= c80].mean() > cos.mean() + 0.05


def test_hemisphere_normals_name_bad_arguments():
    with pytest.raises(PassiveInputError, match="count"):
        visible_hemisphere_normals(0)
    with pytest.raises(PassiveInputError, match="max_view_angle_deg"):
        visible_hemisphere_normals(100, max_view_angle_deg=90)
    with pytest.raises(PassiveInputError, match="view_dir"):
        visible_hemisphere_normals(100, view_dir=(0, 0, 2))


def _lambertian_sphere(truth, sky, size=40):
    normals, mask = sphere_normals(size)
    image = np.zeros(normals.shape)
    image[mask] = shade_distant(truth, normals[mask], *sky)
    return image, normals, mask


def test_reweighting_discounts_pixels_the_table_cannot_follow():
    """A Lambertian sphere (albedo 0.2, 0.4, 0.6) under a sky of 200 sources, 3 % of its pixels
    made 4x brighter (a glint no homogeneous bivariate BRDF explains): the plain solve under a
    ModesPrior (8 x 8 nodes, learned from Lambertian and Oren-Nayar materials) is pulled up by
    them (~10 %), the reweighted one (``reweight=1``: each pixel's noise variance the plain
    one's plus its squared misfit) keeps the albedo within 2 % (mean over the inner nodes), as
    it does on the clean image. Smoothness priors refuse it."""
    # a library that varies beyond its modes (Lambertian alone leaves no remainder to solve in)
    prior = learn_modes([Lambertian(a) for a in (0.1, 0.3, 0.5, 0.7)]
                        + [OrenNayar(a, s) for a in (0.2, 0.6) for s in (0.2, 0.5)], (8, 8), n_modes=3)
    d = np.random.default_rng(3).normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sky = (d, np.ones((200, 3)), np.full(200, 4 * np.pi / 200))
    albedo = np.array([0.2, 0.4, 0.6])
    image, normals, mask = _lambertian_sphere(Lambertian(albedo), sky)
    glint = mask & (np.random.default_rng(5).uniform(size=mask.shape) < 0.03)
    error = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PassiveWarning)
        for key, img, rw in (("glint", np.where(glint[..., None], 4 * image, image), 0),
                             ("glint", np.where(glint[..., None], 4 * image, image), 1),
                             ("clean", image, 1)):
            fit = passive_reflectometry(img, normals, mask, sky, grid=(8, 8), prior=prior,
                                        reweight=rw)
            error[key, rw] = np.abs(fit.brdf.table[2:6, 2:6].mean(axis=(0, 1)) * np.pi / albedo - 1)
        with pytest.raises(PassiveInputError, match="reweight is for a ModesPrior"):
            passive_reflectometry(image, normals, mask, sky, grid=(8, 8), reweight=1)
    assert np.all(error["glint", 0] > 0.05), error
    assert np.all(error["glint", 1] < 0.02) and np.all(error["clean", 1] < 0.02), error
