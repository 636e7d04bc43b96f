"""The floors of the RGL zoo rows (Zickler Sect. 5.1's sphere experiment at 48 px, 21 held-out
images): a perfect table of what the images record, and the best any reciprocal model can do.

Measured 2026-11-26 at 48 px (100 px in docs/zoo.md): a 30 x 30 x 120 table of f_r cos theta_i
(``TabulatedCosine``) is within 1.3 % (matte paint) / 1.6 % (vinyl) median of the truth's
images, a 30 x 30 x 60 table of f_r (``TabulatedIsotropic``, reciprocity folded, f_r a quotient
by cos theta_light near the horizon) 9.7 / 7.2 %; ``NearestReciprocal`` is 4.1 / 4.7 % off.
"""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.brdf import TabulatedIsotropic
from reconstruct.brdf.analytic import CookTorrance
from reconstruct.brdf.rgl import read_rgl
from reconstruct.brdf.tabulated import TabulatedCosine
from reconstruct.brdf.zoo import NearestReciprocal
from reconstruct.coords import from_halfway_difference
from reconstruct.sharing import fit_isotropic, samples_from_images
from sims.distant_scenes import render_distant, stratified, theta_d_lights

SPHERE = 48


def _median_error(brdf, test):
    lit = test.radiance.max(axis=(1, 2)) > 0
    pred = render_distant(brdf, SPHERE, test.directions[lit]).radiance
    truth = test.radiance[lit]
    return float(np.median(np.sqrt(((pred - truth) ** 2).sum(axis=(1, 2))
                                   / (truth ** 2).sum(axis=(1, 2)))))


def _pairs(seed, n=300):
    """Random direction pairs (a, b), each (n, 3), over the upper hemisphere."""
    a, b = np.random.default_rng(seed).normal(size=(2, n, 3))
    a[:, 2], b[:, 2] = np.abs(a[:, 2]), np.abs(b[:, 2])
    return (a / np.linalg.norm(a, axis=1, keepdims=True),
            b / np.linalg.norm(b, axis=1, keepdims=True))


def test_cosine_table_holds_the_truth_at_its_nodes_and_nearest_reciprocal_is_reciprocal():
    truth = CookTorrance((0.4, 0.3, 0.2), 0.04, 0.2)
    table = TabulatedCosine.from_brdf(truth, (6, 6, 12))
    th, td, pd = (a.ravel() for a in np.meshgrid((np.arange(6) / 6) ** 2 * np.pi / 2,
                                                 np.arange(6) / 6 * np.pi / 2,
                                                 np.arange(12) / 12 * 2 * np.pi, indexing="ij"))
    wi, wo = from_halfway_difference(th, 0.0, td, pd)
    up = (wi[:, 2] > 1e-6) & (wo[:, 2] > 1e-6)
    np.testing.assert_allclose(table.evaluate(wi[up], wo[up]), truth.evaluate(wi[up], wo[up]),
                               rtol=1e-9)
    with pytest.raises(ValueError, match="TabulatedCosine.table has negative entries"):
        TabulatedCosine(-np.ones((2, 2, 2, 3)))
    a, b = _pairs(3)
    np.testing.assert_allclose(NearestReciprocal(truth).evaluate(a, b), truth.evaluate(a, b),
                               rtol=1e-12)


@pytest.mark.realdata
@pytest.mark.parametrize("name, reciprocal_floor", [
    ("colodur_napoli_4f_rgb", (0.03, 0.06)),   # matte paint: above its 2 % target (the default fit is not reciprocal)
    ("vch_golden_yellow_rgb", (0.035, 0.065)),  # glossy vinyl
])
def test_rgl_floors_on_the_sphere_experiment(shared_data, name, reciprocal_floor):
    truth = read_rgl(shared_data / "brdfs" / "rgl" / f"{name}.bsdf")
    test = render_distant(truth, SPHERE, theta_d_lights(stratified(21)))
    cosine = _median_error(TabulatedCosine.from_brdf(truth, (30, 30, 120)), test)
    assert cosine < 0.025
    assert _median_error(TabulatedIsotropic.from_brdf(truth, (30, 30, 60)), test) > 2 * cosine
    nearest = NearestReciprocal(truth)
    a, b = _pairs(4)
    np.testing.assert_allclose(nearest.evaluate(a, b), nearest.evaluate(b, a), rtol=1e-12)
    assert reciprocal_floor[0] < _median_error(nearest, test) < reciprocal_floor[1]


def test_merging_near_pairs_brings_the_vinyl_fit_towards_the_reciprocal_images(shared_data):
    """The vinyl's images hold both orderings of a pair a pixel apart, 13-23 % apart on the
    highlight's flank: the plain interpolant goes through whichever becomes a centre. Merged
    into their weighted mean first (``merge_radius``), the fit comes closer to the images of the
    nearest reciprocal BRDF, the best any reciprocal fit can aim at. Measured 2026-11-26 off
    those images (m_w 0.25), plain / merged / the same fit fed them: 48 px, 400 centres 4.24 /
    3.73 / 3.30 %; 100 px, 1000 centres 2.77 / 2.26 / 1.94 % (docs/zoo.md: off the truth the
    gain changes sign with the size, which is why merging is not the default). Reciprocal fits
    (``reciprocal=True``): by default the vinyl is found not reciprocal and fitted as it is
    (``test_sharing_reciprocity.py``)."""
    truth = read_rgl(shared_data / "brdfs" / "rgl" / "vch_golden_yellow_rgb.bsdf")
    nearest = NearestReciprocal(truth)
    lights, held_out = theta_d_lights(stratified(10)), theta_d_lights(stratified(21))
    rec = render_distant(nearest, SPHERE, held_out).radiance
    lit = rec.max(axis=(1, 2)) > 0
    held_out, rec = held_out[lit], rec[lit]

    def off_reciprocal(images, **kw):
        s = samples_from_images(images.normals, images.radiance, images.directions)
        fit = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, m_w=0.25, max_centers=400,
                              reciprocal=True, **kw)
        pred = render_distant(fit.brdf, SPHERE, held_out).radiance
        per = np.sqrt(((pred - rec) ** 2).sum(axis=(1, 2)) / (rec ** 2).sum(axis=(1, 2)))
        return float(np.median(per)), fit

    data = render_distant(truth, SPHERE, lights)
    plain, _ = off_reciprocal(data)
    merged, fit = off_reciprocal(data, merge_radius=0.0075)
    fed, _ = off_reciprocal(render_distant(nearest, SPHERE, lights))
    assert fit.fit.n_paired > 0.1 * fit.n_used
    assert fed < merged < fed + 0.006 and merged < plain - 0.003
