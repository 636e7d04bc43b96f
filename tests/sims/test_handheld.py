"""Hand-held board views (sims/handheld.py) and their staging in the simulated labs: each view
is where its prompt says, tilted as stated, wholly in the frame, and the rendered board is found
where the truth projects it."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.raw import demosaic_bilinear, read_raw
from calibration.targets import detect_charuco, make_charuco_board, to_gray_u8
from capture.pipeline.demo_lab import DemoLab
from capture.plan import Plan
from sims.handheld import HANDHELD_PLACES, handheld_board_pose, handheld_view
from sims.world import CAPTURE_CHARUCO, SimWorld, default_camera

VIEWS = 12


def _sheet_px(camera, T, *, distort: bool) -> np.ndarray:
    """The printed sheet's four corners in the image, (4, 2) px."""
    x0, y0, x1, y1 = CAPTURE_CHARUCO.extent_mm
    pts = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float) @ T[:3, :3].T + T[:3, 3]
    if distort:
        return camera.project(pts)
    p = pts @ camera.R.T + camera.t
    return p[:, :2] / p[:, 2:] * camera.K[0, 0] + camera.K[:2, 2]


@pytest.mark.parametrize("size", [(320, 240), (640, 480)])
def test_views_tilt_as_stated_stay_in_frame_and_reach_every_corner(size):
    cam = default_camera(*size)
    w, h = size
    margin = 0.04 * w
    reached = set()
    for k in range(VIEWS):
        v = handheld_view(k, VIEWS)
        T = handheld_board_pose(CAPTURE_CHARUCO, cam, **v.pose_options())
        normal_cam = cam.R @ T[:3, 2]  # the sheet's z (into it) in the camera frame
        assert np.degrees(np.arccos(normal_cam[2])) == pytest.approx(v.tilt_deg, abs=1e-6)
        # the tilt axis lies in the image plane at tilt_axis_deg from x: the normal leans across it
        axis = np.array([np.cos(np.radians(v.tilt_axis_deg)), np.sin(np.radians(v.tilt_axis_deg)), 0])
        assert abs(normal_cam @ axis) < 1e-9
        uv = _sheet_px(cam, T, distort=False)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        assert np.all(lo >= margin - 1e-6) and np.all(hi <= np.array([w - 1, h - 1]) - margin + 1e-6)
        # pushed against the edges its anchor names (pinhole), centred where it says 0
        ax, ay = v.anchor
        for a, lo_, hi_, n in ((ax, lo[0], hi[0], w), (ay, lo[1], hi[1], h)):
            if a < 0:
                assert lo_ == pytest.approx(margin, abs=0.01)
            elif a > 0:
                assert hi_ == pytest.approx(n - 1 - margin, abs=0.01)
            else:
                assert (lo_ + hi_) / 2 == pytest.approx((n - 1) / 2, abs=0.01)
        # the real lens (barrel distortion) keeps the sheet in the frame too
        duv = _sheet_px(cam, T, distort=True)
        assert np.all(duv >= 0) and np.all(duv <= [w - 1, h - 1])
        if ax and ay:
            reached.add((ax, ay))
    assert reached == {(-1, -1), (-1, 1), (1, -1), (1, 1)}


def test_view_sequence_and_bad_arguments():
    assert [handheld_view(k, 9).anchor for k in range(9)] == [a for _, a in HANDHELD_PLACES]
    for k in range(12):
        v = handheld_view(k, 12)
        # the axes turn by 360/12 degrees (modulo a half turn); the side leaning away never faces
        # the frame edge the board is pushed to
        assert (v.tilt_axis_deg - 30.0 * k) % 180.0 == pytest.approx(0.0, abs=1e-9)
        phi = np.radians(v.tilt_axis_deg)
        assert np.dot([-np.sin(phi), np.cos(phi)], v.anchor) <= 1e-9
    with pytest.raises(ValueError, match="view must be a whole number in 0..11"):
        handheld_view(12, 12)
    with pytest.raises(ValueError, match="views must be"):
        handheld_view(0, 0)
    cam = default_camera(320, 240)
    with pytest.raises(ValueError, match="anchor"):
        handheld_board_pose(CAPTURE_CHARUCO, cam, anchor=(2, 0))
    with pytest.raises(ValueError, match="width_fraction"):
        handheld_board_pose(CAPTURE_CHARUCO, cam, width_fraction=0.95)


def test_demo_lab_renders_a_detectable_board_at_every_view():
    """Through the DNG the camera writes: every view's board is found, its corners within 0.5 px
    (rms) of the true camera's projection of the board's corners."""
    lab = DemoLab(320, 240, seed=3)
    cam = lab.camera
    board = make_charuco_board(CAPTURE_CHARUCO.squares, CAPTURE_CHARUCO.square_mm, CAPTURE_CHARUCO.marker_mm, CAPTURE_CHARUCO.dictionary)
    plan = Plan.from_dict({"calibration": [{"kind": "handheld_board", "views": 24, "exposure_s": 0.15}]})
    counts = []
    for step in plan.steps()[:len(HANDHELD_PLACES)]:  # every place in the frame (all 24 in the e2e test)
        lab.prepare_target(step.target, step)
        raw = read_raw(lab({"exposure_s": 0.15}))
        img = demosaic_bilinear(raw.data - raw.black_level, raw.channels)
        det = detect_charuco(to_gray_u8(img.mean(axis=2), white_percentile=99.5), board, frame=f"view {step.view}")
        T = handheld_board_pose(CAPTURE_CHARUCO, cam, **handheld_view(step.view, step.views).pose_options())
        truth = cam.project(CAPTURE_CHARUCO.corners_world(T))[det.ids]
        assert np.sqrt(np.mean(np.sum((det.image_points - truth) ** 2, axis=1))) < 0.5, step.view
        counts.append(len(det.ids))
    assert np.median(counts) >= 20, counts  # of the board's 54
    assert lab.targets().charuco_squares == CAPTURE_CHARUCO.squares  # the lab still states its board
    with pytest.raises(ValueError, match="which view"):
        lab.prepare_target("handheld_board", None)


def test_plain_sim_world_stages_hand_held_views_lit_by_the_ring_flash():
    """``gonio capture run --rig sim`` stages the views in the default world (the runner's
    prepare_target): the board at the step's pose, no platter behind it, lit from the lens."""
    world = SimWorld("sphere", camera=default_camera(320, 240), seed=1)
    step = next(s for s in Plan.from_dict({"calibration": [{"kind": "handheld_board", "views": 4}]}).steps()
                if s.view == 2)
    world.prepare_target("handheld_board", step)
    (target,) = world.targets
    T = handheld_board_pose(CAPTURE_CHARUCO, world.camera, **handheld_view(2, 4).pose_options())
    assert np.allclose(target.points_world(0.0), CAPTURE_CHARUCO.corners_world(T))
    sc = world.scene({"light_position_mm": (0.0, 0.0, -500.0)})  # the lamp behind the board
    assert [o.name for o in sc.objects] == ["charucotarget"] and len(sc.lights) == 1
    assert np.allclose(sc.lights[0].position, world.camera.center)
    world.prepare_target("object")  # back to the lamp where the positioner put it
    (lamp,) = world.scene({"light_position_mm": (0.0, 0.0, -500.0)}).lights
    assert world.targets == [] and np.allclose(lamp.position, (0.0, 0.0, -500.0))
