"""The ``handheld_board`` calibration kind: free board views for the intrinsics, one step per
pose, each step carrying which view it is (so a prompt and a simulated lab stage it the same
way, also after a resume)."""
from __future__ import annotations

import pytest

from capture.events import EventKind
from capture.plan import HANDHELD_VIEWS_DEFAULT, Plan, PlanError, Step, _count, step_prompt
from capture.runner import Runner, create_session
from capture.store import Store
from capture_fakes import SMALL_PLAN, make_rig


def _plan(**cal) -> Plan:
    return Plan.from_dict({**SMALL_PLAN, "calibration": [{"kind": "handheld_board", **cal},
                                                         {"kind": "dark", "frames": 2}]})


def test_expands_into_one_step_per_view_before_the_measurement():
    plan = _plan(views=5, exposure_s=0.1, frames=2)
    steps = plan.steps()
    held = [s for s in steps if s.kind == "handheld_board"]
    assert [(s.index, s.view, s.views) for s in held] == [(k, k, 5) for k in range(5)]
    # the board is held: nothing moves for it (the positioner and turntable stay put)
    assert all(s.turntable_deg is None and s.light is None and s.target == "handheld_board" for s in held)
    assert all(s.exposures_s == (0.1,) and s.repeats == 2 for s in held)
    # counted like the expansion (the plan's caps use the arithmetic count)
    assert len(steps) == 5 + 1 + 12  # views, one dark step, the 3 x 2 x 2 grid
    assert _count(plan) == (len(steps), sum(s.frames for s in steps))
    assert plan.estimate().steps == len(steps) and sum(s.frames for s in held) == 10
    assert all(s.view is None for s in steps if s.kind != "handheld_board")
    assert len([s for s in _plan().steps() if s.kind == "handheld_board"]) == HANDHELD_VIEWS_DEFAULT


def test_round_trips_through_dict_and_toml(tmp_path):
    plan = _plan(views=7)
    assert Plan.from_dict(plan.to_dict()) == plan
    assert plan.to_dict()["calibration"][0]["views"] == 7
    assert _plan(views=8).hash != plan.hash  # the view count is part of the plan
    f = tmp_path / "p.toml"
    f.write_text('[[calibration]]\nkind = "handheld_board"\nviews = 4\n')
    assert [s.view for s in Plan.from_toml(f).steps()] == [0, 1, 2, 3]
    # stored steps keep their view (resume rebuilds them from the store)
    for s in plan.steps():
        assert Step.from_dict(s.to_dict()) == s


@pytest.mark.parametrize("cal, match", [
    ({"views": 2}, r"calibration\[0\]\.views = 2 must be a whole number in 3\.\."),
    ({"views": 4.5}, r"calibration\[0\]\.views must be a whole number"),
    ({"views": "12"}, r"calibration\[0\]\.views must be a whole number"),
    ({"views": 10**6}, r"calibration\[0\]\.views = 1000000 must be"),
    ({"turntable_angles_deg": [0, 10]}, r"calibration\[0\]\.turntable_angles_deg does not apply"),
    ({"lights": "grid"}, r"calibration\[0\]\.lights does not apply"),
])
def test_bad_handheld_blocks_name_the_key(cal, match):
    with pytest.raises(PlanError, match=match):
        _plan(**cal)


def test_views_only_for_the_handheld_kind():
    with pytest.raises(PlanError, match=r"calibration\[0\]\.views is only for kind = 'handheld_board'"):
        Plan.from_dict({"calibration": [{"kind": "checkerboard", "views": 4}]})


def test_prompt_says_which_view_and_how_to_hold_the_board():
    steps = [s for s in _plan(views=12).steps() if s.kind == "handheld_board"]
    prompts = [step_prompt(s) for s in steps]
    assert prompts[2].startswith("hold the calibration board in front of the camera: view 3 of 12: ")
    assert "top-right corner of the frame" in prompts[2] and "tilted about 45°" in prompts[2]
    # the views push the board into every corner and tilt it every way
    for where in ("top-left corner", "top-right corner", "bottom-left corner", "bottom-right corner"):
        assert sum(f"{where} of the frame" in p for p in prompts) >= 1
    leans = {p.split("with its ")[1].split(" away")[0] for p in prompts}
    assert leans & {"left edge", "right edge"} and leans & {"top edge", "bottom edge"}  # both axes
    assert step_prompt(next(s for s in _plan().steps() if s.kind == "dark")) == "put the lens cap on"


def test_runner_stages_every_view_and_a_resume_restages_the_pending_one(tmp_path):
    store = Store(tmp_path / "store")
    rig = make_rig()
    create_session(store, _plan(views=4), rig, name="s", reserve_bytes=0)
    staged, prompts = [], []
    runner = Runner(rig, store, "s", reserve_bytes=0,
                    prepare_target=lambda target, step: staged.append((target, step.view)))
    runner.bus.subscribe(lambda e: e.kind == EventKind.TARGET and prompts.append((e.step, e.message, e.data)))
    # pause once view 2 (step 2) is done
    runner.bus.subscribe(lambda e: e.kind == EventKind.STEP_DONE and e.step == 2 and runner.request_pause())
    assert runner.run() == "paused"
    assert staged == [("handheld_board", 0), ("handheld_board", 1), ("handheld_board", 2)]
    assert prompts[1][0] == 1 and "view 2 of 4" in prompts[1][1] and prompts[1][2]["view"] == 1
    staged.clear()
    resumed = Runner(rig, store, "s", reserve_bytes=0,
                     prepare_target=lambda target, step: staged.append((target, step.view)))
    assert resumed.run() == "done"
    # the operator is asked for view 4 (not the scene alone), then the next scenes once each
    assert staged == [("handheld_board", 3), ("dark", None), ("object", None)]
    store.close()
