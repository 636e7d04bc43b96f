"""Intrinsics end to end: a session captured on the simulated rig (real drivers, DNG frames)
with hand-held board views beside the turntable sweep calibrates to the focal-length target
against the simulation's true camera. More seeds, view counts and 640 x 480:
``benchmarks/handheld_intrinsics.py``."""
from __future__ import annotations

import numpy as np

from capture.pipeline.calibrate import calibrate_session
from capture.pipeline.demo_lab import DemoLab
from capture.plan import Plan
from capture.rigs import open_rig
from capture.runner import Runner, create_session
from capture.store import Store

#: the quick demo's calibration board captures (examples/demo-quick.toml)
PLAN = {"name": "board", "calibration": [
    {"kind": "dark", "frames": 2, "exposure_s": 0.15},
    {"kind": "dark", "frames": 2, "exposure_s": 0.02},
    {"kind": "handheld_board", "views": 24, "exposure_s": 0.15},
    {"kind": "checkerboard", "exposure_s": 0.02,
     "turntable_angles_deg": [300, 310, 320, 330, 340, 350, 0, 10, 20, 30, 40, 50, 60]}]}


def test_hand_held_views_bring_the_intrinsics_to_the_targets(tmp_path):
    lab = DemoLab(320, 240, seed=0)
    store = Store(tmp_path / "store", durable=False)
    with open_rig("sim", fast=True, home=True, frame_source=lab) as opened:
        create_session(store, Plan.from_dict(PLAN), opened.rig, name="board", reserve_bytes=0)
        assert Runner(opened.rig, store, "board", reserve_bytes=0, prepare_target=lab.prepare_target).run() == "done"
    rep = calibrate_session(store, "board", targets=lab.targets(), stages=("dark", "hdr", "intrinsics", "turntable"))
    intr, axis = rep.stage("intrinsics"), rep.stage("turntable")
    assert intr.status == "ok" and axis.status == "ok", (intr.reason, axis.reason)
    f = intr.figures
    true = lab.truth().camera.K
    stored = [r for r in store.results(store.session("board").id, "calibration") if r.kind == "intrinsics"][-1]
    pp_std = np.asarray(stored.result["K_std"], float)[2:4]
    # the focal length: the 0.2 % target (issue 13) is met on this seed only (-0.14 %); the noise
    # seeds 0, 1, 2 give -0.14, -0.32, -0.25 % (benchmarks/handheld_intrinsics.py runs them), the
    # turntable sweep alone -0.30 / -0.75 %; so the bound is 0.4 %, what 0.13 px corners allow at
    # 320 x 240 on any seed, as in tests/capture/test_demo.py. The principal point is at this board's
    # statistical limit at 320 x 240 (its 1-sigma ~1.8 / 1.2 px; seen -1.8 / 0.0 px; the sweep
    # alone: 1-sigma 2.9 / 2.3 px), so the check is that the stated uncertainty covers the truth
    focal_err = 100 * (np.array([f["fx_px"], f["fy_px"]]) / true[0, 0] - 1)
    pp_err = np.array([f["cx_px"], f["cy_px"]]) - true[:2, 2]
    assert np.all(np.abs(focal_err) < 0.4), focal_err
    assert np.all(pp_std < 2.2) and np.all(np.abs(pp_err) < 2 * pp_std), (pp_err, pp_std)
    # both kinds of view went in; the axis stays the sweep's alone
    assert f["views_handheld_board"] >= 22 and f["views_checkerboard"] >= 10
    assert axis.figures["views"] == f["views_checkerboard"]
    assert f["model"] == "full" and f["coverage_pct"] > 55
    store.close()
