"""End to end on the simulated lab's rendered frames (sims/world.py): the calibration functions
against the renderer's own ground truth. Rendering costs seconds per frame (the multi-frame cases
take 5-25 s each on 2 cores); they run by default, as the accuracy checks CI must see."""
from __future__ import annotations

import functools

import numpy as np
import pytest

import sims.world as sims_world
from calibration.hdr import merge_raw_brackets
from calibration.intrinsics import detect_all
from calibration.lights import SphereImage, find_highlight, reflect_highlight
from calibration.polarization import separate_parallel_crossed
from calibration.raw import read_raw
from calibration.targets import detect_charuco, make_charuco_board
from calibration.turntable import fit_turntable


def _angle_deg(u, v):
    return float(np.degrees(np.arccos(np.clip(np.dot(u, v) / np.linalg.norm(u) / np.linalg.norm(v), -1, 1))))


def test_chrome_sphere_light_direction_on_rendered_frame():
    world = sims_world.SimWorld.for_capture("chrome")
    light = sims_world.light_position(40.0, 35.0)
    rad = world.radiance({"light_position_mm": light})
    cam = world.camera
    centre_w = world.targets[0].points_world(0.0)[0]
    radius = world.targets[0].spec.radius_mm
    C = cam.R @ centre_w + cam.t  # sphere centre, camera frame (known position, per Lensch)
    # the sphere's disc in the image, from its known position (the silhouette against a dark
    # cloth is not a clean mask)
    uv = cam.project(centre_w[None])[0]
    r_px = cam.K[0, 0] * radius / np.sqrt(C @ C - radius ** 2)
    sph = SphereImage(uv, float(r_px), None, np.zeros((0, 2)))
    hl = find_highlight(rad.mean(axis=2), sph)
    P, L = reflect_highlight(hl.xy_px[None], C[None], radius, cam.K, cam.dist)
    truth = (cam.R @ light + cam.t) - P[0]
    assert _angle_deg(L[0], truth) < 0.25


def test_turntable_axis_on_rendered_charuco_views():
    world = sims_world.SimWorld.for_capture("charuco")
    spec = world.targets[0].spec
    board = make_charuco_board(spec.squares, spec.square_mm, spec.marker_mm, spec.dictionary)
    readings = np.arange(-60.0, 61.0, 20.0)
    imgs = [world.radiance({"turntable_deg": r}) for r in readings]
    dets, missing = detect_all(imgs, functools.partial(detect_charuco, board=board), on_missing="skip")
    keep = [i for i, d in enumerate(imgs) if f"frame {i}" not in {m.frame for m in missing}]
    fit = fit_turntable(dets, world.camera.K, world.camera.dist, angles_deg=readings[keep])
    cam = world.camera
    assert _angle_deg(fit.axis_camera, cam.R[:, 2]) < 0.1
    # our origin lies on the true axis (through the world origin, along world +z)
    d = fit.origin_camera - cam.t
    assert np.linalg.norm(d - np.dot(d, cam.R[:, 2]) * cam.R[:, 2]) < 0.5
    assert abs(fit.angle_scale - 1) < 1e-9 and fit.rms_px < 0.3


def test_polarization_separation_on_rendered_object():
    world = sims_world.SimWorld.for_capture("object", "sphere")
    par = world.ground_truth({"polarizer_deg": 0.0})
    cro = world.ground_truth({"polarizer_deg": 90.0})
    sep = separate_parallel_crossed(par.radiance, cro.radiance)
    surf = par.buffers.mask if par.buffers.mask.ndim == 2 else par.buffers.mask[..., 0]
    d_true = (par.diffuse + cro.diffuse)[surf]
    s_true = (par.specular - cro.specular)[surf]
    rel = lambda e, t: np.sqrt(np.mean((e - t) ** 2)) / np.sqrt(np.mean(t ** 2))  # noqa: E731
    assert rel(sep.diffuse[surf], d_true) < 0.02
    assert rel(sep.specular[surf], s_true) < 0.02


def test_raw_hdr_from_simulated_dngs(tmp_path):
    world = sims_world.SimWorld.for_capture("object", "sphere")
    iso = 100.0
    times = [1 / 400, 1 / 100, 1 / 25]
    mosaics, truth = [], None
    for k, t in enumerate(times):
        state = {"exposure_s": t, "iso": iso}
        path = tmp_path / f"f{k}.dng"
        path.write_bytes(world.frame_source(state))
        raw = read_raw(path)
        mosaics.append(raw.data)
        if k == 0:
            gt = world.ground_truth(state)
            truth = (gt.expected.mean_dn - raw.black_level) / t  # DN/s
            unsat = ~gt.expected.saturated
    g = world.sensor.e_per_dn(iso)
    hdr = merge_raw_brackets(mosaics, times, black_level=raw.black_level, white_level=raw.white_level,
                             gain_e_per_dn=g, read_noise_dn=world.sensor.read_noise_e / g)
    bright = unsat & (truth > 50 * (world.sensor.read_noise_e / g) / times[-1])
    ratio = hdr.radiance[bright] / truth[bright]
    assert abs(np.mean(ratio) - 1) < 0.01
    z = (hdr.radiance - truth)[bright] / hdr.sigma[bright]
    assert 0.8 < z.std() < 1.25


def test_mirror_probe_matches_simulated_environment():
    """The sim's chrome ball under Grace Cathedral -> our world lat-long map agrees with the
    environment the renderer used (same lat-long convention as reconstruct.envmap)."""
    from calibration.probe import latlong_directions, mirror_sphere_to_latlong_perspective
    from sims.targets import CHROME_REFLECTANCE

    world = sims_world.SimWorld.for_capture("mirror_probe")
    rad = world.radiance({})
    cam = world.camera
    centre = cam.R @ world.targets[0].points_world(0.0)[0] + cam.t
    h = 48
    probe = mirror_sphere_to_latlong_perspective(rad, cam.K, cam.dist, centre, world.targets[0].spec.radius_mm,
                                                 cam.R, height=h)
    truth = CHROME_REFLECTANCE * world.environment.lookup(latlong_directions(h).reshape(-1, 3)).reshape(h, 2 * h, 3)
    good = probe.weight >= 1
    assert good.mean() > 0.85
    # one ray per pixel on a ~90 px ball aliases the cathedral's small bright windows, so the
    # check is statistical: median error (measured 3.8 %) and log-luminance correlation
    # (measured 0.95; a mirrored azimuth convention gives 0.70)
    assert np.median(np.abs(probe.env / np.maximum(truth, 1e-6) - 1)[good]) < 0.06
    a, b = np.log(probe.env.mean(2)[good] + 1e-4), np.log(truth.mean(2)[good] + 1e-4)
    assert np.corrcoef(a, b)[0, 1] > 0.9


@pytest.mark.parametrize("light_az_el", [(60.0, 40.0), (-30.0, 25.0)])
def test_lensch_sphere_row_on_rendered_frames(light_az_el):
    """The sim's row of six 1-inch steel balls: ring-flash highlights -> sphere centres (Lensch
    Eqs. 1-5), lamp highlights -> point light, within the issue's 0.5 % of its distance.

    The balls are ~36 px in radius and the lamp's highlight about a pixel wide, so the frames are
    rendered 3 x 3 supersampled (pixel-area integration, as a sensor does): one ray per pixel
    aliases the highlight and gives 2.1 % whatever the estimator. Measured (true centres):
    0.39 % / 0.36 % for these two lights (0.84 % / 1.38 % with the old 0.5 highlight threshold).
    With ring-flash-derived centres (0.25-0.3 mm off at 740 mm) the light lands 1.4-3.3 % off:
    the row's reflected rays are nearly coplanar, so centre errors are amplified along the row;
    that is checked against the stated uncertainty, not the 0.5 % bar."""
    from calibration.lights import locate_collinear_spheres, triangulate_point_light

    world = sims_world.SimWorld.for_capture("spheres", None, supersample=3)
    cam = world.camera
    row = world.targets[0]
    centres_w = row.points_world(0.0)
    radius = row.spec.radius_mm
    centres = centres_w @ cam.R.T + cam.t
    light = sims_world.light_position(*light_az_el)
    light_cam = cam.R @ light + cam.t
    lamp = world.radiance({"light_position_mm": light}).mean(axis=2)
    discs = [SphereImage(uv, float(cam.K[0, 0] * radius / np.sqrt(c @ c - radius ** 2)), None, np.zeros((0, 2)))
             for uv, c in zip(cam.project(centres_w), centres)]
    lamp_hl = np.array([find_highlight(lamp, d).xy_px for d in discs])
    pl = triangulate_point_light(lamp_hl, centres, radius, cam.K, cam.dist, sigma_px=0.1)
    distance = np.linalg.norm(light_cam - centres.mean(axis=0))
    assert np.linalg.norm(pl.position_mm - light_cam) < 0.005 * distance
    if light_az_el == (60.0, 40.0):  # the flash frame does not depend on the lamp: render it once
        flash = world.radiance({"ring_flash": True}).mean(axis=2)
        flash_hl = np.array([find_highlight(flash, d).xy_px for d in discs])
        est = locate_collinear_spheres(flash_hl, row.spec.spacing_mm, cam.K, cam.dist)
        assert np.linalg.norm(est - centres, axis=1).max() < 0.5
        pl2 = triangulate_point_light(lamp_hl, est, radius, cam.K, cam.dist, sigma_px=0.1)
        assert np.linalg.norm(pl2.position_mm - light_cam) < 3 * np.sqrt(np.trace(pl2.covariance_mm2))
