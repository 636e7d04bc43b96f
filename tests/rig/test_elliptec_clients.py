"""ElliptecSim against two Elliptec clients from PyPI written by others (``test`` extras):
``thorlabs-elliptec`` (the ``ELLx`` class) and ``elliptec`` (``Controller`` + ``Rotator``).

Evidence recorded here, since where a client and the simulator disagree the client (written
against real mounts) is right:

- ``thorlabs-elliptec`` 1.3 writes every request followed by ``\\r\\n`` (``b"0in\\r\\n"``) and
  polls ``gs`` and ``gp`` every 0.1 s; the simulator used to frame the CR LF as the start of the
  next request and answered late or not at all;
- ``elliptec`` 0.1 writes requests bare (``b"0gj"``) and uses ``gj``/``sj`` (jog step, reply
  ``GJ``), ``fw`` (one jog step, reply ``PO``), ``go``/``so`` (home offset, reply ``HO``), ``i1``
  (motor info, reply ``I1`` + 22 characters), which the simulator answered ``GS03`` before.
"""
from __future__ import annotations

import time

import pytest

from sims.elliptec_sim import ElliptecSim

thorlabs_elliptec = pytest.importorskip("thorlabs_elliptec",
                                        reason="thorlabs-elliptec (test extra) not installed")
elliptec = pytest.importorskip("elliptec", reason="elliptec (test extra) not installed")

PULSES = 143360  # ELL14 pulses per revolution, as the simulator reports in IN


@pytest.fixture
def sim():
    with ElliptecSim(name="polarizer", fast=True) as s:
        yield s


def test_thorlabs_elliptec_identifies_homes_and_moves_the_mount(sim):
    ell = thorlabs_elliptec.ELLx(serial_port=sim.port)
    written: list[bytes] = []
    write = ell._port.write
    ell._port.write = lambda data: (written.append(bytes(data)), write(data))[1]
    try:
        assert (ell.model_number, ell.serial_number, ell.firmware_version) == ("ELL14/M", "11400123", "17")
        assert (ell.travel, ell.units) == (360, "°")
        ell.home(blocking=True)
        assert ell.get_position() == 0.0 and sim.homed
        ell.move_absolute(90.0, blocking=True)
        assert ell.get_position() == pytest.approx(90.0, abs=1e-3)
        assert sim.angle_deg == pytest.approx(90.0, abs=360 / PULSES)
        ell.move_relative(-30.0, blocking=True)  # the client truncates -11946.7 to -11946 pulses
        assert sim.angle_deg == pytest.approx(60.0 + 0.67 * 360 / PULSES, abs=360 / PULSES)
        time.sleep(0.25)  # two status polls (gs + gp) run meanwhile
        assert ell.status == thorlabs_elliptec.ELLStatus.OK
        assert ell.get_position() == pytest.approx(sim.angle_deg, abs=1e-3)
    finally:
        ell.close()
    # the client's own bytes end in CR LF; the firmware took each request whole, nothing stray
    assert b"0ho0\r\n" in written and all(w.endswith(b"\r\n") for w in written)
    assert set(sim.requests) <= {b"0in", b"0gs", b"0gp", b"0ho0", b"0ma00008C00", b"0mrFFFFD156"}
    assert b"0mrFFFFD156" in sim.requests  # -11946 pulses, two's complement


def test_elliptec_package_jog_home_offset_and_motor_info(sim):
    controller = elliptec.Controller(sim.port, debug=False)
    try:
        rotator = elliptec.Rotator(controller)
        assert (rotator.motor_type, rotator.pulse_per_rev, rotator.range) == (14, PULSES, 360)
        assert rotator.get_angle() == pytest.approx(37.0, abs=1e-3)  # power-up angle of the sim
        assert rotator.get_jog_step() == pytest.approx(0x2000 * 360 / PULSES, abs=1e-3)
        rotator.set_jog_step(10.0)
        assert sim.jog_pulses == int(10.0 / 360 * PULSES)
        assert rotator.jog("forward") == pytest.approx(47.0, abs=2e-3)
        assert sim.angle_deg == pytest.approx(47.0, abs=2e-3)
        rotator.set_home_offset(5.0)
        assert rotator.get_home_offset() == pytest.approx(5.0, abs=1e-3)
        rotator.home()
        assert sim.angle_deg == pytest.approx(5.0, abs=1e-3) and sim.homed
        info = rotator.get("motor_1_info")
        assert (info["Loop"], info["Motor"]) == ("1", "0")
        assert 60e3 < info["Forward frequency"] < 150e3  # the client's own period -> Hz conversion
        assert rotator.set_angle(45.0) == pytest.approx(45.0, abs=1e-3)
    finally:
        controller.close_connection()
    assert sim.requests[:3] == [b"0in", b"0gp", b"0gj"]
    assert b"0sj00000F8E" in sim.requests  # 10 deg = 3982 pulses, as the client encodes it
