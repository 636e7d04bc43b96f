"""Reflectance sharing on data whose two orderings of a pair differ (``sharing.reciprocity``,
``fit_isotropic(reciprocal=...)``): the check tells such data from reciprocal data under pixel
noise, and the fit then follows what no reciprocal model can.

Measured 2026-11-27 on Zickler Sect. 5.1's sphere experiment (10 images in, 21 held out,
median relative RMS), reciprocal fit / the default ("auto") / the nearest reciprocal BRDF:
a Cook-Torrance lobe times (1 + 0.3 (cos theta_i - cos theta_o)) at 32 px 7.81 / 0.96 / 6.55 %
(check gap 0.122, 0.115 with 2 % noise); the lobe itself 0.55 / 0.55 / 0 % (gap -0.001 and
-0.002); the RGL vinyl at 48 px 6.50 / 4.15 / 4.73 % (gap 0.102), the RGL matte paint
5.14 / 2.03 / 4.06 % (gap 0.028); at 100 px docs/zoo.md. The default's figures before the fit
that is not reciprocal took the value f_r cos theta_i / (cos theta_i + min_cos) and twice the
centres (2026-11-27): 0.61, 4.64 and 3.64 %; the value alone: 1.29, 4.59 and 2.81 %.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from reconstruct.brdf.analytic import CookTorrance
from reconstruct.brdf.base import BRDF
from reconstruct.brdf.rgl import read_rgl
from reconstruct.brdf.zoo import NearestReciprocal
from reconstruct.sharing import (RECIPROCITY_TOLERANCE, RbfBRDF, SharingError,
                                 check_reciprocity, fit_isotropic, samples_from_images)
from reconstruct.sharing.fits import MIN_COS
from sims.distant_scenes import render_distant, stratified, theta_d_lights

LOBE = CookTorrance((0.4, 0.3, 0.2), 0.04, 0.2)


@dataclass(frozen=True, eq=False)
class Skewed(BRDF):
    """``brdf`` times (1 + ``k`` (cos theta_i - cos theta_o)): brighter lit from above than
    seen from above, as a gonio-photometer's table can be; not reciprocal."""

    brdf: BRDF
    k: float = 0.3

    def _evaluate(self, wi, wo):
        return self.brdf.evaluate(wi, wo) * (1 + self.k * (wi[:, 2:3] - wo[:, 2:3]))

    def take(self, index) -> "Skewed":
        return self


def _experiment(truth, size):
    train = render_distant(truth, size, theta_d_lights(stratified(10)))
    test = render_distant(truth, size, theta_d_lights(stratified(21)))
    return samples_from_images(train.normals, train.radiance, train.directions), test


def _median_error(brdf, test, size):
    lit = test.radiance.max(axis=(1, 2)) > 0
    pred = render_distant(brdf, size, test.directions[lit]).radiance
    truth = test.radiance[lit]
    return float(np.median(np.sqrt(((pred - truth) ** 2).sum(axis=(1, 2))
                                   / (truth ** 2).sum(axis=(1, 2)))))


@pytest.mark.parametrize("noise", [0.0, 0.02])
def test_the_check_tells_a_skewed_lobe_from_a_reciprocal_one(noise):
    for truth, reciprocal in ((LOBE, True), (Skewed(LOBE), False)):
        s, _ = _experiment(truth, 32)
        f = s.brdf * (1 + noise * np.random.default_rng(1).normal(size=s.brdf.shape))
        check = check_reciprocity(s.wi[s.valid], s.wo[s.valid], f[s.valid])
        assert check.reciprocal is reciprocal
        # far from the tolerance either way: it is not what decides these
        if reciprocal:
            assert check.gap < 0.2 * RECIPROCITY_TOLERANCE
        else:
            assert check.gap > 5 * RECIPROCITY_TOLERANCE
        assert ("not reciprocal" in check.report()) is not reciprocal


def test_repeated_captures_do_not_make_reciprocal_data_look_otherwise():
    """Each sample four times over (a session captured four times): the nearest sample that is
    not a twin still measures the sampling step, and samples that are their own swap do not vote
    (the review's case: 4x repeated noisy reciprocal data read 0.042 against 0.013 before)."""
    s, _ = _experiment(LOBE, 32)
    f = s.brdf * (1 + 0.02 * np.random.default_rng(1).normal(size=s.brdf.shape))
    v = s.valid
    once = check_reciprocity(s.wi[v], s.wo[v], f[v])
    four = check_reciprocity(*(np.tile(a[v], (4, 1)) for a in (s.wi, s.wo, f)))
    assert once.reciprocal and four.reciprocal
    assert abs(four.gap - once.gap) < 0.2 * RECIPROCITY_TOLERANCE
    assert check_reciprocity(np.tile([[0.0, 0.6, 0.8]], (5, 1)), np.tile([[0.0, -0.6, 0.8]], (5, 1)),
                             np.ones(5)).n_samples == 0   # every sample its own swap: nothing to judge


def test_the_check_says_what_is_wrong_with_its_input():
    wi = np.tile([0.0, 0.0, 1.0], (4, 1))
    with pytest.raises(ValueError, match=r"brdf \(S,\) or \(S, 3\)"):
        check_reciprocity(wi, wi, np.ones(3))
    with pytest.raises(ValueError, match="at least 3 samples with f > 0 to check reciprocity, got 2"):
        check_reciprocity(wi, wi, [1.0, 1.0, 0.0, -1.0])
    s, _ = _experiment(LOBE, 16)
    with pytest.raises(SharingError, match="reciprocal must be True, False or 'auto'"):
        fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, reciprocal="yes")


def test_a_skewed_lobe_is_fitted_past_the_floor_of_reciprocal_models():
    truth = Skewed(LOBE)
    s, test = _experiment(truth, 32)
    kw = dict(valid=s.valid, m_w=1.0, max_centers=400)
    auto = fit_isotropic(s.wi, s.wo, s.brdf, **kw)
    forced = fit_isotropic(s.wi, s.wo, s.brdf, reciprocal=True, **kw)
    assert auto.brdf.asymmetry_weight is not None and not auto.reciprocity.reciprocal
    assert "not reciprocal" in auto.report() and "un-doubled phi_d" in auto.report()
    # the value that holds radiance past the terminator rule, and twice the centres
    assert auto.brdf.horizon == MIN_COS and forced.brdf.horizon is None
    assert "cos theta_i / (cos theta_i + 0.05)" in auto.report()
    assert auto.fit.model.n_centers == 800 and forced.fit.model.n_centers == 400
    floor = _median_error(NearestReciprocal(truth), test, 32)
    assert floor > 0.05                                     # measured 6.55 %
    assert _median_error(forced.brdf, test, 32) > floor     # 7.81 %
    assert _median_error(auto.brdf, test, 32) < 0.2 * floor  # 0.96 %
    # the model itself tells the orderings apart, as the truth does
    wi, wo = s.wi[s.valid][::50], s.wo[s.valid][::50]
    up = (wi[:, 2] > 0.2) & (wo[:, 2] > 0.2) & (np.abs(wi[:, 2] - wo[:, 2]) > 0.3)
    ratio = auto.brdf.evaluate(wi[up], wo[up]) / auto.brdf.evaluate(wo[up], wi[up])
    true = truth.evaluate(wi[up], wo[up]) / truth.evaluate(wo[up], wi[up])
    assert np.median(np.abs(np.log(ratio / true))) < 0.05
    np.testing.assert_allclose(forced.brdf.evaluate(wi[up], wo[up]),
                               forced.brdf.evaluate(wo[up], wi[up]), rtol=1e-5)
    # forced the other way, the same model as the check chose; its refits on fewer centres too
    asked = fit_isotropic(s.wi, s.wo, s.brdf, reciprocal=False, **kw)
    assert asked.reciprocity is None
    np.testing.assert_array_equal(asked.brdf.evaluate(wi, wo), auto.brdf.evaluate(wi, wo))
    fewer = auto.brdf_with(100)
    assert (fewer.asymmetry_weight, fewer.horizon) == (auto.brdf.asymmetry_weight, MIN_COS)
    # cos theta_i is no function of the reciprocal (u, v, w): the value needs the asymmetry
    with pytest.raises(SharingError, match="horizon"):
        RbfBRDF(forced.fit.model, forced.brdf.log_offset, forced.brdf.angular_weight,
                horizon=MIN_COS)


def test_reciprocal_data_get_the_papers_reciprocal_fit_unchanged():
    s, _ = _experiment(LOBE, 32)
    kw = dict(valid=s.valid, m_w=1.0, max_centers=400)
    auto = fit_isotropic(s.wi, s.wo, s.brdf, **kw)
    forced = fit_isotropic(s.wi, s.wo, s.brdf, reciprocal=True, **kw)
    assert auto.brdf.asymmetry_weight is None and auto.reciprocity.reciprocal
    wi, wo = s.wi[s.valid][::7], s.wo[s.valid][::7]
    np.testing.assert_array_equal(auto.brdf.evaluate(wi, wo), forced.brdf.evaluate(wi, wo))


@pytest.mark.realdata
@pytest.mark.parametrize("name, bound, terminator", [
    # glossy vinyl: the 5 % (measured 4.15 %); past the terminator 0.68 x (0.30 before)
    ("vch_golden_yellow_rgb", 0.05, 0.55),
    # matte paint: measured 2.03 % (its 2 % target is the 100 px experiment's: 1.88 % there);
    # past the terminator 0.81 x the truth's radiance (0.50 x before)
    ("colodur_napoli_4f_rgb", 0.025, 0.65),
])
def test_rgl_files_are_found_not_reciprocal_and_fitted_below_the_reciprocal_floor(
        shared_data, name, bound, terminator):
    truth = read_rgl(shared_data / "brdfs" / "rgl" / f"{name}.bsdf")
    s, test = _experiment(truth, 48)
    fit = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, max_centers=400)
    assert not fit.reciprocity.reciprocal
    error = _median_error(fit.brdf, test, 48)
    assert error < bound
    assert error < _median_error(NearestReciprocal(truth), test, 48)
    # Held-out pixels lit from beyond the terminator rule (no sample there): the files keep
    # f_r cos theta_i finite to the horizon (matte paint at theta_d 45 deg: 0.0014 at 89-90 deg
    # against 0.0044 at 79-80 deg), and the fit holds that radiance (median ratio to the truth's).
    pred = render_distant(fit.brdf, 48, test.directions).radiance[..., 1]
    true = test.radiance[..., 1]
    cos_i = (test.normals @ test.directions.T).T
    past = (cos_i < MIN_COS) & (true > 0)
    ratio = np.median(pred[past] / true[past])
    assert terminator < ratio < 1 / terminator
