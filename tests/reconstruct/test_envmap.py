"""Lat-long environment maps: conventions, solid angles, lookup, sampling, irradiance."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.envmap import (EnvironmentMap, direction_to_pixel, pixel_directions,
                                pixel_solid_angles, pixel_to_direction)


def _random_dirs(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_convention_zenith_row0_azimuth_from_x_towards_y():
    H, W = 8, 16
    xy = direction_to_pixel(np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1.0, 0],
                                      [-1.0, 0, 0]]), H, W)
    np.testing.assert_allclose(xy[:2, 1], [-0.5, H - 0.5])  # poles at the top/bottom edges
    np.testing.assert_allclose(xy[2:, 0], [-0.5, W / 4 - 0.5, W / 2 - 0.5])
    np.testing.assert_allclose(xy[2:, 1], H / 2 - 0.5)  # the horizon mid-height


def test_pixel_direction_round_trip():
    d = _random_dirs(1000)
    xy = direction_to_pixel(d, 32, 64)
    np.testing.assert_allclose(pixel_to_direction(xy, 32, 64), d, atol=1e-12)
    centres = pixel_directions(32, 64)
    xy_c = direction_to_pixel(centres.reshape(-1, 3), 32, 64)
    ys, xs = np.mgrid[0:32, 0:64]
    np.testing.assert_allclose(xy_c, np.stack([xs.ravel(), ys.ravel()], 1), atol=1e-9)


def test_solid_angles_exact():
    sa = pixel_solid_angles(16, 32)
    assert sa.sum() == pytest.approx(4 * np.pi, rel=1e-12)
    # the upper hemisphere is the first half of the rows
    assert sa[:8].sum() == pytest.approx(2 * np.pi, rel=1e-12)
    # a polar cap of 2 rows: 2 pi (1 - cos(2 pi / 16))
    assert sa[:2].sum() == pytest.approx(2 * np.pi * (1 - np.cos(np.pi / 8)), rel=1e-12)


def test_lookup_bilinear_and_nearest():
    env = EnvironmentMap.from_function(lambda d: np.stack([d[:, 0], d[:, 1], d[:, 2]], 1) + 1,
                                       64)
    d = _random_dirs(2000, 1)
    # the map of a smooth function reproduces it to interpolation accuracy
    np.testing.assert_allclose(env.lookup(d), d + 1, atol=3e-3)
    centres = env.directions().reshape(-1, 3)
    np.testing.assert_allclose(env.lookup(centres, interpolation="nearest"),
                               env.image.reshape(-1, 3))
    np.testing.assert_allclose(env.lookup(centres), env.image.reshape(-1, 3), atol=1e-6)
    with pytest.raises(ValueError, match="interpolation"):
        env.lookup(d, interpolation="cubic")


def test_rotation_turns_the_map():
    # a map bright towards +x of its own frame; rotated so that map +x is world +y
    env0 = EnvironmentMap.from_function(lambda d: np.repeat(np.clip(d[:, :1], 0, None), 3, 1), 32)
    Rz = np.array([[0, 1.0, 0], [-1.0, 0, 0], [0, 0, 1.0]])  # world -> map: world +y -> map +x
    env = EnvironmentMap(env0.image, rotation=Rz)
    assert env.lookup(np.array([[0, 1.0, 0]]))[0, 0] == pytest.approx(1.0, abs=0.01)
    assert env.lookup(np.array([[1.0, 0, 0]]))[0, 0] == pytest.approx(0.0, abs=0.05)
    np.testing.assert_allclose(env.directions().reshape(-1, 3) @ Rz.T,
                               env0.directions().reshape(-1, 3), atol=1e-12)


def test_irradiance_closed_forms():
    const = EnvironmentMap.constant(2.0, 32)
    n = _random_dirs(50, 2)
    np.testing.assert_allclose(const.irradiance(n), 2.0 * np.pi, rtol=2e-3)  # midpoint rule
    # sky L = max(0, w_z): E(+z) = int cos^2 = 2 pi / 3; E(-z) = 0
    sky = EnvironmentMap.from_function(lambda d: np.repeat(np.clip(d[:, 2:], 0, None), 3, 1), 64)
    E = sky.irradiance(np.array([[0, 0, 1.0], [0, 0, -1.0]]))
    assert E[0, 0] == pytest.approx(2 * np.pi / 3, rel=2e-3)
    assert E[1, 0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("method", ["importance", "uniform"])
def test_sampling_pdf_is_a_density_and_estimates_integrals(method):
    """The returned pdf integrates the map exactly in expectation: mean(L / pdf) = sum L dw."""
    rng = np.random.default_rng(11)
    env = EnvironmentMap.from_function(
        lambda d: np.stack([0.1 + 5 * np.exp(30 * (d[:, 0] - 1)), 0.2 + 0 * d[:, 0],
                            0.3 + d[:, 2] ** 2], 1), 32)
    truth = (env.image * env.solid_angles()[..., None]).sum(axis=(0, 1))
    d, pdf = env.sample(200_000, rng, method=method)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    est = (env.lookup(d, interpolation="nearest") / pdf[:, None]).mean(axis=0)
    tol = 0.01 if method == "importance" else 0.03
    np.testing.assert_allclose(est, truth, rtol=tol)
    if method == "importance":
        np.testing.assert_allclose(env.pdf(d), pdf, rtol=1e-9)
        # pdf proportional to luminance: the bright lobe gets its share of samples
        lum = env.luminance() * env.solid_angles()
        share = lum[env.luminance() > 1.0].sum() / lum.sum()
        frac = (env.luminance().ravel()[env._pixel_index(d)] > 1.0).mean()
        assert frac == pytest.approx(share, abs=0.01)


def test_sampling_is_seeded_and_validated():
    env = EnvironmentMap.constant(1.0, 8)
    a = env.sample(10, np.random.default_rng(4))
    b = env.sample(10, np.random.default_rng(4))
    np.testing.assert_array_equal(a[0], b[0])
    with pytest.raises(TypeError, match="Generator"):
        env.sample(10, 4)
    with pytest.raises(ValueError, match="method"):
        env.sample(10, np.random.default_rng(0), method="stratified")
    with pytest.raises(ValueError, match="n must be"):
        env.sample(0, np.random.default_rng(0))


def test_black_map_samples_uniformly():
    env = EnvironmentMap.constant(0.0, 8)
    d, pdf = env.sample(1000, np.random.default_rng(0))
    np.testing.assert_allclose(pdf, 1 / (4 * np.pi), rtol=1e-12)


def test_bad_images_rejected():
    with pytest.raises(ValueError, match="shape"):
        EnvironmentMap(np.zeros((8, 16)))
    with pytest.raises(ValueError, match="non-negative"):
        EnvironmentMap(-np.ones((8, 16, 3)))
    with pytest.raises(ValueError, match="rotation"):
        EnvironmentMap(np.ones((8, 16, 3)), rotation=np.ones((3, 3)))
    with pytest.raises(FileNotFoundError):
        EnvironmentMap.load("/nonexistent/probe.hdr")


@pytest.mark.realdata
def test_load_real_probe(shared_data):
    env = EnvironmentMap.load(shared_data / "probes" / "grace.hdr")
    assert env.shape == (128, 256)
    small = env.resized(32)
    assert small.shape == (32, 64)
    # solid-angle weighted averaging keeps the integral of the radiance over the sphere
    tot = (env.image * env.solid_angles()[..., None]).sum(axis=(0, 1), dtype=np.float64)
    tot_s = (small.image * small.solid_angles()[..., None]).sum(axis=(0, 1), dtype=np.float64)
    np.testing.assert_allclose(tot_s, tot, rtol=1e-5)
