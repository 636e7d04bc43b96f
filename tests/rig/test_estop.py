"""The emergency stop of every serial driver reaches the wire at once, whatever else the driver is
doing: it never waits for the port lock that a request in flight holds. Each test puts a long
exchange in flight (a status poll the device leaves unanswered, a move waiting for its reply, a
GRBL homing cycle), calls stop() and measures when the stop bytes reached the simulated device.
The real GRBL firmware's version is in test_grbl_firmware.py."""
from __future__ import annotations

import time

import pytest

from rig import DeviceError
from rig.elliptec import ElliptecRotator
from rig.grbl import GrblAlarm, GrblPositioner
from rig.zaber import ZaberRotaryStage
from sims.elliptec_sim import ElliptecSim
from sims.grbl_sim import GrblSim
from sims.lab import KINEMATICS, MACHINE_MAPS
from sims.zaber_sim import ZaberSim

WIRE_S = 0.050  # the bound: an E-stop on the wire within 50 ms


def record_arrivals(sim, marker: bytes) -> list[float]:
    """Times (monotonic) at which requests containing ``marker`` reached ``sim``."""
    times: list[float] = []
    handle = sim.handle

    def recording(request: bytes):
        if marker in request:
            times.append(time.monotonic())
        return handle(request)

    sim.handle = recording
    return times


def delay(arrivals: list[float], t0: float) -> float:
    """Seconds from ``t0`` to the first arrival (waiting up to 2 s for it)."""
    deadline = time.monotonic() + 2.0
    while not arrivals and time.monotonic() < deadline:
        time.sleep(0.001)
    assert arrivals, "the stop never reached the device"
    return arrivals[0] - t0


def test_zaber_stop_does_not_wait_for_a_poll_in_flight():
    with ZaberSim(fast=False, homed=True, speed_deg_s=30, accel_deg_s2=300) as sim:
        st = ZaberRotaryStage("turntable", sim.port, timeout_s=0.5, poll_interval_s=0.005)
        st.connect()
        arrivals = record_arrivals(sim, b"stop")
        status = st.move_to(90.0)
        time.sleep(0.1)
        sim.inject("no_reply")  # the next status poll waits out its 0.5 s timeout, holding the port
        time.sleep(0.05)
        t0 = time.monotonic()
        st.stop()
        assert (d := delay(arrivals, t0)) < WIRE_S, f"stop reached the device after {d:.3f} s"
        assert sim.angle_deg < 90.0
        with pytest.raises(DeviceError, match="not at the target"):
            status.wait(3)  # the poll retried after its timeout, then found the axis stopped
        st.close()


def test_elliptec_stop_goes_past_the_move_waiting_for_its_reply():
    with ElliptecSim(name="polarizer", fast=False, speed_deg_s=100.0) as sim:
        r = ElliptecRotator("polarizer", sim.port, timeout_s=0.3, require_home=False)
        r.connect()
        arrivals = record_arrivals(sim, b"st")
        status = r.move_to(337.0)  # 3.4 s; the move thread holds the port until the PO reply
        time.sleep(0.2)
        t0 = time.monotonic()
        r.stop()
        assert (d := delay(arrivals, t0)) < WIRE_S, f"stop reached the device after {d:.3f} s"
        assert status.wait(1) == pytest.approx(sim.angle_deg, abs=0.01) and not sim.moving
        r.close()


def test_grbl_stop_during_homing_is_a_reset_on_the_wire_at_once():
    # the simulator's homing takes (185 + 90) deg / 60 deg/s: the driver waits for its 'ok'
    with GrblSim(fast=False, kinematics=KINEMATICS["arm"], machine_map=MACHINE_MAPS["arm"],
                 power_up_position=(-185.0, -90.0, -1.0)) as sim:
        p = GrblPositioner("positioner", sim.port, kinematics=sim.kinematics, timeout_s=0.5,
                           **sim.machine_map)
        p.connect()
        arrivals = record_arrivals(sim, b"\x18")
        status = p.home()
        time.sleep(0.2)
        t0 = time.monotonic()
        p.stop()
        assert (d := delay(arrivals, t0)) < WIRE_S, f"reset reached the device after {d:.3f} s"
        with pytest.raises(GrblAlarm) as info:
            status.wait(2)
        assert info.value.alarm == 6 and not p.homed  # "homing fail: the active homing cycle was reset"
        assert p.status().state == "Alarm"
        p.close()
