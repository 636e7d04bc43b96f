"""``calibrate_session`` and ``gonio calibrate`` end to end on the simulated lab.

A small plan (320 x 240 sims, a few views) is captured with the Runner on the simulated rig (real
drivers over the real wire protocols); the runner's ``prepare_target`` hook swaps the simulated
scene the way an operator swaps targets. The pipeline's results are checked against the
SimWorld's ground-truth camera, turntable axis and light positions.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import capture.pipeline.calibrate as calibrate_module
from calibration.errors import TargetNotFound
from capture.pipeline.calibrate import STAGES, CalibrationReport, LabTargets, NothingToCalibrate, calibrate_session
from capture.pipeline.calibration_report import write_report
from capture.pipeline.stage_records import read_record
from capture.cli import app
from capture.plan import Plan
from capture.rigs import open_rig
from capture.runner import Runner, create_session
from capture.store import SessionNotFound, Store
from reconstruct.brdf import Lambertian
from reconstruct.raycast import Plane
from reconstruct.render import SceneObject
from background import load, save
from sims.targets import CHROME_REFLECTANCE
from sims.world import (CAPTURE_CHARUCO, SimWorld, Target, board_on_turntable, capture_targets, default_camera, light_position,
                        spheres_target)

W, H = 320, 240
SPHERE_RADIUS_MM = 25.0
#: the simulated lab's board: it fills much of the frame (a turntable sweep only ever shows the
#: board near the centre)
BOARD = CAPTURE_CHARUCO
#: three chrome balls on a bar in front of a lit backdrop (fixed in the lab)
SPHERES = spheres_target("chrome", count=3, radius_mm=SPHERE_RADIUS_MM, spacing_mm=90.0,
                         start_mm=(-120.0, -90.0, 110.0))
#: the board stands on the platter with its corner grid's centre this high (sims.world)
BOARD_CENTRE_HEIGHT_MM = float(board_on_turntable(BOARD).points_world(0.0).mean(axis=0)[2])
TARGETS = LabTargets(**capture_targets(SPHERES))
PLAN = {
    "name": "cal", "turntable": {"angles_deg": [0]},
    "light": {"azimuth_deg": [-40, 0, 40], "elevation_deg": [20, 50]},
    "polarizer": {"angles_deg": [0, 90]},
    "exposure": {"base_s": 0.02, "stops": [-2, 0]},
    "calibration": [
        {"kind": "dark", "frames": 2},
        {"kind": "handheld_board", "views": 24, "exposure_s": 0.15},   # the intrinsics' strong views
        {"kind": "checkerboard", "exposure_s": 0.02, "lights": "first",
         "turntable_angles_deg": [300, 310, 320, 330, 340, 350, 0, 10, 20, 30, 40, 50, 60]},
        {"kind": "spheres", "lights": "grid"},
        {"kind": "gray_card", "lights": "first"},
        {"kind": "mirror_probe", "when": "after"},
    ],
}


def _backdrop() -> Target:
    """A white matte board behind the sphere row, facing the camera (+x): the spheres show as
    dark discs against it."""
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = (0, 1, 0), (0, 0, 1), (1, 0, 0), (-400, 0, 150)
    obj = SceneObject(Plane((1200.0, 700.0), pose), Lambertian(0.8), "backdrop")
    return Target("backdrop", lambda ang: [obj], lambda ang: np.zeros((0, 3)), False)


class SceneSwitch:
    """The camera's frame source: renders the scene of the target the runner asked for."""

    def __init__(self) -> None:
        self.camera = default_camera(W, H)
        self.worlds = {
            "object": SimWorld("sphere", camera=self.camera, seed=1),
            "dark": SimWorld.for_capture("dark", camera=self.camera, seed=2),
            "checkerboard": SimWorld(None, camera=self.camera, targets=[board_on_turntable(BOARD)],
                                     supersample=2, seed=3),
            # a 120 mm diffuser: its highlight on a 25 mm ball spans a few pixels at 320 x 240
            "spheres": SimWorld(None, camera=self.camera, targets=[SPHERES, _backdrop()],
                                light_radius_mm=60.0, seed=4),
            "gray_card": SimWorld.for_capture("gray_card", camera=self.camera, seed=6),
            "handheld_board": SimWorld.for_capture("handheld_board", camera=self.camera, seed=7),
            "mirror_probe": SimWorld.for_capture("mirror_probe", None, camera=self.camera, seed=5),
        }
        self.current = self.worlds["object"]

    def __call__(self, state):
        return self.current.frame_source(state)

    def prepare(self, target, step) -> None:
        self.current = self.worlds[target]
        if target == "handheld_board":
            self.current.hold_board(BOARD, step)


def capture_and_calibrate(root: Path) -> None:
    """The background job (tests/background.py) behind ``session``: PLAN captured in the
    SceneSwitch's scenes into ``root / "store"`` and calibrated; the report kept beside it."""
    scenes = SceneSwitch()
    with open_rig("sim", fast=True, home=True, frame_source=scenes) as opened, \
            Store(root / "store", durable=False) as store:
        create_session(store, Plan.from_dict(PLAN), opened.rig, name="cal", reserve_bytes=0)
        runner = Runner(opened.rig, store, "cal", reserve_bytes=0, prepare_target=scenes.prepare)
        assert runner.run() == "done"
        report = calibrate_session(store, "cal", targets=TARGETS)
    save(root, report)
    save(root, write_report(report, root / "r" / "cal.png").read_bytes(), "png")
    save(root, _cli_calibrations(root), "cli")
    with _copy(root, "silhouettes") as copy:
        save(root, calibrate_session(copy, "cal", targets=TARGETS, measurement_hdr=False,
                                     stages=("dark", "hdr", "intrinsics", "lights")), "silhouettes")
    save(root, _first_spheres_step_hidden(_copy(root, "hidden")), "hidden")


def _copy(root: Path, name: str) -> Store:
    """A copy of the calibrated session's store, ``root / name / "store"``, opened."""
    shutil.copytree(root / "store", root / name / "store")
    return Store(root / name / "store", durable=False)


def _first_spheres_step_hidden(copy: Store) -> tuple[CalibrationReport, str]:
    """The calibration up to the lights on ``copy`` with the first spheres step's balls hidden
    (fewer than two show whole): (its report, the frame named)."""
    known, lost = calibrate_module._known_spheres, []

    def first_step_hidden(ctx, K, dist, radius, shape, frame, reading):
        if not lost:
            lost.append(frame)
            raise TargetNotFound("1 of the 3 configured spheres project whole and unoccluded", frame=frame)
        return known(ctx, K, dist, radius, shape, frame, reading)
    calibrate_module._known_spheres = first_step_hidden
    try:
        with copy:
            report = calibrate_session(copy, "cal", targets=TARGETS, measurement_hdr=False,
                                       stages=("dark", "hdr", "intrinsics", "turntable", "lights"))
    finally:
        calibrate_module._known_spheres = known
    return report, lost[0]


@dataclass(frozen=True)
class CliCalibrations:
    """``gonio calibrate`` twice on a copy of the calibrated session's store, with a --targets
    file: (exit code, output) of the table run (``--quiet``) and of the ``--json`` run; the
    results stored before and after the first; the size of the PNG report it wrote, bytes."""

    table: tuple[int, str]
    json: tuple[int, str]
    results_before: int
    results_after_table: int
    png_bytes: int


def _cli_calibrations(root: Path) -> CliCalibrations:
    targets = root / "targets.toml"
    targets.write_text(f"charuco_squares = [10, 7]\ncharuco_square_mm = 28.0\ncharuco_marker_mm = 21.0\n"
                       f"sphere_radius_mm = {SPHERE_RADIUS_MM}\nsphere_reflectance = {CHROME_REFLECTANCE}\n"
                       f"charuco_centre_height_mm = {BOARD_CENTRE_HEIGHT_MM}\n"
                       f"sphere_centres_mm = {SPHERES.points_world(0.0).tolist()}\n")
    copy = root / "cli" / "store"
    shutil.copytree(root / "store", copy)

    def results() -> int:
        with Store(copy, readonly=True) as store:
            return len(store.results(store.session("cal").id))

    def calibrate(*flags: str) -> tuple[int, str]:
        r = CliRunner().invoke(app, ["calibrate", "cal", "--store", str(copy), "--targets", str(targets),
                                     "--out", str(root / "cli" / "out"), *flags])
        return r.exit_code, r.output
    before = results()
    table = calibrate("--quiet")
    after, png = results(), (root / "cli" / "out" / "cal-calibration.png").stat().st_size
    return CliCalibrations(table, calibrate("-q", "--json"), before, after, png)


@pytest.fixture(scope="module")
def session(background):
    """(store, calibration report, the scenes' camera, folder) of PLAN's session."""
    root = background.folder("calibrate")
    store = Store(root / "store", durable=False)
    yield store, load(root), default_camera(W, H), root   # the SceneSwitch's camera
    store.close()


def _stored(store: Store) -> dict[str, dict]:
    return {r.kind: r for r in store.results(store.session("cal").id, "calibration")}


def _angle_deg(u, v) -> float:
    u, v = np.asarray(u, float), np.asarray(v, float)
    return float(np.degrees(np.arccos(np.clip(u @ v / np.linalg.norm(u) / np.linalg.norm(v), -1, 1))))


def test_every_stage_runs_in_order_and_is_stored_with_provenance(session):
    store, report, _, _ = session
    assert [s.stage for s in report.stages] == list(STAGES)
    assert not report.failed, [(s.stage, s.reason) for s in report.failed]
    assert all(s.status == "ok" for s in report.stages), [(s.stage, s.reason) for s in report.stages]
    stored = _stored(store)
    info = store.session("cal")
    frames = {f.id: f for f in store.frames(info.id)}
    steps = {s.index: s.step for s in store.steps(info.id)}
    for s in report.stages:
        r = next(x for x in store.results(info.id) if x.id == s.calibration_id)
        assert r.input_frames and set(r.input_frames) <= set(frames)
        assert r.code_version.startswith("gonio ")
    def kinds_of(kind):
        return {steps[frames[i].step].kind for i in stored[kind].input_frames}
    assert kinds_of("intrinsics") == {"checkerboard", "handheld_board"}
    assert kinds_of("light_positions") == {"spheres"}
    assert kinds_of("dark") == {"dark"}
    assert stored["intrinsics"].params["targets"]["sphere_radius_mm"] == SPHERE_RADIUS_MM
    # the master darks are stored as objects and read back as arrays of the sensor's size
    arts = stored["dark"].artifacts
    assert sorted(arts) == ["dark_0.005s.npy", "dark_0.02s.npy"]
    import io
    dark = np.load(io.BytesIO(store.read_object(arts["dark_0.02s.npy"])))
    assert dark.shape == (H, W)


def test_dark_read_noise_matches_the_sensor(session):
    store, report, _, _ = session
    from sims.sensor import SensorModel
    sensor = SensorModel.full_frame()
    # read noise in DN plus ADC quantisation (1/12 DN^2); dark current is negligible at 20 ms
    truth = np.hypot(sensor.read_noise_e / sensor.e_per_dn(100.0), np.sqrt(1 / 12))
    assert report.stage("dark").figures["read_noise_dn"] == pytest.approx(truth, rel=0.1)


def test_intrinsics_match_the_sim_camera(session):
    store, report, camera, _ = session
    r = _stored(store)["intrinsics"].result
    K, K_std = np.array(r["K"]), np.array(r["K_std"])
    assert r["target"] == "charuco" and r["image_size"] == [W, H]
    assert r["rms_px"] < 0.4
    # focal length within 1.5 % (seen: -0.16 / -0.22 % with the hand-held views; the sweep alone
    # 0.6 %); the principal point is the weakest parameter: within 4 sigma of its stated
    # uncertainty and 12 px (seen: 0.0, 0.9 px, 1-sigma 1.9, 1.3; the sweep alone 1.7, 8.9 px)
    for i in (0, 1):
        assert K[i, i] == pytest.approx(camera.K[i, i], rel=0.015)
    for i, (row, col) in enumerate([(0, 2), (1, 2)]):
        err = abs(K[row, col] - camera.K[row, col])
        assert err < 12.0 and err < 4 * K_std[2 + i], (err, K_std)


def test_turntable_axis_matches_the_sim(session):
    store, report, camera, _ = session
    r = _stored(store)["turntable"].result
    truth = camera.R @ np.array([0.0, 0.0, 1.0])  # world +z (the platter axis) in the camera frame
    # seen: 0.9 deg, mostly from the principal point error above
    assert _angle_deg(r["axis_camera"], truth) < 1.5
    assert r["rms_px"] < 0.4
    # the turntable's readings turn the platter counter-clockwise (sims: Rz(angle))
    assert r["angle_scale"] == 1.0
    readings = np.array(r["readings_deg"])
    assert sorted(np.round(readings % 360)) == sorted([300, 310, 320, 330, 340, 350, 0, 10, 20, 30, 40, 50])


def _light_truth(camera, light) -> np.ndarray:
    return camera.R @ light_position(light.azimuth_deg, light.elevation_deg) + camera.t


def test_light_positions_match_the_sim(session):
    store, report, camera, _ = session
    r = read_record(_stored(store)["light_positions"])
    centres = r.sphere_centres_camera_mm
    truth_centres = SPHERES.points_world(0.0) @ camera.R.T + camera.t
    # sphere centres from their known lab positions through the fitted lab frame (turntable fit
    # + board height; azimuth 0 towards the camera): within 3 % of their distance (seen: 14 mm,
    # 1.8 %, a common shift from the 320 x 240 intrinsics and axis)
    distance = np.linalg.norm(truth_centres, axis=1)
    assert r.sphere_centres_from.startswith("known")
    assert np.all(np.linalg.norm(centres - truth_centres, axis=1) < 0.03 * distance), centres - truth_centres
    assert np.allclose(r.sphere_centres_lab_mm, SPHERES.points_world(0.0), atol=1e-6)
    assert len(r.lights) == 6
    mid = truth_centres.mean(axis=0)
    for row in r.lights:
        t = _light_truth(camera, row.commanded)
        p = row.position_camera_mm
        # This fixture is far from the lights' 0.5 % / 0.25 deg target, which the full demo meets
        # at 640 x 480 (docs/measurements.md): at 320 x 240 a 25 mm ball is ~21 px wide, and three
        # balls 180 mm apart triangulate a light 500 mm away with ~25 mm depth error per 0.1 px of
        # highlight or sphere-centre error, plus the lab frame's 14 mm shift. Bounds: the measured
        # worst plus ~25 % (seen: direction 0.5-2.4 deg; distance 3-16 % long, never short)
        assert _angle_deg(p - mid, t - mid) < 3.0, (p, t)
        assert -0.02 < np.linalg.norm(p - mid) / np.linalg.norm(t - mid) - 1 < 0.20, (p, t)


def test_lights_fall_back_to_silhouettes_without_a_lab_frame(session):
    """Known positions need the lab frame; without the turntable stage the spheres are found
    from their silhouettes against the backdrop (perspective cone fit, K from the session)."""
    _, _, camera, root = session
    report = load(root, "silhouettes")   # the stages up to the lights, on a copy (the job's)
    assert report.stage("lights").status == "ok", report.stage("lights").reason
    assert report.stage("lights").figures["centres"] == "silhouettes"
    with Store(root / "silhouettes" / "store", readonly=True) as store:
        r = read_record(next(x for x in store.results(store.session("cal").id)
                             if x.id == report.stage("lights").calibration_id))
    truth = SPHERES.points_world(0.0) @ camera.R.T + camera.t
    # within 4 % of their distance (seen: 2.1-3.6 %, the silhouette's depth from a ~40 px disc)
    err = np.linalg.norm(r.sphere_centres_camera_mm - truth, axis=1)
    assert np.all(err < 0.04 * np.linalg.norm(truth, axis=1)), err
    assert len(r.lights) == 6 and r.lights[0].position_lab_mm is None and r.sphere_centres_lab_mm is None


def test_lab_frame_matches_the_sim_world(session):
    """The lab frame (axis at the platter, +x towards the camera) is the sims' world frame: the
    camera centre lands on the simulated eye point."""
    store, _, camera, _ = session
    r = _stored(store)["turntable"].result
    eye = camera.center
    got = np.array(r["camera_centre_lab_mm"])
    # seen: ~3 % of the distance, mostly the focal length of a 320 x 240 intrinsics fit (scale)
    assert abs(got[1]) < 1e-6 * np.linalg.norm(eye)  # +x is defined through the camera
    assert np.linalg.norm(got - eye) < 0.05 * np.linalg.norm(eye), (got, eye)
    R = np.array(r["lab_to_camera"]["R"])
    assert _angle_deg(R[:, 2], camera.R[:, 2]) < 1.5


def _scene_targets(**overrides) -> LabTargets:
    """The targets of the sims' ``SimWorld.for_capture`` scenes (steel-ball row, ChArUco)."""
    return LabTargets(**{**capture_targets(), **overrides})


def test_lab_targets_validation():
    t = _scene_targets(sphere_centres_mm=[[0, 0, 100], [0, 60, 100]])  # TOML lists
    assert t.sphere_centres_mm == ((0.0, 0.0, 100.0), (0.0, 60.0, 100.0))
    assert _scene_targets(sphere_centres_mm=[]).sphere_centres_mm is None  # silhouettes instead
    with pytest.raises(ValueError, match="sphere_centres_mm must hold >= 2"):
        _scene_targets(sphere_centres_mm=[[0, 0, 100]])
    with pytest.raises(ValueError, match="less than a sphere's diameter"):
        _scene_targets(sphere_centres_mm=[[0, 0, 100], [0, 10, 100]])
    # a real lab states its own: no board, or half a board, is an error naming the fields
    with pytest.raises(ValueError, match="at least one board"):
        LabTargets()
    with pytest.raises(ValueError, match="missing chessboard_centre_height_mm"):
        LabTargets(chessboard_inner=(9, 6), chessboard_square_mm=20.0)


def test_scene_targets_come_from_the_sim_scenes():
    """sims.world.capture_targets() states the for_capture scenes' own targets: the boards and
    balls they render (their corner grids' centres and ball centres from the scene objects)."""
    t = _scene_targets()
    worlds = {k: SimWorld.for_capture(k) for k in ("checkerboard", "charuco", "spheres")}
    np.testing.assert_allclose(t.sphere_centres_mm, worlds["spheres"].targets[0].points_world(0.0))
    # both board captures show the lab's ChArUco; no scene shows a chessboard, so none is stated
    for kind in ("checkerboard", "charuco"):
        board = worlds[kind].targets[0]
        assert t.charuco_centre_height_mm == pytest.approx(board.points_world(0.0).mean(axis=0)[2])
        assert (board.spec.squares, board.spec.square_mm) == (t.charuco_squares, t.charuco_square_mm)
    assert t.chessboard_inner is None


def test_positioner_model_gives_every_measurement_step_a_light(session):
    store, report, camera, _ = session
    r = _stored(store)["positioner_model"].result
    info = store.session("cal")
    steps = {s.index: s.step for s in store.steps(info.id)}
    measured = {row["step"]: row for row in r["step_lights"]}
    measure_steps = [i for i, d in steps.items() if d.kind == "measure"]
    assert set(measure_steps) <= set(measured)
    mid = SPHERES.points_world(0.0).mean(axis=0) @ camera.R.T + camera.t
    for i in measure_steps:
        t = _light_truth(camera, steps[i].light)
        p = np.array(measured[i]["position_camera_mm"])
        # the arm model through the six lights above (seen: direction <= 1.5 deg, distance 7.6-11.8 %
        # long; the 0.5 % target holds at 640 x 480 only): the measured worst plus ~25 %
        assert _angle_deg(p - mid, t - mid) < 2.0, (p, t)
        assert -0.02 < np.linalg.norm(p - mid) / np.linalg.norm(t - mid) - 1 < 0.15, (p, t)


def _truth_dn_per_s(world, frame, polarizer_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The sensor model's noise-free signal of a stored frame's scene, DN/s per photosite, and
    the photosites' channels: the ground truth the HDR merge and demosaic are checked against."""
    t = 0.005  # short: nothing clips
    gt = world.ground_truth({"turntable_deg": frame.positions["turntable_deg"], "exposure_s": t, "iso": 100.0,
                             "light_position_mm": frame.positions["light_mm"], "polarizer_deg": polarizer_deg})
    dn_s = (gt.expected.mean_dn - world.sensor.black_level) / t
    return dn_s, world.sensor.cfa_channels(*dn_s.shape), gt


def test_polarization_gray_card_and_probe(session):
    store, report, _, _ = session
    stored = _stored(store)
    info = store.session("cal")
    worlds = SceneSwitch().worlds  # the same deterministic scenes the session was captured in
    poses = stored["polarization_check"].result["poses"]
    assert len(poses) == 4 and all(p["method"] == "parallel/crossed" for p in poses)
    # specular fraction against the renderer's truth: (parallel - crossed) / (parallel + crossed)
    # per channel (equal weights, as the demosaiced image has), from the noise-free sensor signal
    for pose in poses:
        sums = []
        for step, angle in zip(pose["steps"], pose["angles_deg"]):
            dn_s, ch, _ = _truth_dn_per_s(worlds["object"], store.frames(info.id, step=step)[0], angle)
            sums.append(np.array([dn_s[ch == c].mean() for c in range(3)]))
        par, cro = sums if abs(pose["angles_deg"][0] % 180) < 45 else sums[::-1]
        truth = float((par - cro).sum() / (par + cro).sum())
        # the check clamps parallel - crossed at 0 pixel by pixel, so noise adds a little
        # (seen: 0.030 for a true 0.025); an analyser at the wrong angle gives ~0 or ~2x
        assert truth > 0.01 and abs(pose["specular_fraction"] - truth) < 0.4 * truth, (pose, truth)
    # the gray card's value per channel against the same truth on the card's (eroded) pixels
    card = stored["gray_card"].result
    # the card's spread is the lamp's fall-off across it plus cos^4 vignetting (seen: 11 %)
    assert len(card["cards"]) == 1 and card["cards"][0]["relative_spread"] < 0.2
    row = card["cards"][0]
    dn_s, ch, gt = _truth_dn_per_s(worlds["gray_card"], store.frames(info.id, step=row["step"])[0], 0.0)
    import cv2
    card_index = [o.name for o in gt.scene.objects].index("gray_card")
    on_card = gt.buffers.mask & (gt.buffers.surface_index == card_index)
    inner = cv2.erode(on_card.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    truth_rgb = np.array([np.median(dn_s[inner & (ch == c)]) for c in range(3)])
    np.testing.assert_allclose(row["value_rgb"], truth_rgb, rtol=0.03)
    np.testing.assert_allclose(card["relative_scale_rgb"], card["albedo"] / truth_rgb, rtol=0.03)
    probe = stored["environment_map"]
    assert probe.result["frame"] == "lab" and probe.result["valid_fraction"] > 0.9
    import io
    env = np.load(io.BytesIO(store.read_object(probe.artifacts["environment.npz"])))
    # the probe keeps its own resolution: at least 128 x 256, one row per pixel of sphere radius
    h = env["env"].shape[0]
    assert h >= 128 and h >= probe.result["views"][0]["radius_px"]
    assert env["env"].shape == (h, 2 * h, 3) and np.all(np.isfinite(env["env"]))
    # the blind cone behind the sphere (15 deg half-angle) is masked out: the solid angle left is
    # 1 - (1 - cos 15 deg) / 2 of the sphere (closed form; lat-long rows weighted by sin(theta))
    assert np.array_equal(env["mask"], env["weight"] > 0)
    sin_t = np.sin((np.arange(h) + 0.5) * np.pi / h)[:, None]
    seen = float((env["mask"] * sin_t).sum() / (sin_t.sum() * 2 * h))
    assert seen == pytest.approx(1 - (1 - np.cos(np.radians(15))) / 2, abs=0.004)


def test_report_png_written(session):
    """The report's PNG (``write_report`` of the session's calibration, by the job)."""
    data = load(session[3], "png")
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 50_000


def test_cli_calibrate_table_report_and_exit_code(session):
    cli = load(session[3], "cli")   # the job's CliCalibrations
    code, output = cli.table
    assert code == 0, output
    for stage in STAGES:
        assert stage in output
    assert "rms_px" in output and "axis" in output
    assert cli.png_bytes > 50_000
    # every stage, and the record that closes a whole run (capture.pipeline.calibration_record)
    assert cli.results_after_table == cli.results_before + len(STAGES) + 1
    code, output = cli.json
    assert code == 0, output
    out = json.loads(output)
    assert [s["stage"] for s in out["stages"]] == list(STAGES)
    assert out["report"].endswith("cal-calibration.png")
    assert out["stages"][2]["figures"]["fx_px"] > 0


def test_cli_unknown_session_and_bad_targets(session, tmp_path):
    _, _, _, root = session
    r = CliRunner().invoke(app, ["calibrate", "nope", "--store", str(root / "store")])
    assert r.exit_code == 2 and "no session 'nope'" in r.output
    bad = tmp_path / "t.toml"
    bad.write_text("sphere_diameter_mm = 25\n")
    r = CliRunner().invoke(app, ["calibrate", "cal", "--store", str(root / "store"), "--targets", str(bad)])
    assert r.exit_code == 2 and "unknown key(s) sphere_diameter_mm" in r.output
    with pytest.raises(SessionNotFound):
        calibrate_session(Store(root / "store", durable=False), "nope")


def test_session_without_calibration_captures(tmp_path):
    store = Store(tmp_path / "s", durable=False)
    plan = Plan.from_dict({"turntable": {"angles_deg": [0, 90]}})
    create_session(store, plan, None, name="meas", reserve_bytes=0)
    with pytest.raises(NothingToCalibrate, match="no stored frames yet"):
        calibrate_session(store, "meas")
    sid = store.session("meas").id
    store.add_frame(sid, 0, 0, 0, data=b"not a raw file", filename="a.dng", format="dng",
                    exposure_requested_s=0.01, exposure_s=0.01, completes_step=True)
    with pytest.raises(NothingToCalibrate, match=r"no calibration captures \(its stored steps are measure\)"):
        calibrate_session(store, "meas")
    store.close()
    r = CliRunner().invoke(app, ["calibrate", "meas", "--store", str(tmp_path / "s"), "--quiet"])
    assert r.exit_code == 3 and "no calibration captures" in r.output


def _bad_session(tmp_path) -> Store:
    """Darks and three checkerboard steps of stand-in frames; step 3's frame is not a raw file."""
    from sims.ptp_sim import placeholder_frame
    store = Store(tmp_path / "s", durable=False)
    plan = Plan.from_dict({"turntable": {"angles_deg": [0]}, "exposure": {"base_s": 0.01},
                           "calibration": [{"kind": "dark", "frames": 2},
                                           {"kind": "checkerboard", "turntable_angles_deg": [0, 20, 40]}]})
    create_session(store, plan, None, name="bad", reserve_bytes=0)
    sid = store.session("bad").id
    for stored in store.steps(sid):
        idx, step = stored.index, stored.step
        for rep in range(step.repeats):
            data = placeholder_frame({"exposure_s": 0.01, "iso": 100.0, "fnumber": 8.0},
                                     size=(64, 48), seed=idx + rep)
            if step.kind == "checkerboard" and idx == 3:
                data = b"garbage"
            store.add_frame(sid, idx, 0, rep, data=data, filename="f.dng", format="dng",
                            exposure_requested_s=0.01, exposure_s=0.01, positions={"turntable_deg": 0.0},
                            completes_step=rep == step.repeats - 1)
    return store


def test_a_spheres_step_whose_balls_do_not_show_loses_only_its_step(session):
    """A turntable angle at which fewer than two configured balls show whole (one left the
    frame, one behind another): that step is named and left out, the other lights are located
    (:func:`_first_spheres_step_hidden`, on a copy of the store, by the job)."""
    _, before, _, root = session
    report, lost = load(root, "hidden")
    lights = report.stage("lights")
    assert lights.status == "failed" and lost in lights.reason and lights.calibration_id
    assert lights.figures["lights"] == before.stage("lights").figures["lights"] - 1


def test_a_failing_stage_names_the_frame_and_the_rest_continue(tmp_path):
    """A checkerboard step whose frame is not a raw file: hdr reports it (naming the frame) and
    merges the other steps; intrinsics finds no board in the stand-in frames and says where;
    the turntable skips for want of intrinsics; dark runs regardless."""
    store = _bad_session(tmp_path)
    sid = store.session("bad").id
    report = calibrate_session(store, "bad", targets=_scene_targets())
    bad_frame = store.frames(sid, step=3)[0].id
    assert report.stage("dark").status == "ok"
    assert report.stage("hdr").status == "failed"
    assert f"frame {bad_frame} (step 3)" in report.stage("hdr").reason
    assert report.stage("hdr").figures["failed_steps"] == 1 and report.stage("hdr").calibration_id
    intr = report.stage("intrinsics")
    assert intr.status == "failed" and "found in 0 of 2 board steps" in intr.reason
    assert f"frame {store.frames(sid, step=1)[0].id} (step 1)" in intr.reason
    assert report.stage("turntable").status == "skipped" and "intrinsics" in report.stage("turntable").reason
    assert report.stage("lights").reason == "no spheres captures in this session"
    store.close()


def test_a_programming_error_in_a_stage_raises(tmp_path, monkeypatch):
    """Only bad data fails a stage: a bug (here a ValueError that is no CalibrationError, as a
    wrong numpy call would raise) must surface, not be reported as a failed stage."""
    import capture.pipeline.calibrate as cal

    def broken(*args, **kwargs):
        raise ValueError("operands could not be broadcast together")
    monkeypatch.setattr(cal, "master_frame", broken)
    store = _bad_session(tmp_path)
    with pytest.raises(ValueError, match="operands could not be broadcast"):
        calibrate_session(store, "bad", targets=_scene_targets())
    store.close()


def test_calibration_hdr_only_skips_measurement_steps(session):
    store, _, _, _ = session
    info = store.session("cal")
    kinds = {s.index: s.step.kind for s in store.steps(info.id)}
    report = calibrate_session(store, "cal", targets=TARGETS, measurement_hdr=False,
                               stages=("dark", "hdr", "polarization"))
    hdr = next(r for r in store.results(info.id) if r.id == report.stage("hdr").calibration_id)
    merged = {m["step"] for m in hdr.result["steps"]}
    assert merged == {i for i, k in kinds.items() if k not in ("dark", "measure")}
    # the polarization check merges the measurement poses it needs by itself
    assert report.stage("polarization").status == "ok"
    assert report.stage("intrinsics").reason == "not requested"


# -- the sims' SimWorld.for_capture scenes (steel-ball row, no backdrop) on the simulated rig ---------
DEFAULT_PLAN = {
    "name": "default", "turntable": {"angles_deg": [0]},
    "light": {"azimuth_deg": [-40, 40], "elevation_deg": [20, 50]},
    "exposure": {"base_s": 0.02, "stops": [-2, 0]},
    "calibration": [
        {"kind": "dark", "frames": 2},
        # the default chessboard seen from the front (its print shows through from behind in
        # the sims, mirrored, which no turntable fit can use)
        {"kind": "checkerboard", "exposure_s": 0.02, "turntable_angles_deg": [315, 330, 345, 0, 15, 30, 45]},
        # one exposure short enough that the lamp's image does not clip (clipped colour channels
        # of a 2-3 px highlight shift its centroid by tenths of a pixel after demosaicing)
        {"kind": "spheres", "exposure_s": 0.00025},
    ],
}


def capture_and_calibrate_default(root: Path) -> None:
    """The background job behind ``default_session``: DEFAULT_PLAN captured on ``--rig sim`` with
    the sphere object and the ``SimWorld.for_capture`` scenes as the frame source and scene
    switcher into ``root / "store"``, then calibrated with those scenes' targets."""
    world = SimWorld("sphere", camera=default_camera(W, H))
    with open_rig("sim", fast=True, home=True, frame_source=world.frame_source) as opened, \
            Store(root / "store", durable=False) as store:
        create_session(store, Plan.from_dict(DEFAULT_PLAN), opened.rig, name="default", reserve_bytes=0)
        runner = Runner(opened.rig, store, "default", reserve_bytes=0, prepare_target=world.prepare_target)
        assert runner.run() == "done"
        save(root, calibrate_session(store, "default", targets=_scene_targets(), measurement_hdr=False))


@pytest.fixture
def default_session(background):
    """(store, calibration report, camera) of DEFAULT_PLAN's session."""
    root = background.folder("calibrate-default")
    with Store(root / "store", durable=False) as store:
        yield store, load(root), default_camera(W, H)


def _located_lights(store, camera):
    """(light rows, truth camera-frame positions, truth sphere centres) of the default session."""
    r = {x.kind: x for x in store.results(store.session("default").id, "calibration")}
    lights = read_record(r["light_positions"])
    truth_centres = spheres_target("steel").points_world(0.0) @ camera.R.T + camera.t
    return lights, [_light_truth(camera, row.commanded) for row in lights.lights], truth_centres


def test_default_sim_session_locates_lights_from_known_sphere_positions(default_session):
    """The for_capture scenes at 320 x 240: their steel-ball row has no backdrop, so the sphere centres
    come from LabTargets' known positions through the lab frame. Each 1-inch ball is ~20 px
    wide and the 50 mm lamp's highlight on it ~1 px: a 0.1 px highlight error moves a light
    ~5 % of its distance here, and the constrained intrinsics of a small board at this size
    scale the lab frame by ~3 % (seen: lights 12-22 % short, 1.6-4.8 deg). So this test holds
    the pipeline to honesty (each light within 3 sigma of its stated uncertainty, lights that
    fewer than 2 balls show reported unseen); the full-resolution test below holds accuracy."""
    store, report, camera = default_session
    for stage in ("intrinsics", "turntable", "lights"):
        assert report.stage(stage).status == "ok", (stage, report.stage(stage).reason)
    lights, truths, truth_centres = _located_lights(store, camera)
    assert lights.sphere_centres_from.startswith("known")
    # centres through the fitted lab frame: within 4 % of their distance (seen: 2.9 %, mostly the
    # focal length of a constrained 320 x 240 intrinsics fit from a small board)
    err = np.linalg.norm(lights.sphere_centres_camera_mm - truth_centres, axis=1)
    assert np.all(err < 0.04 * np.linalg.norm(truth_centres, axis=1)), err
    assert len(lights.lights) + len(lights.unseen) == 4 and lights.lights
    assert all(u.spheres_showing_lamp < 2 for u in lights.unseen)
    mid = truth_centres.mean(axis=0)
    for row, t in zip(lights.lights, truths):
        p = row.position_camera_mm
        # the stated uncertainty is honest: the error lies within 3 sigma of it
        assert np.linalg.norm(p - t) < 3 * np.linalg.norm(row.std_mm), (p, t, row.std_mm)
        # and the light is where the sim put it, to what this resolution allows: seen from the
        # ball row, within 6 deg and 30 % of its distance (seen: 1.6-4.8 deg, 12-22 % short)
        assert _angle_deg(p - mid, t - mid) < 6.0
        assert abs(np.linalg.norm(p - mid) / np.linalg.norm(t - mid) - 1) < 0.3
