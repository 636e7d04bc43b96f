"""Plans: parsing, canonical form and hash, validation messages, motion-minimising expansion."""
from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from capture.plan import (DEFAULT_FRAME_BYTES, MotionModel, Plan, PlanError, Step, _serpentine,
                          frame_bytes_from_describe, plan_diff)
from capture_fakes import SMALL_PLAN, make_rig
from rig import LightTarget
from sims.dng import write_dng

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "plan.toml"

FULL = """
name = "teapot"
object = "glazed teapot"
repeats = 2

[turntable]
angles_deg = { start = 0, stop = 330, step = 30 }

[light]
azimuth_deg = [0, 60, 120]
elevation_deg = { start = 15, stop = 75, step = 30 }

[polarizer]
count = 2

[exposure]
base_s = 0.02
stops = [-2, 0, 2]
iso = 100

[[calibration]]
kind = "dark"
frames = 3

[[calibration]]
kind = "checkerboard"
turntable_angles_deg = [0, 45, 90]
"""


def test_full_plan_parses_with_ranges_and_defaults(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text(FULL)
    plan = Plan.from_toml(p)
    assert plan.turntable_deg == tuple(float(a) for a in range(0, 331, 30))
    assert plan.light.elevation_deg == (15.0, 45.0, 75.0)
    assert plan.polarizer_deg == (0.0, 90.0)
    assert plan.exposure.exposures_s == pytest.approx((0.005, 0.02, 0.08))
    steps = plan.steps()
    measure = [s for s in steps if s.kind == "measure"]
    assert len(measure) == 12 * 3 * 3 * 2
    assert all(s.frames == 3 * 2 for s in measure)
    dark = [s for s in steps if s.kind == "dark"]
    assert len(dark) == 1 and dark[0].exposures_s == pytest.approx((0.005, 0.02, 0.08))
    assert dark[0].repeats == 3 and dark[0].turntable_deg is None and dark[0].light is None
    cb = [s.turntable_deg for s in steps if s.kind == "checkerboard"]
    assert cb == [0.0, 45.0, 90.0]
    assert [s.index for s in steps] == list(range(len(steps)))
    # every (turntable, light, polarizer) pose exactly once
    poses = {(s.turntable_deg, s.light.azimuth_deg, s.light.elevation_deg, s.polarizer_deg)
             for s in measure}
    assert len(poses) == len(measure)


def test_canonical_dict_roundtrips_and_hash_is_form_independent():
    a = Plan.from_dict({"turntable": {"angles_deg": {"start": 0, "stop": 90, "step": 45}}})
    b = Plan.from_dict({"turntable": {"angles_deg": [0, 45.0, 90]}})
    assert a == b and a.hash == b.hash
    assert Plan.from_dict(a.to_dict()) == a
    c = Plan.from_dict({"turntable": {"angles_deg": [0, 45, 91]}})
    assert c.hash != a.hash
    assert plan_diff(a.to_dict(), c.to_dict()) == ["turntable.angles_deg: [0.0, 45.0, 90.0] -> [0.0, 45.0, 91.0]"]


def test_python_built_plan_equals_toml_plan():
    from capture.plan import Exposure, LightGrid
    p = Plan(turntable_deg=[0, 90, 180], light=LightGrid(azimuth_deg=(0.0, 90.0), elevation_deg=(30.0,)),
             polarizer_deg=[0, 90], exposure=Exposure(base_s=0.01, stops=(-1.0, 1.0)), name="small")
    assert p == Plan.from_dict(SMALL_PLAN)
    assert p.hash == Plan.from_dict(SMALL_PLAN).hash


@pytest.mark.parametrize("data, message", [
    ({"turntable": {"angles_deg": [0]}, "lights": {}}, "plan: unknown key 'lights'"),
    ({"turntable": {"angle_deg": [0]}}, "turntable: unknown key 'angle_deg'; allowed: angles_deg"),
    ({"turntable": {"angles_deg": [0, "ten"]}}, r"turntable.angles_deg\[1\] must be a number, got a string \('ten'\)"),
    ({"turntable": {"angles_deg": "0..90"}}, "turntable.angles_deg must be a list of numbers"),
    ({"turntable": [0, 90]}, r"turntable must be a table \(\[turntable\]\)"),
    ({"turntable": {"angles_deg": []}}, "turntable.angles_deg is empty"),
    ({"light": {"azimuth_deg": [], "elevation_deg": [10]}}, "light.azimuth_deg is empty"),
    ({"light": {"azimuth_deg": [0]}}, "light.elevation_deg is missing"),
    ({"light": {"azimuth_deg": [0], "elevation_deg": [10, 20, 30, 95]}},
     r"light.elevation_deg\[3\] = 95 is outside the valid range -90..90"),
    ({"light": {"xyz_mm": [[1, 2]]}}, r"light.xyz_mm\[0\] must be \[x, y, z\]"),
    ({"light": {"xyz_mm": [[1, 2, 3]], "azimuth_deg": [0]}}, "either xyz_mm or azimuth_deg"),
    ({"turntable": {"angles_deg": {"start": 0, "stop": 90}}}, "turntable.angles_deg.step is missing"),
    ({"turntable": {"angles_deg": {"start": 0, "stop": 90, "step": -5}}}, "step -5 never goes from 0 to 90"),
    ({"polarizer": {"angles_deg": [0], "count": 2}}, "exactly one of angles_deg or count"),
    ({"polarizer": {"count": 0}}, "polarizer.count must be a whole number >= 1"),
    ({"turntable": {"angles_deg": [0]}, "exposure": {"base_s": "fast"}}, "exposure.base_s must be a number"),
    ({"turntable": {"angles_deg": [0]}, "exposure": {"base_s": -1}}, "exposure.base_s = -1 must be a positive"),
    ({"turntable": {"angles_deg": [0]}, "exposure": {"stops": []}}, "exposure.stops is empty"),
    ({"turntable": {"angles_deg": [0]}, "exposure": {"stops": [0, 0]}}, "has duplicates"),
    ({"turntable": {"angles_deg": [0]}, "exposure": {"highlight": 0.5}}, "only used with exposure.auto"),
    ({"turntable": {"angles_deg": [0]}, "exposure": {"auto": True, "highlight": 0.99}},
     "exposure.highlight = 0.99 must lie in 0.05..0.9"),
    ({"turntable": {"angles_deg": [0]}, "exposure": {"auto": "yes"}}, "exposure.auto must be true or false"),
    ({"turntable": {"angles_deg": [0]}, "repeats": 1.5}, "repeats must be a whole number"),
    ({"turntable": {"angles_deg": [0]}, "repeats": True}, "repeats must be a whole number"),
    ({"calibration": [{"kind": "flatfield"}]}, r"calibration\[0\].kind = 'flatfield' is unknown"),
    ({"calibration": [{"kind": "dark", "frame": 3}]}, r"calibration\[0\]: unknown key 'frame'"),
    ({"calibration": [{"kind": "dark", "when": "during"}]}, r"calibration\[0\].when = 'during'"),
    ({"name": 5, "turntable": {"angles_deg": [0]}}, "name must be a string"),
    ({}, "the plan captures nothing"),
    ({"turntable": {"angles_deg": [0, 90, 90]}},
     r"turntable.angles_deg\[2\] = 90 repeats turntable.angles_deg\[1\]; use repeats"),
    ({"light": {"azimuth_deg": [0], "elevation_deg": [30, 30]}}, r"light.elevation_deg\[1\] = 30 repeats"),
    ({"light": {"xyz_mm": [[1, 2, 3], [1, 2, 3]]}}, r"light.xyz_mm\[1\] = .* repeats light.xyz_mm\[0\]"),
    ({"polarizer": {"angles_deg": [0, 90, 0]}}, r"polarizer.angles_deg\[2\] = 0 repeats"),
])
def test_bad_plans_name_the_field(data, message):
    with pytest.raises(PlanError, match=message):
        Plan.from_dict(data)


def test_toml_errors_name_the_file(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[turntable\nangles_deg = [0]")
    with pytest.raises(PlanError, match="bad.toml: not valid TOML"):
        Plan.from_toml(p)
    p.write_text("[turntable]\nangles = [0]")
    with pytest.raises(PlanError, match="bad.toml: turntable: unknown key 'angles'"):
        Plan.from_toml(p)
    with pytest.raises(PlanError, match="does not exist"):
        Plan.from_toml(tmp_path / "missing.toml")


@pytest.mark.parametrize("data, message", [
    ({"light": {"azimuth_deg": [0], "elevation_deg": [10, 20, 30, 88]}},
     r"light.elevation_deg\[3\] = 88 is outside the positioner's limit 0..85"),
    ({"turntable": {"angles_deg": [0, 400]}}, r"turntable.angles_deg\[1\] = 400 is outside the turntable's limit -360..360"),
    ({"polarizer": {"angles_deg": [-10]}}, r"polarizer.angles_deg\[0\] = -10 is outside the polarizer's limit 0..360"),
    ({"turntable": {"angles_deg": [0]}, "exposure": {"base_s": 10, "stops": [0, 2]}},
     r"exposure.stops\[1\] = 2 gives 40 s, outside the camera's range 0.0001..30 s"),
    ({"light": {"xyz_mm": [[0, 0, 100]]}}, r"light.xyz_mm\[0\] = \[0, 0, 100\] is out of the positioner's reach"),
])
def test_rig_limits_from_describe(data, message):
    rig = make_rig()
    plan = Plan.from_dict(data)
    with pytest.raises(PlanError, match=message):
        plan.check_rig(rig)


def test_missing_device_is_named():
    rig = make_rig()
    rig.polarizer = None
    with pytest.raises(PlanError, match="polarizer.angles_deg is given but the rig has no polarizer"):
        Plan.from_dict(SMALL_PLAN).check_rig(rig)


def _moving_axes(a: Step, b: Step) -> int:
    return sum([a.turntable_deg != b.turntable_deg, a.light != b.light, a.polarizer_deg != b.polarizer_deg])


def test_serpentine_moves_one_axis_one_grid_step_at_a_time(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text(FULL)
    measure = [s for s in Plan.from_toml(p).steps() if s.kind == "measure"]
    for a, b in zip(measure, measure[1:]):
        assert _moving_axes(a, b) == 1
        if a.turntable_deg != b.turntable_deg:
            assert abs(a.turntable_deg - b.turntable_deg) == 30
        if a.light != b.light:
            assert (abs(a.light.azimuth_deg - b.light.azimuth_deg) == 60) != \
                   (abs(a.light.elevation_deg - b.light.elevation_deg) == 30)


def test_fastest_axis_is_innermost_and_nesting_is_optimal():
    plan = Plan.from_dict(SMALL_PLAN)
    steps = [s for s in plan.steps() if s.kind == "measure"]
    # polarizer (180 deg/s) changes every step, the slowest axis least often
    changes = {k: sum(getattr(a, k) != getattr(b, k) for a, b in zip(steps, steps[1:]))
               for k in ("turntable_deg", "light", "polarizer_deg")}
    assert changes["polarizer_deg"] == max(changes.values())
    # brute force: no nesting order of the same serpentine grid moves for less time
    model = MotionModel()
    axes = {"turntable": [0.0, 90.0, 180.0], "light_el": [30.0], "light_az": [0.0, 90.0],
            "polarizer": [0.0, 90.0]}
    chosen = model.estimate(steps).motion_s
    costs = []
    for names in itertools.permutations(axes):
        grid = [dict(zip(names, combo)) for combo in _serpentine([axes[n] for n in names])]
        other = [Step(0, "measure", "object", v["turntable"],
                      LightTarget(v["light_az"], v["light_el"]), v["polarizer"],
                      (0.01,)) for v in grid]
        costs.append(model.estimate(other).motion_s)
    assert chosen == pytest.approx(min(costs)) and max(costs) > 1.5 * chosen


def test_speeds_come_from_describe():
    rig = make_rig()
    model = MotionModel.from_rig(rig)
    assert model.speeds["turntable"] == (30.0, 60.0)  # fake axis describe()
    assert model.frame_bytes == 4096
    # trapezoid: 90 deg at 30 deg/s, 60 deg/s^2 -> 90/30 + 30/60 = 3.5 s
    assert model.move_s("turntable", 90) == pytest.approx(3.5)
    # triangle: 10 deg -> 2 * sqrt(10 / 60)
    assert model.move_s("turntable", 10) == pytest.approx(2 * math.sqrt(10 / 60))


def test_estimate_counts_frames_bytes_and_time():
    plan = Plan.from_dict({**SMALL_PLAN, "repeats": 2})
    est = plan.estimate(make_rig())
    assert est.steps == 12
    assert est.frames == 12 * 2 * 2
    assert est.bytes == est.frames * 4096
    assert est.exposure_s == pytest.approx(12 * 2 * (0.005 + 0.02))
    assert est.motion_s > 0 and est.seconds == pytest.approx(est.motion_s + est.exposure_s + est.overhead_s)


def test_example_plan_is_valid():
    plan = Plan.from_toml(EXAMPLE)
    assert plan.steps() and plan.estimate().frames > 0


@pytest.mark.parametrize("width, height", [(640, 480), (1200, 800), (3000, 2000)])
def test_frame_bytes_from_camera_describe_bounds_a_real_dng(width, height):
    """Every size form a camera reports gives the same estimate, and it bounds the file a
    16-bit raw of that size really is (an uncompressed DNG as sims.dng writes it, decoded by
    LibRaw elsewhere): no smaller than the file, at most the 64 kB header allowance above it."""
    actual = len(write_dng(np.zeros((height, width), np.uint16)))
    forms = [{"image_size": f"{width}x{height}"}, {"image_size": [width, height]},
             {"width": width, "height": height, "bit_depth": 14}]
    estimates = {frame_bytes_from_describe(d) for d in forms}
    assert len(estimates) == 1
    [estimate] = estimates
    assert actual <= estimate <= actual + 65536, (estimate, actual)


@pytest.mark.parametrize("describe, expected", [
    ({"frame_bytes": 1234}, 1234),                # the camera's own figure wins
    ({"driver": "ptp", "model": "no size"}, None),
    ({"image_size": "big"}, None),
])
def test_frame_bytes_from_describe_takes_a_stated_size_or_says_none(describe, expected):
    assert frame_bytes_from_describe(describe) == expected


def test_estimate_says_when_the_frame_size_is_assumed():
    plan = Plan.from_dict(SMALL_PLAN)
    rig = make_rig()
    assert plan.estimate(rig).frame_bytes_source == "camera"  # the fake reports frame_bytes
    rig.camera.describe = lambda: {"driver": "fake"}
    est = plan.estimate(rig)
    assert est.frame_bytes_assumed and est.bytes == est.frames * DEFAULT_FRAME_BYTES
    measured = MotionModel.from_rig(rig).with_frame_bytes(48e6).estimate(plan.steps(rig))
    assert measured.frame_bytes_source == "measured" and measured.bytes == measured.frames * 48_000_000
    assert measured.overhead_s > est.overhead_s  # a bigger transfer per frame


def test_a_calibration_capture_takes_its_own_bracket():
    # a mirror probe's room outruns one raw: its own exposures, not the measurement's bracket
    p = Plan.from_dict({"turntable": {"angles_deg": [0]}, "exposure": {"base_s": 0.01, "stops": [-2, 0]},
                        "calibration": [{"kind": "mirror_probe", "exposure_s": [0.0005, 0.004, 0.032]},
                                        {"kind": "gray_card", "exposure_s": 0.002}]})
    probe, card = (s for s in p.steps() if s.kind in ("mirror_probe", "gray_card"))
    assert probe.exposures_s == (0.0005, 0.004, 0.032) and card.exposures_s == (0.002,)
    assert Plan.from_dict(p.to_dict()) == p
    with pytest.raises(PlanError, match="exposure_s"):
        Plan.from_dict({"calibration": [{"kind": "mirror_probe", "exposure_s": [0.001, -1]}]})
