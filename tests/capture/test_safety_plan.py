"""Plan caps (issue 15): counted before expanding, so a 10^9-step plan is refused at once."""
from __future__ import annotations

import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capture import plan as plan_mod
from capture.cli.capture import app as capture_app
from capture.plan import Plan, PlanError
from capture_fakes import SMALL_PLAN

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "plan.toml"
CAL_PLAN = {"turntable": {"angles_deg": [0, 30, 60]}, "light": {"azimuth_deg": [0, 90, 180],
            "elevation_deg": [20, 50]}, "polarizer": {"count": 2}, "repeats": 2,
            "exposure": {"base_s": 0.01, "stops": [-1, 0, 1]},
            "calibration": [{"kind": "dark", "frames": 4}, {"kind": "checkerboard"},
                            {"kind": "spheres", "lights": "grid"}, {"kind": "gray_card", "exposure_s": 0.1,
                             "when": "after", "turntable_angles_deg": [0, 90]},
                            {"kind": "mirror_probe", "lights": "first"}]}
HUGE = {"turntable": {"angles_deg": {"start": 0, "stop": 359.64, "step": 0.36}},
        "light": {"azimuth_deg": {"start": -180, "stop": 179.64, "step": 0.36},
                  "elevation_deg": {"start": 0, "stop": 89.91, "step": 0.09}},
        "exposure": {"base_s": 0.01}}


@pytest.mark.parametrize("plan", [Plan.from_toml(EXAMPLE), Plan.from_dict(SMALL_PLAN),
                                  Plan.from_dict(CAL_PLAN)], ids=["example", "small", "calibrations"])
def test_the_count_before_expanding_equals_the_expansion(plan):
    steps = plan.steps()
    assert plan_mod._count(plan) == (len(steps), sum(s.frames for s in steps))


def test_a_billion_step_plan_is_refused_in_well_under_a_second():
    t0 = time.perf_counter()
    with pytest.raises(PlanError, match=r"1,000,000,000 steps .* caps are 200,000 steps"):
        Plan.from_dict(HUGE)
    assert time.perf_counter() - t0 < 0.5


@pytest.mark.parametrize("change, words", [
    ({"repeats": 10**9}, "repeats = 1000000000 is more than 1000"),
    ({"calibration": [{"kind": "dark", "frames": 10**8}]}, r"calibration\[0\].frames = 100000000"),
    ({"turntable": {"angles_deg": [i * 1e-3 for i in range(200_000)]}},
     r"turntable.angles_deg has 200000 values; more than 100000"),
    ({"light": {"xyz_mm": [[i, 0, 400] for i in range(150_000)]}}, "light.xyz_mm has 150000"),
    ({"exposure": {"base_s": 0.01, "stops": list(range(100))}}, "exposure.stops has 100 stops"),
    ({"turntable": {"angles_deg": {"start": 0, "stop": 359, "step": 1}},
      "light": {"azimuth_deg": {"start": 0, "stop": 359, "step": 1}, "elevation_deg": [10, 20]}},
     "518,400 steps and 1,036,800 frames"),
])
def test_values_that_are_surely_typos_are_refused_naming_the_field(change, words):
    t0 = time.perf_counter()
    with pytest.raises(PlanError, match=words):
        Plan.from_dict({**SMALL_PLAN, **change})
    assert time.perf_counter() - t0 < 1.0


def test_caps_leave_a_large_real_plan_alone():
    plan = Plan.from_dict({"turntable": {"angles_deg": {"start": 0, "stop": 359, "step": 1}},
                           "light": {"azimuth_deg": {"start": 0, "stop": 355, "step": 5},
                                     "elevation_deg": [10, 30, 50]}, "exposure": {"base_s": 0.01}})
    assert plan_mod._count(plan) == (360 * 72 * 3, 360 * 72 * 3)


def test_capture_run_names_the_plan_file_in_its_errors(tmp_path):
    p = tmp_path / "far.toml"
    p.write_text('[turntable]\nangles_deg = [0]\n[light]\nazimuth_deg = [0]\nelevation_deg = [88]\n'
                 '[exposure]\nbase_s = 0.01\n')
    rig = tmp_path / "rig.toml"  # one simulated device: quick to start
    rig.write_text('[turntable]\ndriver = "zaber"\nport = "sim"\n')
    r = CliRunner().invoke(capture_app, ["run", str(p), "--rig", str(rig), "--store",
                                         str(tmp_path / "st"), "--quiet"])
    assert r.exit_code == 2 and f"{p}: light is given but the rig has no positioner" in " ".join(r.output.split())


def test_a_plan_the_rig_cannot_reach_leaves_no_store_folder(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text('name = "p"\n[turntable]\nangles_deg = [0]\n[light]\nazimuth_deg = [0]\n'
                    'elevation_deg = [40]\ndistance_mm = 5000\n[exposure]\nbase_s = 0.01\n')
    r = CliRunner().invoke(capture_app, ["run", str(plan), "--rig", "sim", "--store",
                                         str(tmp_path / "st"), "--quiet"])
    assert r.exit_code == 2 and "out of the positioner's reach" in r.output, r.output
    assert str(plan) in r.output and not (tmp_path / "st").exists()
