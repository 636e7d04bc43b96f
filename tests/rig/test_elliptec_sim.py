"""ElliptecRotator against the ELL14 firmware simulator over a real pty."""
from __future__ import annotations

import time

import pytest

from rig.elliptec import ElliptecRotator
from rig.errors import DeviceBusy, DeviceError, DeviceTimeout, Disconnected, LimitError, ProtocolError
from sims.elliptec_sim import ElliptecSim


@pytest.fixture
def sim():
    s = ElliptecSim(name="polarizer", fast=True)
    s.start()
    yield s
    s.stop()


@pytest.fixture
def rot(sim):
    r = ElliptecRotator("polarizer", sim.port, timeout_s=0.3, move_timeout_s=2.0, busy_retry_s=0.5)
    r.connect()
    yield r
    r.close()


def test_connect_home_move_position(sim, rot):
    assert rot.describe()["pulses_per_revolution"] == sim.pulses_per_rev
    assert rot.position == pytest.approx(37.0, abs=360 / sim.pulses_per_rev)
    rot.home().wait(2)
    assert rot.homed and sim.homed and sim.angle_deg == 0.0
    for target in (22.5, 90.0, 359.0, 0.0, 137.25):
        assert rot.move_to(target).wait(2) == pytest.approx(target, abs=0.003)
        assert sim.angle_deg == pytest.approx(target, abs=0.003)
    assert rot.read()["position"]["value"] == pytest.approx(137.25, abs=0.003)


def test_port_is_opened_9600_8n1_without_flow_control(rot):
    settings = rot.transport._serial.get_settings()  # what pyserial configured on the tty
    assert {k: settings[k] for k in ("baudrate", "bytesize", "parity", "stopbits", "xonxoff", "rtscts")} == \
        {"baudrate": 9600, "bytesize": 8, "parity": "N", "stopbits": 1, "xonxoff": False, "rtscts": False}


def test_requests_on_the_wire_are_byte_exact(sim, rot):
    rot.home().wait(2)
    rot.move_to(90).wait(2)
    assert sim.requests == [b"0in", b"0gs", b"0ho0", b"0ma00008C00"]


def test_relative_move_wraps_past_full_turn(sim, rot):
    rot.home().wait(2)
    rot.move_to(350).wait(2)
    assert rot.move_by(20).wait(2) == pytest.approx(10.0, abs=0.003)
    assert sim.angle_deg == pytest.approx(10.0, abs=0.003)
    sent = len(sim.requests)
    with pytest.raises(ValueError, match="delta must be a finite number"):
        rot.move_by(float("nan"))
    with pytest.raises(LimitError, match="relative move"):
        rot.move_by(1e12)  # more turns than a signed 32-bit pulse count holds
    assert len(sim.requests) == sent  # neither reached the wire


def test_timed_motion_and_stop():
    with ElliptecSim(name="polarizer", fast=False, speed_deg_s=100.0) as sim:
        r = ElliptecRotator("polarizer", sim.port, timeout_s=0.3, require_home=False)
        r.connect()
        t0 = time.monotonic()
        st = r.move_to(37.0 + 30.0)  # 0.3 s at 100 deg/s
        assert not st.done
        assert st.wait(2) == pytest.approx(67.0, abs=0.003)
        assert time.monotonic() - t0 == pytest.approx(0.3, abs=0.15)
        st = r.move_to(337.0)  # 2.7 s: stop it half way
        time.sleep(0.3)
        assert 40 < sim.angle_deg < 120
        r.stop()
        stopped = st.wait(1)
        assert stopped == pytest.approx(sim.angle_deg, abs=0.01) and not sim.moving
        assert r.position == pytest.approx(stopped, abs=0.01)  # the port is clean after the stop
        r.close()


def test_busy_fault_retried(sim, rot):
    rot.home().wait(2)
    sim.inject("busy", 3)
    assert rot.move_to(45).wait(2) == pytest.approx(45.0, abs=0.003)
    assert sim.requests.count(b"0ma00004600") == 4


def test_busy_forever_raises_device_busy(sim, rot):
    sim.inject("busy", 1000)
    t0 = time.monotonic()
    with pytest.raises(DeviceBusy):
        rot.home().wait(2)
    assert time.monotonic() - t0 < 1.0
    sim.clear_faults()
    rot.home().wait(2)  # recovers


def test_mechanical_timeout(sim, rot):
    rot.home().wait(2)
    sim.inject("mechanical_timeout")
    with pytest.raises(DeviceError, match="mechanical time out") as info:
        rot.move_to(90).wait(2)
    assert info.value.code == 2
    assert 0 < sim.angle_deg < 90
    assert rot.move_to(90).wait(2) == pytest.approx(90.0, abs=0.003)


def test_out_of_range(sim, rot):
    rot.home().wait(2)
    sim.inject("out_of_range")
    with pytest.raises(DeviceError, match="out of range") as info:
        rot.move_to(90).wait(2)
    assert info.value.code == 12


def test_no_reply_times_out_then_recovers(sim, rot):
    sim.inject("no_reply")
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        rot.position
    assert time.monotonic() - t0 < 0.6
    assert rot.position == pytest.approx(37.0, abs=0.003)


def test_garbled_reply_is_protocol_error_then_recovers(sim, rot):
    sim.inject("garble")
    with pytest.raises(ProtocolError):
        rot.position
    assert rot.position == pytest.approx(37.0, abs=0.003)


def test_disconnect_then_reconnect(sim, rot):
    rot.home().wait(2)
    sim.inject("disconnect")
    with pytest.raises(Disconnected):
        rot.position
    sim.reconnect()
    rot.close()
    rot.connect()
    assert not rot.homed  # power-cycled: reference lost
    rot.home().wait(2)
    assert rot.move_to(10).wait(2) == pytest.approx(10.0, abs=0.003)


def test_incomplete_request_answered_with_communication_timeout(sim, rot):
    rot.transport.write(b"0ma0000")
    with pytest.raises(DeviceTimeout, match="communication time out"):
        rot._check_ok(rot._read_reply(timeout_s=1.5), "partial request")


def test_other_address_gets_no_reply(sim):
    r = ElliptecRotator("polarizer", sim.port, address="3", timeout_s=0.2)
    with pytest.raises(DeviceTimeout):
        r.connect()
    r.close()


def test_built_from_rig_config(sim):
    from rig import Rig
    rig = Rig.from_config({"polarizer": {"driver": "elliptec", "port": sim.port, "timeout_s": 0.3}},
                          usb_backend=None)
    with rig:
        rig.polarizer.home().wait(2)
        assert rig.polarizer.move_to(45).wait(2) == pytest.approx(45.0, abs=0.003)
        assert rig.describe()["polarizer"]["model"] == "ELL14"


def test_firmware_framing_by_command_length(sim):
    """Raw bytes on the pty: back-to-back requests in one write, an unknown command, a bad home
    direction."""
    import serial
    with serial.Serial(sim.port, 9600, timeout=0.5) as port:
        port.write(b"0gs0gp0in")
        assert port.readline() == b"0GS00\r\n"
        assert port.readline() == b"0PO0000398E\r\n"  # 37 deg = 14734 pulses at power-up
        assert port.readline() == b"0IN0E1140012320231701016800023000\r\n"
        port.write(b"0xx")
        assert port.readline() == b"0GS03\r\n"
        port.write(b"0ho7")
        assert port.readline() == b"0GS04\r\n"
        sim.comm_timeout_s = 1.0
        port.write(b"0ma0000")  # three data characters short: dropped with a communication time out
        t0 = time.monotonic()
        port.timeout = 0.3
        assert port.readline() == b""
        port.timeout = 2.0
        assert port.readline() == b"0GS01\r\n"
        assert time.monotonic() - t0 >= 1.0


def test_cable_pulled_mid_move_fails_fast():
    with ElliptecSim(name="polarizer", fast=False, speed_deg_s=50.0) as sim:
        r = ElliptecRotator("polarizer", sim.port, timeout_s=0.3, move_timeout_s=5.0,
                            require_home=False)
        r.connect()
        st = r.move_to(300)  # ~5 s of motion
        time.sleep(0.2)
        t0 = time.monotonic()
        sim.disconnect()
        with pytest.raises(Disconnected):
            st.wait(2)
        assert time.monotonic() - t0 < 1.0
        stopped_at = sim.angle_deg
        assert 37 < stopped_at < 60  # power lost: the mount stopped where it was
        sim.reconnect()
        r.close()
        r.connect()
        assert r.position == pytest.approx(stopped_at, abs=0.01)


def test_cr_lf_ignored_and_unknown_data_command_does_not_swallow_the_next(sim):
    """What vendor clients send: ``thorlabs-elliptec`` ends every request with CR LF; a command
    the firmware does not know may carry data. Neither may shift the framing of what follows."""
    import serial
    with serial.Serial(sim.port, 9600, timeout=0.5) as port:
        port.write(b"0gs\r\n0gp\r\n")
        assert port.readline() == b"0GS00\r\n"
        assert port.readline() == b"0PO0000398E\r\n"
        port.write(b"0zz000020000gs\r\n0gj")  # unknown + 8 data characters, then two requests
        assert [port.readline() for _ in range(3)] == [b"0GS03\r\n", b"0GS00\r\n",
                                                        b"0GJ00002000\r\n"]
        port.write(b"0zz00002000")  # unknown with data at the end of the input: framed on silence
        assert port.readline() == b"0GS03\r\n"
        port.write(b"0gs")
        assert port.readline() == b"0GS00\r\n"
    assert sim.requests[-6:] == [b"0gp", b"0zz00002000", b"0gs", b"0gj", b"0zz00002000", b"0gs"]


def test_jog_home_offset_and_motor_info_as_an_ell14_answers(sim):
    import serial
    with serial.Serial(sim.port, 9600, timeout=0.5) as port:
        port.write(b"0sj00001C00")  # jog step 7168 pulses = 18 deg
        assert port.readline() == b"0GS00\r\n"
        port.write(b"0gj")
        assert port.readline() == b"0GJ00001C00\r\n"
        port.write(b"0fw")  # one jog step forward from 37 deg: 14734 + 7168 = 21902 pulses
        assert port.readline() == b"0PO0000558E\r\n"
        port.write(b"0bw")
        assert port.readline() == b"0PO0000398E\r\n"
        port.write(b"0so00000E00")  # home offset 3584 pulses = 9 deg
        assert port.readline() == b"0GS00\r\n"
        port.write(b"0go")
        assert port.readline() == b"0HO00000E00\r\n"
        port.write(b"0ho0")  # homing ends at the offset
        assert port.readline() == b"0PO00000E00\r\n"
        assert sim.angle_deg == pytest.approx(9.0)
        port.write(b"0i1")
        reply = port.readline()
        # I1 + loop, motor, current, ramp up, ramp down, forward and backward period (4 hex each)
        assert reply[:3] == b"0I1" and len(reply) == 3 + 22 + 2
        assert 60_000 < 14_740_000 / int(reply[17:21], 16) < 150_000  # a resonance in kHz range
