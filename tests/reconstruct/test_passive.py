"""Passive reflectometry (Romeiro et al. 2008): the lighting matrix against an independent
renderer, recovery of materials from one image of a sphere under a real light probe, the
adequacy report, and bad input. Ground truth images come from ``reconstruct.distant`` (exact
quadrature over the probe's texels, no Monte Carlo noise)."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.brdf import Bivariate, CookTorrance, Lambertian, OrenNayar
from reconstruct.distant import shade_distant, sphere_normals
from reconstruct.envmap import EnvironmentMap
from reconstruct import passive
from reconstruct.passive import (PassiveInputError, PassiveWarning, bivariate_error,
                                 learn_prior, lighting_matrix, passive_reflectometry)

#: camera (OpenCV) frame -> probe frame: the probe's +z (up) is the camera's -y.
CAMERA_TO_PROBE = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])


@pytest.fixture(scope="module")
def grace(shared_data):
    return EnvironmentMap.load(shared_data / "probes" / "grace.hdr",
                               rotation=CAMERA_TO_PROBE).resized(32)


def sphere_image(brdf, env, size=48):
    normals, mask = sphere_normals(size)
    image = np.zeros(normals.shape)
    image[mask] = shade_distant(brdf, normals[mask], *env.sources())
    return image, normals, mask


def test_lighting_matrix_matches_an_independent_renderer():
    """L @ table equals shade_distant of the same Bivariate table (local frames, halfway
    angles, bilinear lookup: none of L's dot-product shortcuts) to 1e-4, for an orthographic
    and a perspective (per-point view) camera."""
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(400, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[:, 2] = -np.abs(normals[:, 2]) - 0.3
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    dirs = rng.normal(size=(1500, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radiance = rng.uniform(0, 2, (1500, 3))
    omega = rng.uniform(0.5, 1.5, 1500) * 4 * np.pi / 1500
    table = rng.uniform(0.1, 1.0, (12, 9, 3))
    views = normals * 0.3 + np.array([0.1, -0.2, -1.0])
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    for view in ((0.0, 0.0, -1.0), views):
        L = lighting_matrix(normals, dirs, radiance, omega, view_dirs=view, grid=(12, 9))
        got = np.stack([L[c] @ table[..., c].ravel() for c in range(3)], axis=1)
        want = shade_distant(Bivariate(table), normals, dirs, radiance, omega, view_dirs=view)
        np.testing.assert_allclose(got, want, rtol=1e-4)


@pytest.mark.parametrize("n_normals", [3, 50, 700])
def test_lighting_matrix_normals_over_the_whole_sphere(n_normals):
    """Normals in every direction, each with its own camera (chunks of normals far apart, whose
    sources are culled per chunk): L @ table equals shade_distant to 1e-4."""
    rng = np.random.default_rng(n_normals)
    normals = rng.normal(size=(n_normals, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    views = normals + rng.normal(scale=0.4, size=normals.shape)
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    views[np.einsum("ij,ij->i", views, normals) < 0.05] = normals[
        np.einsum("ij,ij->i", views, normals) < 0.05]
    dirs = rng.normal(size=(1200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radiance = rng.uniform(0, 2, (1200, 3))
    omega = np.full(1200, 4 * np.pi / 1200)
    table = rng.uniform(0.1, 1.0, (10, 14, 3))
    L = lighting_matrix(normals, dirs, radiance, omega, view_dirs=views, grid=(10, 14))
    got = np.stack([L[c] @ table[..., c].ravel() for c in range(3)], axis=1)
    want = shade_distant(Bivariate(table), normals, dirs, radiance, omega, view_dirs=views)
    np.testing.assert_allclose(got, want, rtol=1e-4)


def test_lambertian_sphere_comes_back_constant(grace):
    """A Lambertian sphere under Grace Cathedral: every node within 2 % of albedo / pi
    (measured 0.001 %)."""
    albedo = np.array([0.7, 0.5, 0.3])
    fit = passive_reflectometry(*sphere_image(Lambertian(albedo), grace), grace)
    np.testing.assert_allclose(fit.brdf.table, np.broadcast_to(albedo / np.pi, (32, 32, 3)),
                               rtol=0.02)
    np.testing.assert_allclose(fit.lambertian, albedo / np.pi, rtol=1e-3)
    assert fit.converged and fit.residual.max() < 1e-3


@pytest.mark.parametrize("truth, prior, bound, vs_flat", [
    (OrenNayar([0.6, 0.55, 0.4], 0.4), "diffuse", 0.16, 1.05),
    (CookTorrance([0.3, 0.2, 0.1], 0.04, 0.1), "glossy", 0.40, 0.5),
])
def test_recovers_a_material_from_one_image(grace, truth, prior, bound, vs_flat):
    """One 48 x 48 sphere image under Grace (32 x 64 texels): the right prior wins, and the
    Eq. 1 error against the true 3-D BRDF is below ``bound`` and ``vs_flat`` x that of the
    best constant (Lambertian) BRDF. Measured: glossy Cook-Torrance 29.5 % (its bivariate
    reduction: 6.9 %; the best constant: more than twice that); Oren-Nayar 11.9 %, no better
    than the best constant (12.0 %; reduction 2.5 %): its brightening towards retro-reflection
    at grazing angles lies where one orthographic view observes nothing (see ``Adequacy``)."""
    fit = passive_reflectometry(*sphere_image(truth, grace), grace)
    assert fit.prior == prior
    err = bivariate_error(fit.brdf, truth, shape=(45, 45, 90))
    flat = bivariate_error(Lambertian(fit.lambertian * np.pi), truth, shape=(45, 45, 90))
    assert err < bound and err < vs_flat * flat, (err, flat)


def test_bivariate_error_closed_forms():
    """Eq. 1: 0 for the truth itself; exactly 0.1 for a Lambertian 10 % too bright."""
    truth = OrenNayar(0.5, 0.3)
    assert bivariate_error(truth, truth, shape=(10, 10, 20)) == 0.0
    assert bivariate_error(Lambertian(0.55), Lambertian(0.5), shape=(10, 10, 20)) == \
        pytest.approx(0.1, rel=1e-12)
    assert bivariate_error(Lambertian(0.45), Lambertian(0.5), shape=(10, 10, 20),
                           exclude_grazing_deg=10) == pytest.approx(0.1, rel=1e-12)


def test_learn_prior_is_the_variance_of_the_differences():
    """Two tables f = c s (c = 0 and 2) per channel: every s-difference is c / (n_s - 1), so
    its variance over the six channel samples is (1 / (n_s - 1))^2; the t-differences are all
    0 and floored at 1e-3 x the median variance."""
    n_t, n_s = 5, 7
    s = np.linspace(0, 1, n_s)
    tables = [Bivariate(np.broadcast_to((c * s)[None, :, None], (n_t, n_s, 3)).copy())
              for c in (0.0, 2.0)]
    prior = learn_prior(tables, (n_t, n_s))
    np.testing.assert_allclose(prior.var_s, 1.0 / (n_s - 1) ** 2, rtol=1e-12)
    np.testing.assert_allclose(prior.var_t, 1e-3 / (n_s - 1) ** 2, rtol=1e-12)
    assert prior.grid == (n_t, n_s) and prior.n_brdfs == 2


def test_few_point_sources_warn(grace):
    """Three directional lights: the adequacy report says the environment is a few sources and
    the lighting matrix is rank deficient."""
    dirs = np.array([[0.3, -0.5, -0.8], [-0.6, -0.2, -0.77], [0.1, 0.7, -0.7]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    env = (dirs, np.ones((3, 3)), np.full(3, 1e-3))
    normals, mask = sphere_normals(48)
    image = np.zeros(normals.shape)
    image[mask] = shade_distant(CookTorrance(0.3, 0.04, 0.2), normals[mask], *env)
    with pytest.warns(PassiveWarning, match="3 point-like sources"):
        fit = passive_reflectometry(image, normals, mask, env, grid=(16, 16))
    assert fit.adequacy.effective_sources == 3
    assert fit.adequacy.effective_rank < 0.5 * 16 * 16


def test_rotated_probe_warns(grace):
    """The image rendered under Grace, solved with Grace turned 90 degrees about the camera's
    vertical: the residual exposes the mismatch."""
    image, normals, mask = sphere_image(CookTorrance([0.4, 0.3, 0.2], 0.04, 0.15), grace)
    turn = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # camera frame, about y
    rotated = EnvironmentMap(grace.image, CAMERA_TO_PROBE @ turn)
    with pytest.warns(PassiveWarning, match="residual"):
        passive_reflectometry(image, normals, mask, rotated, grid=(16, 16))


def test_too_few_normals_is_an_error(grace):
    normals, mask = sphere_normals(64)
    small = np.zeros_like(mask)
    small[30:36, 30:36] = mask[30:36, 30:36]
    with pytest.raises(PassiveInputError, match="only 36 usable normals"):
        passive_reflectometry(np.ones(normals.shape), normals, small, grace)


@pytest.mark.parametrize("kwargs, match", [
    (dict(image=np.ones((4, 4))), "image must have shape"),
    (dict(normals=np.ones((64, 64, 3))), "normals must be finite unit vectors"),
    (dict(mask=np.ones((64, 64))), "mask must be a bool array"),
    (dict(view_dirs=np.ones(2)), "view_dirs must have shape"),
    (dict(environment=(np.ones((3, 3)), np.ones((3, 3)))), "environment must be"),
    (dict(environment=(np.eye(3), -np.ones((3, 3)), np.ones(3))), "environment: radiance"),
    (dict(grid=(1, 32)), "grid must have"),
    (dict(max_view_angle_deg=95), "max_view_angle_deg"),
    (dict(environment_weight=np.ones(7)), "environment_weight must have the map's shape"),
    (dict(image=[np.ones((64, 64, 3))] * 2), "normals must be a sequence of 2 arrays"),
])
def test_bad_arguments_are_named(grace, kwargs, match):
    normals, mask = sphere_normals(64)
    args = dict(image=np.ones(normals.shape), normals=normals, mask=mask, environment=grace)
    args.update(kwargs)
    with pytest.raises(PassiveInputError, match=match):
        passive_reflectometry(**args)


def test_large_probe_with_a_blind_region(grace, monkeypatch):
    """A probe over ``MAX_TEXELS`` (lowered here to 4096: the 64 x 128 map is area-averaged
    to 45 x 90) with garbage (20x) in a 14 deg cap at the zenith, marked by ``environment_weight`` = 0: observations seeing more than 2 %
    of it are dropped and a Lambertian sphere comes back within 10 % (median node; measured
    6.3 %: the kept ones still miss up to 2 % of a bright part of Grace); trusting the garbage
    instead is > 50 % off (measured 92.7 %)."""
    monkeypatch.setattr(passive, "MAX_TEXELS", 4096)
    image2 = np.repeat(np.repeat(grace.image, 2, axis=0), 2, axis=1)
    image2[:10] *= 20.0
    big = EnvironmentMap(image2, grace.rotation)
    weight = np.ones(big.shape)
    weight[:10] = 0.0
    normals, mask = sphere_normals(48)
    image = np.zeros(normals.shape)
    image[mask] = shade_distant(Lambertian(0.5), normals[mask], *grace.sources())
    errors = []
    for w in (weight, None):
        fit = passive_reflectometry(image, normals, mask, big, environment_weight=w,
                                    grid=(16, 16))
        errors.append(np.median(np.abs(fit.brdf.table * np.pi / 0.5 - 1)))
        if w is not None:
            assert fit.adequacy.n_observations < 0.6 * mask.sum()
    assert errors[0] < 0.10 and errors[1] > 0.5, errors


def test_two_views_combine(grace):
    """Two images of one glossy sphere, the second from a camera turned 70 degrees about the
    vertical (normals and view direction turned with it): both views' observations enter one
    fit, which explains both images (residual < 6 %, measured 1.9-4.5 % per channel; one view
    alone: 1.4-2.8 %) and is no worse than the first view alone on Eq. 1 (measured 25.5 % vs
    29.5 %). Ignoring the second camera's direction leaves a residual of 24-45 %."""
    truth = CookTorrance([0.3, 0.2, 0.1], 0.04, 0.1)
    a = np.radians(70)
    turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    first = sphere_image(truth, grace)
    normals, mask = sphere_normals(48)
    normals = normals @ turn.T
    view = turn @ np.array([0.0, 0.0, -1.0])
    image = np.zeros(normals.shape)
    image[mask] = shade_distant(truth, normals[mask], *grace.sources(), view_dirs=view)
    both = passive_reflectometry([first[0], image], [first[1], normals], [first[2], mask],
                                 grace, view_dirs=[None, view])
    one = passive_reflectometry(*first, grace)
    with pytest.warns(PassiveWarning, match="residual"):  # the second view's camera ignored
        wrong = passive_reflectometry([first[0], image], [first[1], normals],
                                      [first[2], mask], grace)
    e_both, e_one = (bivariate_error(f.brdf, truth, shape=(45, 45, 90)) for f in (both, one))
    assert both.adequacy.n_observations > 1.9 * one.adequacy.n_observations
    assert both.residual.max() < 0.06 and wrong.residual.min() > 2 * both.residual.max()
    assert e_both <= e_one * 1.02, (e_both, e_one)


def test_unconstrained_bands_name_the_poorly_lit_nodes():
    """The adequacy table the report shows, on a coverage grid made here: nodes lit below
    ``POOR_COVERAGE`` or never seen (NaN) are named per 10-deg theta_d band with their theta_h
    range (nodes at theta_h = (i / n)^2 90 deg, theta_d = j / n 90 deg, n = 31 steps) and their
    share of the band; a fully lit band is not listed."""
    n = 32
    cov = np.ones((n, n))
    cov[28:, 30:] = 0.01 * passive.POOR_COVERAGE        # theta_h >= 73 deg, theta_d >= 87 deg
    cov[:2, 0] = np.nan                                   # never seen: theta_h 0-0.1 deg at theta_d 0
    ad = passive.Adequacy(np.ones(1), 1, 1.0, cov, {}, 1, 1)
    bands = ad.unconstrained_bands()
    assert [b.theta_d_deg for b in bands] == [(0, 10), (80, 90)]
    # theta_d 0-10 holds columns 0-3 (0, 2.9, 5.8, 8.7 deg): 2 of 4 x 32 nodes; 80-90 columns 28-31
    assert bands[0].theta_h_deg == "0" and bands[0].poorly_lit_share == pytest.approx(2 / (4 * n))
    th = np.linspace(0, 1, n) ** 2 * 90
    assert bands[1].theta_h_deg == f"{th[28]:.0f}-90" and bands[1].poorly_lit_share == pytest.approx(8 / (4 * n))
    assert ad.unconstrained_ranges() == f"theta_d 0-10: theta_h 0; theta_d 80-90: theta_h {th[28]:.0f}-90"
