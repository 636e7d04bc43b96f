"""Reflectance sharing's homogeneous fit on lobes no fitted model expresses (Zickler et al.
Sect. 5.1 at reduced size: 10 sphere images of 48 px in, 21 held out, 400 centres; the paper's
size, 100 px and 1000 centres, is ``benchmarks/zoo.py``, and the measured phenolic below)."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.brdf.lobes import AshikhminShirley, RetroReflective
from reconstruct.brdf.zoo import measured_zoo
from reconstruct.sharing import fit_isotropic, samples_from_images
from reconstruct.sharing.baselines import fit_ward
from sims.distant_scenes import render_distant, stratified, theta_d_lights

SPHERE = 48
PHENOLIC = "merl/specular-red-phenolic"


def _median_error(brdf, test, size=SPHERE):
    lit = test.radiance.max(axis=(1, 2)) > 0
    pred = render_distant(brdf, size, test.directions[lit]).radiance
    truth = test.radiance[lit]
    return float(np.median(np.sqrt(((pred - truth) ** 2).sum(axis=(1, 2))
                                   / (truth ** 2).sum(axis=(1, 2)))))


@pytest.mark.parametrize("material, bound, m_w_range", [
    # sharp highlight with Fresnel: varies fast in (u, v), slowly in theta_d -> small m_w
    (AshikhminShirley((0.35, 0.25, 0.15), 0.05, 300.0), 0.03, (0.25, 0.5)),
    # Hapke opposition surge over Lambertian: varies only with theta_d -> large m_w
    (RetroReflective(), 0.002, (2.0, 4.0)),
])
def test_sharp_and_retro_lobes_from_ten_images(material, bound, m_w_range):
    """Measured at this size (2026-11-26): Ashikhmin-Shirley n = 300 1.6 % (over (u, v, w)
    instead of its polar form: 4.8 %; as the paper wrote it, f_r values and m_w = 0.5: 27 %;
    Ward 198 %), opposition surge 0.04 % (0.09 %; 2.9 %; Ward 18 %)."""
    train = render_distant(material, SPHERE, theta_d_lights(stratified(10)))
    test = render_distant(material, SPHERE, theta_d_lights(stratified(21)))
    s = samples_from_images(train.normals, train.radiance, train.directions)
    fit = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, max_centers=400, groups=s.image)
    before = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, max_centers=400, m_w=0.5,
                           log_values=False)
    ward = fit_ward(s.wi, s.wo, s.brdf, valid=s.valid, alphas=(0.05, 0.15))
    err = _median_error(fit.brdf, test)
    assert err < bound
    assert err < 0.25 * _median_error(before.brdf, test)
    assert err < 0.1 * _median_error(ward.brdf, test)
    assert m_w_range[0] <= fit.m_w <= m_w_range[1]
    choice = fit.scale_choice
    assert choice.held_out == 3 and choice.m_w == choice.candidates[int(np.argmin(choice.errors))]
    assert "chosen by held-out images" in fit.report()


def test_a_highlight_narrower_than_a_pixel_pools_across_images(shared_data):
    """MERL specular-red-phenolic (NBRDF fit): the highlight is half its peak 0.3 deg from the
    mirror direction, a quarter of a 100 px sphere's normal step, so each image sees it at one
    to three pixels. Over (u, v, w) those samples of the ten images sit at scattered phi_d and
    do not pool (held-out median 9.4 %); in the polar form (phi_d weighed 0.1) they do: 4.7 %,
    within the issue's 5 % (docs/zoo.md; m_w fixed at the value m_w="auto" chooses, 0.0625)."""
    truth = measured_zoo(shared_data / "brdfs", [PHENOLIC])[PHENOLIC]
    train = render_distant(truth, 100, theta_d_lights(stratified(10)))
    test = render_distant(truth, 100, theta_d_lights(stratified(21)))
    s = samples_from_images(train.normals, train.radiance, train.directions)
    polar, plain = (fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, m_w=0.0625,
                                  angular_weight=a) for a in (0.1, None))
    err = _median_error(polar.brdf, test, 100)
    assert err <= 0.05
    assert _median_error(plain.brdf, test, 100) > 1.5 * err
    # the held-out profile at theta_d 49.3 deg (the input at 49.5 deg sees the peak only at
    # 1.03-1.07 deg, so 0.4-1 deg comes from the other images): round and within 25 % of the
    # truth where the held-out pixels fall (over (u, v, w): 0.28-2.3 x)
    theta_h = np.radians([0.4, 0.6, 0.8, 1.0])
    theta_d = stratified(21)[11]
    h = np.stack([np.sin(theta_h), 0 * theta_h, np.cos(theta_h)], axis=1)
    for across in (np.broadcast_to([0.0, 1.0, 0.0], h.shape),                    # phi_d 90 deg
                   np.stack([np.cos(theta_h), 0 * theta_h, -np.sin(theta_h)], axis=1)):  # 0
        wi, wo = (np.cos(theta_d) * h + sign * np.sin(theta_d) * across for sign in (1, -1))
        ratio = polar.brdf.evaluate(wi, wo)[:, 0] / truth.evaluate(wi, wo)[:, 0]
        assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio
