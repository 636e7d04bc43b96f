"""Which targets ``gonio calibrate`` uses without --targets: the built-in simulated lab's only for a
session recorded in it (its rig snapshots say so), else a refusal naming the fields."""
from __future__ import annotations

import pytest
from typer.testing import CliRunner

from capture.pipeline.calibrate import TargetsNeeded, calibrate_session
from capture.rigs import BUILT_IN_SCENE
from capture.cli import app
from capture.plan import Plan
from capture.runner import create_session
from capture.store import Store
from sims.lab import LAB_NAME
from sims.ptp_sim import placeholder_frame

REAL_RIG = {"turntable": {"driver": "zaber", "port": "/dev/ttyUSB0"},
            "camera": {"driver": "gphoto2", "port": "usb:001,004"}}


def _dark_session(root, config: dict) -> Store:
    """Two dark frames recorded on the rig ``config`` (as its snapshot)."""
    store = Store(root, durable=False)
    plan = Plan.from_dict({"turntable": {"angles_deg": [0]}, "exposure": {"base_s": 0.01},
                           "calibration": [{"kind": "dark", "frames": 2}]})
    create_session(store, plan, None, name="s", reserve_bytes=0)
    sid = store.session("s").id
    store.add_rig_snapshot(sid, config, {})
    for stored in store.steps(sid):
        idx, step = stored.index, stored.step
        for rep in range(step.repeats):
            store.add_frame(sid, idx, 0, rep, data=placeholder_frame(
                {"exposure_s": 0.01, "iso": 100.0, "fnumber": 8.0}, size=(64, 48), seed=rep),
                filename="f.dng", format="dng", exposure_requested_s=0.01, exposure_s=0.01,
                completes_step=rep == step.repeats - 1)
    return store


def test_a_real_rig_session_needs_targets(tmp_path):
    store = _dark_session(tmp_path / "st", REAL_RIG)
    with pytest.raises(TargetsNeeded, match="sphere_radius_mm"):
        calibrate_session(store, "s", stages=("dark",))
    assert store.results(store.session("s").id) == []
    store.close()
    r = CliRunner().invoke(app, ["calibrate", "s", "--store", str(tmp_path / "st"), "-q",
                                 "--out", str(tmp_path)])
    assert r.exit_code == 2 and "--targets" in r.output and "chessboard_square_mm" in r.output, r.output
    assert not list(tmp_path.glob("*.png"))
    targets = tmp_path / "t.toml"
    targets.write_text("chessboard_inner = [9, 6]\nchessboard_square_mm = 20.0\n"
                       "chessboard_centre_height_mm = 100.0\n")
    r = CliRunner().invoke(app, ["calibrate", "s", "--store", str(tmp_path / "st"), "-q",
                                 "--out", str(tmp_path), "--targets", str(targets)])
    assert r.exit_code in (0, 1) and "dark" in r.output, r.output  # it calibrates


BUILT_IN = {"rig": {"name": LAB_NAME, "fast": True, "camera_scene": BUILT_IN_SCENE, "camera_resolution": [64, 48]}}


@pytest.mark.parametrize("snapshots", [[BUILT_IN],
                                       [{"rig": {"name": LAB_NAME, "fast": True}}],  # a frame source of its own
                                       [BUILT_IN, REAL_RIG], []])
def test_the_built_in_labs_targets_only_for_sessions_recorded_in_it(tmp_path, snapshots):
    store = _dark_session(tmp_path / "st", snapshots[0] if snapshots else {})
    for extra in snapshots[1:]:  # resumed on another rig
        store.add_rig_snapshot(store.session("s").id, extra, {})
    if snapshots == [BUILT_IN]:
        report = calibrate_session(store, "s", stages=("dark",))
        assert report.stage("dark").status == "ok"
    else:
        with pytest.raises(TargetsNeeded, match="not in the built-in simulated lab"):
            calibrate_session(store, "s", stages=("dark",))
    store.close()
