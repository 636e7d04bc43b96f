"""The report's plan table: a plan's steps grouped by kind, angles written as compact runs."""
from __future__ import annotations

import pytest

from capture.pipeline.plan_table import compact_angles, plan_rows
from capture.plan import Plan, Step
from capture.store import FrameRecord

SMALL_PLAN = {
    "name": "small", "object": "sphere",
    "turntable": {"angles_deg": [0, 45, 90, 135, 180, 225, 270, 315]},
    "light": {"azimuth_deg": [-30, 30], "elevation_deg": [20, 50], "held_out_deg": [[0, 35]]},
    "polarizer": {"angles_deg": [0, 90]},
    "exposure": {"base_s": 0.01, "stops": [-1, 0]},
    "calibration": [{"kind": "dark", "frames": 2},
                    {"kind": "checkerboard", "exposure_s": 0.02,
                     "turntable_angles_deg": [330, 340, 350, 0, 10, 20, 30]}],
}


@pytest.mark.parametrize("angles, period, text", [
    ([0, 90, 180, 270], 360.0, "0–270 by 90 (4)"),
    # a sweep through 0 deg is one run, started after the circle's widest gap
    ([300, 310, 320, 330, 340, 350, 0, 10, 20, 30, 40, 50, 60], 360.0, "300–60 by 10 (13)"),
    ([0, 30, 150, 180], 360.0, "0, 30, 150, 180"),           # no three evenly spaced
    ([350, 10], 360.0, "350, 10"),
    ([-60, -20, 20, 60, 20], None, "-60–60 by 40 (4)"),       # duplicates counted once
    ([0, 5, 10, 20, 30], None, "0–10 by 5 (3), 20, 30"),
    ([], None, "–"),
])
def test_compact_angles_writes_runs(angles, period, text):
    assert compact_angles(angles, period=period) == text


def _kind(step: Step) -> str:
    return step.kind + (" (held out)" if step.held_out else "")


def _frame(step: int, size: int) -> FrameRecord:
    return FrameRecord(id=0, session_id=1, step=step, bracket_index=0, repeat=0, sha256="", size=size,
                       filename="", format="dng", exposure_requested_s=None, exposure_s=None, iso=None,
                       fnumber=None, positions={}, captured_at=0.0, stored_at=0.0, metadata={})


def test_plan_rows_group_a_small_plan_by_kind_with_compact_angles_and_stored_bytes():
    steps = Plan.from_dict(SMALL_PLAN).steps()
    # every planned frame stored except the last step's, at 1000 + step bytes each
    stored = [_frame(s.index, 1000 + s.index) for s in steps[:-1] for _ in range(s.frames)]
    rows = {r.kind: r for r in plan_rows(steps, stored)}
    assert list(rows) == list(dict.fromkeys(map(_kind, steps)))
    m = rows["measure"]
    assert m.steps == 8 * 4 * 2                      # turntable x lights x polarizer
    assert m.turntable == "0–315 by 45 (8)"          # not 8 lines, one per angle
    assert m.lights == "az -30, 30 × el 20, 50"
    assert m.polarizer == "0, 90"
    assert m.exposures == "5, 10 ms"
    assert m.frames_planned == 2 * m.steps
    held = rows["measure (held out)"]
    assert (held.steps, held.lights, held.turntable) == (8 * 2, "az 0 × el 35", "0–315 by 45 (8)")
    assert rows["checkerboard"].turntable == "330–30 by 10 (7)"
    assert rows["dark"].turntable == rows["dark"].lights == "–"
    assert sum(r.frames_stored for r in rows.values()) == len(stored)
    assert sum(r.bytes_stored for r in rows.values()) == sum(f.size for f in stored)
    last = rows[_kind(steps[-1])]
    assert last.frames_stored == last.frames_planned - steps[-1].frames
