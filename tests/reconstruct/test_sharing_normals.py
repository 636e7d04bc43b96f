"""Reflectance sharing about normals fitted to the diffuse samples (reconstruct.sharing.normals).

Ground truth is the deterministic render (reconstruct.distant) of a sphere whose true normals
carry a tilt field the fitter's geometry lacks (as the demo's bumpy sphere does its mesh); the
fitter is handed the smooth sphere's normals. Errors are against that render under lights the
fit never saw.
"""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.brdf import CookTorrance, Lafortune
from reconstruct.distant import shade_distant
from reconstruct.frames import tangent_frames, to_world
from reconstruct.metrics import relative_rms
from reconstruct.sharing import SharingError, fit_spatial, photometric_normals, samples_from_images
from sims.distant_scenes import VIEW, hemisphere_lights, visible_points

SIZE = 32


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def _tilted(normals, xy, amplitude, freq, phase):
    """Normals tilted by a smooth field along their tangents (up to ~atan(amplitude)); the fits
    use normals point by point, so the field need not be integrable."""
    f = tangent_frames(normals)
    a = amplitude * np.sin(2 * np.pi * freq * xy[:, 0] + phase)
    b = amplitude * np.cos(2 * np.pi * freq * xy[:, 1] - phase)
    n = normals + a[:, None] * f[:, 0] + b[:, None] * f[:, 1]
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _render(brdf, normals, dirs):
    return np.stack([shade_distant(brdf, normals, d[None], np.ones(1), view_dirs=VIEW) for d in dirs])


CASES = {  # a sharp Cook-Torrance lobe and the demo's blue Phong (exponent 70), two tilt fields
    "cook-torrance": (CookTorrance(kd=(0.5, 0.3, 0.2), f0=0.6, alpha=0.12), (0.14, 3.0, 0.3)),
    "phong-70": (Lafortune.phong(rho_d=(0.10, 0.20, 0.50), rho_s=0.8, exponent=70.0), (0.12, 2.0, 1.1)),
}


@pytest.mark.parametrize("case", CASES)
def test_normals_from_the_diffuse_samples_restore_the_held_out_prediction(case):
    material, tilt = CASES[case]
    smooth, xy, _ = visible_points(SIZE)
    true_n = _tilted(smooth, xy, *tilt)
    train_l = hemisphere_lights(9, max_angle_deg=55)
    test_l = hemisphere_lights(4, max_angle_deg=45, offset=0.2)
    dif = _render(material.diffuse_part(), true_n, train_l)
    spec = _render(material.specular_part(), true_n, train_l)
    # the fitter knows only the smooth sphere: its samples' directions are about those normals
    sd = samples_from_images(smooth, dif, train_l)
    ss = samples_from_images(smooth, spec, train_l)
    kw = dict(texel=sd.point, diffuse=np.nan_to_num(sd.brdf), specular=np.nan_to_num(ss.brdf),
              valid=sd.valid, max_centers=300)
    plain = fit_spatial(xy[sd.point], sd.wi, sd.wo, None, **kw)
    fitted = fit_spatial(xy[sd.point], sd.wi, sd.wo, None, fit_normals=True, **kw)
    assert plain.normals is None

    # the normals: camera frame, against the truth (the smooth ones are off by the tilt field)
    pn = fitted.normals
    n_cam = to_world(pn.normals, tangent_frames(smooth))
    err_smooth, err_fit = _angle_deg(smooth, true_n), _angle_deg(n_cam, true_n)
    assert pn.fitted.mean() > 0.8       # the rim sees too few lights: it keeps the given normal
    assert np.median(err_smooth) > 5.0  # the tilt is real (seen 8.0 and 6.8 deg)
    # noise-free Lambertian samples: exact (seen 1.5e-6 deg at the 99th percentile)
    assert np.percentile(err_fit[pn.fitted], 99) < 0.01, np.percentile(err_fit[pn.fitted], 99)

    # held out: lights the fit never saw, rendered with the true normals
    truth = _render(material, true_n, test_l)
    ts = samples_from_images(smooth, truth, test_l)
    pred = [f.predict(ts.point, ts.wi, ts.wo).reshape(truth.shape) for f in (plain, fitted)]
    e_plain, e_fit = relative_rms(pred[0], truth), relative_rms(pred[1], truth)
    # seen: cook-torrance 1.09 -> 0.12, phong-70 1.35 -> 0.16 (the smooth normals put the
    # highlights where they are not: worse than predicting none)
    assert e_fit < 0.2 * e_plain, (e_plain, e_fit)
    assert e_fit < 0.25, e_fit


def test_photometric_normals_closed_form_with_shadows_and_unfit_texels():
    """Exact Lambertian samples of four texels: one tilted, lit from six lights (two of them in
    its attached shadow, diffuse 0); one whose three lights lie in a plane (undetermined); one
    with two lights (too few); one whose normal is the given one, with noise (the tilt is not
    significant, it keeps +z)."""
    rng = np.random.default_rng(4)
    n0 = np.array([0.6, -0.3, 1.0]) / np.linalg.norm([0.6, -0.3, 1.0])
    l0 = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.6, 0.8], [0.5, 0.5, 0.71],
                   [-0.95, 0.0, 0.31], [0.0, 0.97, 0.24]])
    l0 /= np.linalg.norm(l0, axis=1, keepdims=True)
    assert np.sum(l0 @ n0 < 0) == 2   # two lights behind the tilted normal, in front of +z
    coplanar = np.array([[0.6, 0.0, 0.8], [-0.6, 0.0, 0.8], [0.0, 0.0, 1.0]])
    two = np.array([[0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])
    flat = hemisphere_lights(12, max_angle_deg=60) * [1, 1, -1]   # towards +z
    wi = np.vstack([l0, coplanar, two, flat])
    texel = np.repeat([0, 1, 2, 3], [6, 3, 2, 12])
    albedo = np.array([0.7, 0.5, 0.3])
    d = albedo / np.pi * np.maximum(wi @ n0, 0.0)[:, None]
    d[6:11] = rng.random((5, 3))
    d[11:] = albedo / np.pi * flat[:, 2:3] * (1 + 0.01 * rng.standard_normal((12, 1)))
    got = photometric_normals(texel, wi, d, 4)
    np.testing.assert_array_equal(got.fitted, [True, False, False, False])
    np.testing.assert_allclose(got.normals[0], n0, atol=1e-12)
    np.testing.assert_allclose(got.normals[1:], [[0, 0, 1.0]] * 3)
    np.testing.assert_allclose(got.tilt_deg, [np.degrees(np.arccos(n0[2])), 0, 0, 0], atol=1e-9)
    # without the test the noise tilts texel 3 (1 % noise: a fraction of a degree)
    free = photometric_normals(texel, wi, d, 4, significance=None)
    assert free.fitted[3] and 0 < free.tilt_deg[3] < 2.0
    # without dropping the shadowed lights the least squares is biased
    once = photometric_normals(texel, wi, d, 4, iterations=0, significance=None)
    assert _angle_deg(once.normals[:1], n0[None])[0] > 1.0


def test_bad_input_is_named():
    wi = np.tile([0.0, 0.0, 1.0], (4, 1))
    with pytest.raises(SharingError, match="texel must lie in"):
        photometric_normals(np.array([0, 1, 2, 3]), wi, np.ones(4), 3)
    with pytest.raises(SharingError, match="diffuse must have shape"):
        photometric_normals(np.zeros(4, int), wi, np.ones(3), 1)
    with pytest.raises(SharingError, match="max_tilt_deg"):
        photometric_normals(np.zeros(4, int), wi, np.ones(4), 1, max_tilt_deg=0)
    with pytest.raises(SharingError, match="significance"):
        photometric_normals(np.zeros(4, int), wi, np.ones(4), 1, significance=1.5)
    smooth, xy, _ = visible_points(8)
    s = samples_from_images(smooth, np.ones((3, len(smooth))), hemisphere_lights(3))
    with pytest.raises(SharingError, match="fit_normals needs diffuse and specular"):
        fit_spatial(xy[s.point], s.wi, s.wo, np.nan_to_num(s.brdf), valid=s.valid, fit_normals=True)
