"""Turntable axis: a ChArUco board lying on a rendered platter seen at known readings."""
from __future__ import annotations

import functools

import cv2
import numpy as np
import pytest

from calibration.errors import DegenerateFit, NotConverged, TooFewViews
from calibration.intrinsics import detect_all
from calibration.targets import detect_charuco, make_charuco_board
from calib_synth import DIST_TRUE, K_TRUE, render_plane, rot_axis_angle

SQ = 12.0  # mm per square
SCALE, OFFSET = 1.0, 7.0  # platter angle = SCALE * reading + OFFSET, deg
READINGS = np.arange(0.0, 360.0, 45.0)


def _camera(elev_deg=50.0, dist_mm=330.0):
    e = np.radians(elev_deg)
    eye = dist_mm * np.array([np.cos(e), 0.0, np.sin(e)])
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    return R, -R @ eye


def make_scene():
    board = make_charuco_board((8, 6), SQ, 0.75 * SQ, "DICT_4X4_50")
    px = 40
    tex = np.pad(board.generateImage((8 * px, 6 * px), marginSize=0), px, constant_values=255)
    to_tex = lambda uv: np.asarray(uv) / SQ * px + px - 0.5  # noqa: E731
    R_cw, t_cw = _camera()
    # board lying face-up: board x = world x, board y = -world y, board z = -world z
    R_b0 = np.diag([1.0, -1.0, -1.0])
    t_b0 = np.array([10.0, 5.0, 0.0]) - R_b0 @ np.array([4 * SQ, 3 * SQ, 0])
    rng = np.random.default_rng(11)
    imgs = []
    for reading in READINGS:
        Rz = rot_axis_angle([0, 0, 1], np.radians(SCALE * reading + OFFSET))
        R_bc = R_cw @ Rz @ R_b0
        t_bc = R_cw @ (Rz @ t_b0) + t_cw
        imgs.append(render_plane(tex, to_tex, K_TRUE, DIST_TRUE, cv2.Rodrigues(R_bc)[0].ravel(), t_bc,
                                 rng=rng, noise=1.5))
    dets, missing = detect_all(imgs, functools.partial(detect_charuco, board=board))
    return dict(dets=dets, R_cw=R_cw, t_cw=t_cw, R_b0=R_b0, t_b0=t_b0)


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def _angle_deg(u, v):
    return np.degrees(np.arccos(np.clip(np.dot(u, v) / np.linalg.norm(u) / np.linalg.norm(v), -1, 1)))


@pytest.mark.parametrize("mode", ["known", "scale", "unknown"])
def test_axis_direction_within_0p1_deg(scene, mode):
    from calibration.turntable import fit_turntable
    kw = dict(known=dict(angles_deg=READINGS), scale=dict(angles_deg=READINGS, fit_scale=True),
              unknown={})[mode]
    fit = fit_turntable(scene["dets"], K_TRUE, DIST_TRUE, **kw)
    axis_true = scene["R_cw"] @ [0, 0, 1.0]
    assert _angle_deg(fit.axis_camera, axis_true) < 0.1
    assert fit.axis_std_deg < 0.1 and fit.rms_px < 0.3
    assert 1 <= fit.fit_status <= 4 and fit.fit_message  # converged, with scipy's reason
    # world origin (foot of the target origin on the axis: board lies at z = 0) in camera frame
    assert np.linalg.norm(fit.origin_camera - scene["t_cw"]) < 0.5
    # fitted per-view platter angles follow the readings
    d_ang = (fit.view_angles_deg - SCALE * (READINGS - READINGS[0]) + 180) % 360 - 180
    assert np.abs(d_ang).max() < 0.1
    if mode != "unknown":
        assert abs(fit.angle_scale - SCALE) < (1e-3 if mode == "scale" else 1e-12)
    # the model's object pose at any reading maps the board corners where the truth does
    reading = 100.0
    R, t = fit.world_to_camera(reading) if mode != "unknown" else \
        fit.world_to_camera_at_phi(SCALE * reading + OFFSET - (SCALE * READINGS[0] + OFFSET))
    Rt, tt = fit.target_in_world
    corners = scene["dets"][0].object_points
    pred = (corners @ Rt.T + tt) @ R.T + t
    Rz = rot_axis_angle([0, 0, 1], np.radians(SCALE * reading + OFFSET))
    truth = (corners @ scene["R_b0"].T + scene["t_b0"]) @ Rz.T @ scene["R_cw"].T + scene["t_cw"]
    assert np.abs(pred - truth).max() < 0.5  # mm, at ~330 mm range


def test_a_fit_that_does_not_converge_is_an_error(scene):
    from calibration.turntable import fit_turntable
    with pytest.raises(NotConverged, match="turntable bundle adjustment did not converge"):
        fit_turntable(scene["dets"], K_TRUE, DIST_TRUE, max_evaluations=2)


def test_too_few_views_and_no_rotation(scene):
    from calibration.turntable import fit_turntable
    with pytest.raises(TooFewViews):
        fit_turntable(scene["dets"][:2], K_TRUE, DIST_TRUE)
    with pytest.raises(DegenerateFit, match="10°"):
        fit_turntable([scene["dets"][0]] * 3, K_TRUE, DIST_TRUE)
    with pytest.raises(ValueError, match="angles_deg"):
        fit_turntable(scene["dets"], K_TRUE, DIST_TRUE, angles_deg=[0, 1])
