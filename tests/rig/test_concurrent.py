"""Turntable and light positioner moving together take about as long as the slower one alone.

Non-fast simulators with realistic ~0.7-0.9 s moves; each driver polls its own port on its own
thread, so the moves overlap instead of queueing.
"""
from __future__ import annotations

import threading
import time

import pytest

from rig import LightTarget, MoveStatus, wait_all
from rig.grbl import GrblPositioner
from rig.zaber import ZaberRotaryStage
from sims.grbl_sim import GrblSim
from sims.zaber_sim import ZaberSim


@pytest.fixture
def devices():
    with ZaberSim(fast=False, homed=True, speed_deg_s=90, accel_deg_s2=360) as zsim, \
            GrblSim(fast=False, settings={22: 0}) as gsim:
        table = ZaberRotaryStage("turntable", zsim.port, poll_interval_s=0.01)
        light = GrblPositioner("positioner", gsim.port, kinematics=gsim.kinematics, poll_interval_s=0.01)
        table.connect()
        light.connect()
        yield table, light, zsim, gsim
        table.close()
        light.close()


def _timed(fn) -> float:
    t0 = time.monotonic()
    fn()
    return time.monotonic() - t0


def test_concurrent_moves_take_max_not_sum(devices):
    table, light, zsim, gsim = devices
    t_table = _timed(lambda: table.move_to(60).wait(5))
    t_light = _timed(lambda: light.move_to(LightTarget(azimuth_deg=50, elevation_deg=20)).wait(5))
    assert 0.5 < t_table < 1.5 and 0.4 < t_light < 1.5  # realistic move times
    t_both = _timed(lambda: wait_all([table.move_to(0),
                                      light.move_to(LightTarget(azimuth_deg=0, elevation_deg=0))], timeout=5))
    ratio = t_both / max(t_table, t_light)
    assert ratio < 1.25, f"together {t_both:.3f} s vs alone {t_table:.3f} / {t_light:.3f} s"
    assert t_both < 0.8 * (t_table + t_light)
    assert zsim.angle_deg == pytest.approx(0.0, abs=1e-3)
    assert gsim.light_position_mm == pytest.approx((500.0, 0.0, 0.0), abs=0.01)


def test_one_failure_does_not_abandon_the_other_move(devices):
    table, light, zsim, gsim = devices
    zsim.inject("stall")
    statuses = [table.move_to(90), light.move_to(LightTarget(azimuth_deg=30, elevation_deg=10))]
    with pytest.raises(Exception, match="stalled"):
        wait_all(statuses, timeout=5)
    assert statuses[1].done and statuses[1].success  # the positioner still finished its move


def test_any_error_still_waits_for_the_other_moves():
    """A non-rig exception (a bug, a ValueError from a driver) must not make ``wait_all`` abandon
    the moves still running; the first error is raised after all have finished."""
    release = threading.Event()

    def fail():
        raise ValueError("bad reply parse")

    def slow_move():
        release.wait(5)
        return 42.0

    failing = MoveStatus.run(fail, device="a")
    running = MoveStatus.run(slow_move, device="b")
    threading.Timer(0.2, release.set).start()
    t0 = time.monotonic()
    with pytest.raises(ValueError, match="bad reply parse"):
        wait_all([failing, running], timeout=5)
    assert running.done and running.success  # waited for, not left running
    assert time.monotonic() - t0 >= 0.15
