"""The simulated mirror-probe capture carries the room's light, and the calibration recovers it.

A probe ball 20 px in radius squeezes the room into ~1300 pixels; rendered with one ray per pixel
it hit or missed Grace's windows at random and its map's irradiance was ~60 % off (passive
reflectometry in the quick demo then could not explain its own image). Pixel-area integration
(``SimWorld.PROBE_RAYS_ACROSS``) keeps it within ~5 % (bound: 10 %), with the ball's true circle.

The calibration itself (the pipeline's steps on one Bayer mosaic of the same frame) must find
that circle and the colours: the Hough circle alone was 12 % small at 320 x 240, and bilinear
demosaicing gave Grace's windows, each seen by one photosite, that photosite's colour (the map's
irradiance 40-78 % off per channel, green).

Only a window around the ball is rendered (the camera's principal point moved by an even number
of pixels, so the pixels and the Bayer phase are the full frame's): 5 % of the frame's rays.
"""
import dataclasses

import numpy as np
import pytest

from calibration.probe import mirror_sphere_to_latlong
from calibration.raw import demosaic_bilinear, demosaic_smooth_hue
from calibration.spheres import find_mirror_sphere
from reconstruct.envmap import EnvironmentMap
from sims.targets import CHROME_REFLECTANCE, environment
from sims.world import SimWorld, default_camera

BALL_CENTRE_MM = np.array([0.0, 0.0, 25.4])  # sims.world.sphere_target: a 25.4 mm ball on the platter
BALL_RADIUS_MM = 25.4


def probe_window(size, probe, shared_data):
    """The probe ball's true circle (centre px, radius px) in a window of the ``size`` camera
    around it, the window's camera and its noise-free radiance."""
    cam = default_camera(*size)
    d = np.linalg.norm(cam.R @ BALL_CENTRE_MM + cam.t)
    radius_px = cam.K[0, 0] * BALL_RADIUS_MM / np.sqrt(d * d - BALL_RADIUS_MM ** 2)
    centre = cam.project(BALL_CENTRE_MM[None])[0]
    half = 2 * int(np.ceil(0.9 * radius_px))  # the limb search reaches 1.6 radii
    x0, y0 = (2 * (int(v) // 2) - half for v in centre)
    K = cam.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    window = dataclasses.replace(cam, K=K, width=2 * half, height=2 * half)
    env = environment(probe, data_dir=shared_data)
    world = SimWorld.for_capture("mirror_probe", None, camera=window, environment=env)
    return centre - (x0, y0), radius_px, window, world, env


def irradiance_error(env_map: np.ndarray, truth: EnvironmentMap) -> np.ndarray:
    """Per-channel relative RMS of the irradiance of 300 normals under a calibrated map (the
    stage maps at >= 128 rows; compared at 32) against the true environment's."""
    normals = np.random.default_rng(1).normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    want = truth.resized(32).irradiance(normals)
    have = EnvironmentMap(env_map).resized(32).irradiance(normals)
    return np.sqrt(np.mean((have - want) ** 2, axis=0) / np.mean(want ** 2, axis=0))


@pytest.mark.parametrize("probe, size", [("grace", (320, 240)), ("sky", (320, 240)), ("grace", (480, 360))])
def test_simulated_probe_frame_carries_the_environment_irradiance(shared_data, probe, size):
    centre, radius_px, cam, world, env = probe_window(size, probe, shared_data)
    image = world.radiance({"turntable_deg": 0.0})
    # the pipeline's lab frame is the sims' world frame: the true camera rotation maps it
    got = mirror_sphere_to_latlong(image, centre, radius_px, cam.R, height=128)
    rel = irradiance_error(got.env / CHROME_REFLECTANCE, env)
    assert np.all(rel < 0.10), f"{probe} {size}: irradiance rel rms per channel {rel}"


def test_probe_calibration_on_the_quick_demo_mosaic(shared_data):
    """The quick demo's probe frame (320 x 240) as the camera's mosaic (its colour filters and
    channel responses; no noise: the HDR bracket leaves little) through the pipeline's probe
    steps: the circle within 2 % in radius and 0.5 px in centre (measured +0.9 %, 0.14 px), the
    map's irradiance within 15 % per channel (measured 7-11 %); bilinear demosaicing, as
    before, is over 30 % off (measured 42-78 %)."""
    centre, radius_px, cam, world, env = probe_window((320, 240), "grace", shared_data)
    sensor = world.sensor
    response = np.asarray(sensor.quantum_efficiency)
    channels = sensor.cfa_channels(cam.height, cam.width)
    mosaic = sensor.mosaic(world.radiance({"turntable_deg": 0.0}) * response)
    image = demosaic_smooth_hue(mosaic, channels)
    found = find_mirror_sphere(image, reflectance=CHROME_REFLECTANCE)
    assert abs(found.radius_px / radius_px - 1) < 0.02, (found.radius_px, radius_px)
    assert np.linalg.norm(found.center_px - centre) < 0.5, (found.center_px, centre)
    probe = mirror_sphere_to_latlong(image, found.center_px, found.radius_px, cam.R, height=128)
    rel = irradiance_error(probe.env / CHROME_REFLECTANCE / response, env)
    assert np.all(rel < 0.15), f"irradiance rel rms per channel {rel}"
    bilinear = mirror_sphere_to_latlong(demosaic_bilinear(mosaic, channels), centre, radius_px, cam.R, height=128)
    assert irradiance_error(bilinear.env / CHROME_REFLECTANCE / response, env).max() > 0.3
