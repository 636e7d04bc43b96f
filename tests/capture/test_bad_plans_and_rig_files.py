"""Plans and rig files a hostile or careless user writes (issue 19 #6 #9): every value is refused
before anything is expanded or opened, by a message naming the file and the field, with exit
status 2 and no file written."""
from __future__ import annotations

import time

import pytest
from typer.testing import CliRunner

from capture import plan as plan_mod
from capture.cli.capture import app as capture_app
from capture.plan import Plan, PlanError
from capture.rigs import recorded_in_built_in_lab
from rig.rig import ConfigError, Rig, load_config

cli = CliRunner()
HEAD = 'name = "p"\n[turntable]\nangles_deg = [0]\n'


def _files(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.mark.parametrize("text, words", [
    (HEAD + "[exposure]\nbase_s = 0.01\nstops = [2000]\n", r"exposure.stops\[0\] = 2000 gives base_s x 2\^stop outside"),
    (HEAD + "[exposure]\nbase_s = 0.01\nstops = [-60]\n", r"exposure.stops\[0\] = -60"),
    (HEAD + "[exposure]\nbase_s = nan\n", "exposure.base_s = nan must be a positive number"),
    (HEAD + "[exposure]\nbase_s = 1e300\n", "exposure.base_s = 1e.300 must be a positive number"),
    (HEAD + "[exposure]\niso = inf\n", "exposure.iso = inf must be positive"),
    ('[turntable]\nangles_deg = { start = 0, stop = nan, step = 1 }\n', "turntable.angles_deg.stop = nan is not a finite"),
    ('[turntable]\nangles_deg = { start = -inf, stop = 0, step = 1 }\n', "turntable.angles_deg.start = -inf"),
    ('[turntable]\nangles_deg = { start = 0, stop = 10, step = inf }\n', "turntable.angles_deg.step = inf"),
    (HEAD + "[light]\nazimuth_deg = [0]\nelevation_deg = [30]\ndistance_mm = inf\n",
     "light.distance_mm = inf must be a positive finite number"),
    (HEAD + '[[calibration]]\nkind = "dark"\nexposure_s = [0.01, nan]\n',
     r"calibration\[0\].exposure_s\[1\] = nan must be a number of seconds"),
    (HEAD + '[[calibration]]\nkind = "gray_card"\nexposure_s = inf\n', r"calibration\[0\].exposure_s = inf"),
    (HEAD + "[[calibration]]\nkind = ['dark']\n", r"calibration\[0\].kind must be a string, got a list"),
    (HEAD + '[[calibration]]\nkind = "dark"\nwhen = 1\n', r"calibration\[0\].when must be a string"),
    (HEAD + '[[calibration]]\nkind = "dark"\nexposure_s = [' + "0.01, " * 100 + "0.02]\n",
     r"calibration\[0\].exposure_s has 101 exposures"),
    ("a = " + "[" * 100_000 + "]" * 100_000 + "\n", "nested too deep to be a plan file"),
    ("\x00\x01binary", "not valid TOML"),
], ids=lambda v: v[:40] if isinstance(v, str) and len(v) > 40 else None)
def test_a_bad_plan_file_is_refused_naming_the_file_and_field(tmp_path, text, words):
    path = tmp_path / "plan.toml"
    path.write_text(text)
    with pytest.raises(PlanError, match=words) as err:
        Plan.from_toml(path)
    assert str(path) in str(err.value)
    r = cli.invoke(capture_app, ["plan", str(path)])
    assert r.exit_code == 2 and "Traceback" not in r.output and str(path) in " ".join(r.output.split())
    assert _files(tmp_path) == ["plan.toml"]


def test_held_out_lights_count_towards_the_step_cap_before_expanding():
    # 600 held-out lights x 360 angles once passed the 200,000-step cap and ran out of memory
    plan = {"turntable": {"angles_deg": {"start": 0, "stop": 359, "step": 1}},
            "light": {"azimuth_deg": [0], "elevation_deg": [10],
                      "held_out_deg": [[a * 0.5, 45] for a in range(600)]}}
    t0 = time.perf_counter()
    with pytest.raises(PlanError, match="216,360 steps"):
        Plan.from_dict(plan)
    assert time.perf_counter() - t0 < 0.5
    with pytest.raises(PlanError, match="held_out_deg has 100001 lights"):
        Plan.from_dict({**plan, "light": {**plan["light"], "held_out_deg": [[0, 1]] * 100_001}})


def test_the_count_with_held_out_lights_equals_the_expansion():
    p = Plan.from_dict({"turntable": {"angles_deg": [0, 90, 180]}, "polarizer": {"count": 2},
                        "light": {"azimuth_deg": [0, 90], "elevation_deg": [30],
                                  "held_out_deg": [[45, 40], [135, 20]]},
                        "exposure": {"base_s": 0.01, "stops": [0, 1]},
                        "calibration": [{"kind": "spheres", "lights": "grid"}, {"kind": "dark"}]})
    steps = p.steps()
    assert plan_mod._count(p) == (len(steps), sum(s.frames for s in steps))


def test_a_plan_saved_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "bom.toml"
    path.write_bytes("\ufeff".encode() + (HEAD + "[exposure]\nbase_s = 0.01\n").encode())
    assert Plan.from_toml(path).turntable_deg == (0.0,)


@pytest.mark.parametrize("text, words", [
    ('[turntable]\ndriver = "zaber"\nport = "sim"\ntimeout_s = 1e308\n', r"\[turntable\] timeout_s = 1e\+308 s is more than"),
    ('[positioner]\ndriver = "grbl"\nport = "sim"\nkinematics = 5\n', r"\[positioner\] kinematics = 5 must be"),
    ('[positioner]\ndriver = "grbl"\nport = "sim"\n[positioner.kinematics]\ntype = "arm"\ncentre_mm = [0.0, 0.0]\n',
     r"\[positioner\] kinematics 'arm': centre_mm must be 3 finite numbers|\[positioner\] centre_mm must be 3"),
    ('[positioner]\ndriver = "grbl"\nport = "sim"\n[positioner.kinematics]\ntype = "arm"\nradius_mm = inf\n',
     r"\[positioner\] kinematics: every number must be finite"),
    ('rig = "lab A"\n[turntable]\ndriver = "zaber"\nport = "sim"\n', r"rig = 'lab A' must be a table"),
], ids=["timeout", "kinematics-number", "centre-2", "radius-inf", "rig-text"])
def test_a_bad_rig_file_is_refused_naming_the_file_section_and_key(tmp_path, text, words):
    path = tmp_path / "rig.toml"
    path.write_text(text.replace('"sim"', '"/dev/x"'))   # checked without starting simulators
    with pytest.raises(ConfigError, match=words) as err:
        Rig.from_config(load_config(path), where=str(path))
    assert str(path) in str(err.value)
    path.write_text(text)
    plan = tmp_path / "plan.toml"
    plan.write_text(HEAD + "[exposure]\nbase_s = 0.01\n")
    r = cli.invoke(capture_app, ["plan", str(plan), "--rig", str(path)])
    assert r.exit_code == 2 and "Traceback" not in r.output, r.output
    assert _files(tmp_path) == ["plan.toml", "rig.toml"]


def test_a_session_stored_with_a_rig_text_instead_of_a_table_is_not_the_built_in_lab():
    # stores written before the check: `process` read [rig] as a table and crashed
    assert recorded_in_built_in_lab([{"config": {"rig": "lab A"}}]) is False
