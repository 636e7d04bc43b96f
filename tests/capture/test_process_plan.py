"""Plans with held-out lights and the passive capture kind (capture/plan.py)."""
from __future__ import annotations

import pytest

from capture.plan import Plan, PlanError, Step

BASE = {"turntable": {"angles_deg": [0, 90]},
        "light": {"azimuth_deg": [0, 40], "elevation_deg": [30], "held_out_deg": [[20, 50], [-30, 60]]},
        "polarizer": {"angles_deg": [0, 90]},
        "calibration": [{"kind": "spheres", "lights": "grid"}, {"kind": "passive", "when": "after"}]}


def test_held_out_lights_are_captured_at_every_pose_and_marked():
    steps = Plan.from_dict(BASE).steps()
    measure = [s for s in steps if s.kind == "measure"]
    held = [s for s in measure if s.held_out]
    # 2 turntable angles x 2 held-out lights x 2 analyser angles, after the 2 x 2 x 2 grid
    assert len(measure) == 16 and len(held) == 8
    assert all(not s.held_out for s in measure[:8]) and all(s.held_out for s in measure[8:])
    assert {(s.light.azimuth_deg, s.light.elevation_deg) for s in held} == {(20.0, 50.0), (-30.0, 60.0)}
    assert {(s.turntable_deg, s.polarizer_deg) for s in held} == {(a, p) for a in (0.0, 90.0) for p in (0.0, 90.0)}
    # the held_out flag survives the store's JSON round trip; a light dict stays a move target
    assert Step.from_dict(held[0].to_dict()) == held[0] and "held_out" not in held[0].to_dict()["light"]
    assert "held_out" not in measure[0].to_dict()


def test_grid_calibrations_cover_held_out_lights_and_passive_is_one_lamp_off_step():
    steps = Plan.from_dict(BASE).steps()
    spheres = [(s.light.azimuth_deg, s.light.elevation_deg) for s in steps if s.kind == "spheres"]
    assert set(spheres) == {(0.0, 30.0), (40.0, 30.0), (20.0, 50.0), (-30.0, 60.0)}
    passive = [s for s in steps if s.kind == "passive"]
    assert len(passive) == 1 and passive[0].target == "passive" and passive[0].light is None
    assert steps[-1].kind == "passive"


def test_held_out_round_trips_and_changes_the_hash():
    p = Plan.from_dict(BASE)
    assert Plan.from_dict(p.to_dict()) == p
    plain = {**BASE, "light": {k: v for k, v in BASE["light"].items() if k != "held_out_deg"}}
    assert Plan.from_dict(plain).hash != p.hash
    assert "held_out_deg" not in Plan.from_dict(plain).to_dict()["light"]


@pytest.mark.parametrize("held, message", [
    ("x", "light.held_out_deg must be a list"),
    ([[10]], r"light.held_out_deg\[0\] must be \[azimuth, elevation\]"),
    ([[10, 95]], r"light.held_out_deg\[0\] = \[10, 95\] is outside the valid range"),
    ([[40, 30]], r"light.held_out_deg\[0\] = \[40, 30\] is also on the light grid"),
])
def test_bad_held_out_lights_name_the_field(held, message):
    bad = {**BASE, "light": {**BASE["light"], "held_out_deg": held}}
    with pytest.raises(PlanError, match=message):
        Plan.from_dict(bad)


def test_held_out_with_explicit_points_is_refused():
    with pytest.raises(PlanError, match="either xyz_mm or azimuth_deg"):
        Plan.from_dict({"light": {"xyz_mm": [[300, 0, 300]], "held_out_deg": [[0, 30]]}})
