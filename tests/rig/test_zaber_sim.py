"""ZaberRotaryStage against ZaberSim over a real pseudo-terminal: state, motion, faults, recovery."""
from __future__ import annotations

import time

import pytest

from rig import DeviceBusy, DeviceError, DeviceTimeout, Disconnected, NotHomed, ProtocolError
from rig.zaber import ZaberRotaryStage, checksum, move_time_s, parse_message
from sims.zaber_sim import ZaberSim, trapezoid_distance, trapezoid_duration, trapezoid_speed

TIMEOUT = 0.5  # reply timeout used here, seconds: every fault must surface within it (+ margin)


@pytest.fixture
def sim():
    with ZaberSim(fast=True) as s:
        yield s


@pytest.fixture
def stage(sim):
    st = ZaberRotaryStage("turntable", sim.port, timeout_s=TIMEOUT, poll_interval_s=0.002,
                          busy_backoff_s=0.005)
    st.connect()
    yield st
    st.close()


def test_trapezoid_speed_is_the_derivative_of_distance():
    d, v, a = 100.0, 20.0, 50.0
    total = trapezoid_duration(d, v, a)
    for t in [0.1 * total, 0.3 * total, 0.5 * total, 0.95 * total]:
        h = 1e-6
        numeric = (trapezoid_distance(d, v, a, t + h) - trapezoid_distance(d, v, a, t - h)) / (2 * h)
        assert trapezoid_speed(d, v, a, t) == pytest.approx(numeric, rel=1e-5)
    assert trapezoid_speed(d, v, a, total + 1) == 0.0


def test_trapezoid_profile_is_continuous_and_reaches_distance():
    d, v, a = 100.0, 20.0, 50.0
    total = trapezoid_duration(d, v, a)
    assert total == pytest.approx(move_time_s(d, v, a))
    ts = [total * k / 200 for k in range(201)]
    s = [trapezoid_distance(d, v, a, t) for t in ts]
    assert s[0] == 0 and s[-1] == pytest.approx(d)
    assert all(b >= a_ - 1e-12 for a_, b in zip(s, s[1:]))  # monotone
    steps = [b - a_ for a_, b in zip(s, s[1:])]
    assert max(steps) <= v * total / 200 + 1e-9  # never faster than v


def test_power_up_state_needs_homing(stage, sim):
    assert stage.connected and not stage.homed
    assert stage.warnings() == ["WR"]
    with pytest.raises(NotHomed):
        stage.move_to(10)
    assert stage.home().wait(2) == pytest.approx(0.0)
    assert stage.homed and stage.warnings() == []


def test_moves_track_simulator_angle(stage, sim):
    stage.home().wait(2)
    for target in (30.0, 359.5, -45.0, 720.25):
        final = stage.move_to(target).wait(2)
        assert final == pytest.approx(target % 360, abs=stage.microstep_deg)
        assert sim.angle_deg == pytest.approx(target % 360, abs=stage.microstep_deg)
    assert stage.read()["angle"]["units"] == "deg"


def test_homing_corrects_power_up_offset():
    with ZaberSim(fast=True, power_up_angle_deg=123.0) as sim:
        st = ZaberRotaryStage("turntable", sim.port, timeout_s=TIMEOUT)
        st.connect()
        assert st.position == 0.0 and sim.angle_deg == pytest.approx(123.0)  # counter is wrong
        st.home().wait(2)
        st.move_to(10).wait(2)
        assert sim.angle_deg == pytest.approx(10.0, abs=1e-3)
        st.close()


def test_shortest_path_in_real_time():
    with ZaberSim(fast=False, homed=True, speed_deg_s=90, accel_deg_s2=900) as sim:
        st = ZaberRotaryStage("turntable", sim.port, timeout_s=TIMEOUT, poll_interval_s=0.005)
        st.connect()
        st.move_to(350.0).wait(3)  # 10 deg the short way round
        t0 = time.monotonic()
        st.move_to(10.0).wait(3)  # 20 deg across zero, not 340 deg
        elapsed = time.monotonic() - t0
        expected = move_time_s(20, 90, 900)
        assert expected * 0.9 < elapsed < expected + 0.3  # + polling and scheduling slack
        assert sim.angle_deg == pytest.approx(10.0, abs=1e-3)
        st.close()


def test_stop_interrupts_move():
    with ZaberSim(fast=False, homed=True, speed_deg_s=30, accel_deg_s2=300) as sim:
        st = ZaberRotaryStage("turntable", sim.port, timeout_s=TIMEOUT, poll_interval_s=0.005)
        st.connect()
        status = st.move_to(90.0)
        time.sleep(0.25)  # cruising at 30 deg/s
        st.stop()
        at_stop = sim.angle_deg
        with pytest.raises(DeviceError, match="not at the target"):
            status.wait(2)
        # it brakes at 300 deg/s^2: v^2 / 2a = 1.5 deg further (less what passed since the stop)
        assert 1.0 < sim.angle_deg - at_stop <= 1.5 + 1e-6
        assert 0.0 < sim.angle_deg < 90.0
        assert "NI" in st.warnings()
        st.close()


def test_checksum_mismatch_on_the_wire_is_detected(stage, sim):
    sim.inject("garble")
    t0 = time.monotonic()
    with pytest.raises(ProtocolError):
        _ = stage.position
    assert time.monotonic() - t0 < TIMEOUT + 0.2
    assert stage.position == 0.0  # next request is fine


def test_driver_turns_on_reply_checksums_on_a_factory_default_device(stage, sim):
    assert sim.reply_checksums and stage.describe()["reply_checksums"]
    assert stage.request("").checksum_ok is True  # every reply now carries a valid ':CC'


def test_no_reply_times_out_then_recovers(stage, sim):
    sim.inject("no_reply")
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        _ = stage.position
    assert time.monotonic() - t0 < TIMEOUT + 0.2
    assert stage.position == 0.0


def test_busy_is_retried(stage, sim):
    stage.home().wait(2)
    sim.inject("busy", 2)
    assert stage.move_to(45).wait(2) == pytest.approx(45.0, abs=1e-3)
    sim.inject("busy", 10)
    with pytest.raises(DeviceBusy, match="STATUSBUSY"):
        stage.move_to(50)
    sim.clear_faults()


@pytest.mark.parametrize("fault,flag,match", [("stall", "FS", "stalled"), ("encoder", "FQ", "encoder")])
def test_stall_and_encoder_faults(stage, sim, fault, flag, match):
    stage.home().wait(2)
    sim.inject(fault)
    with pytest.raises(DeviceError, match=match) as info:
        stage.move_to(90).wait(2)
    assert info.value.code == flag
    assert sim.angle_deg == pytest.approx(45.0, abs=1e-3)  # stopped half way
    assert flag not in stage.warnings()  # cleared by the driver
    assert stage.move_to(90).wait(2) == pytest.approx(90.0, abs=1e-3)  # retry works


def test_limit_trip_loses_reference_and_rehome_recovers(stage, sim):
    stage.home().wait(2)
    sim.inject("limit")
    with pytest.raises(DeviceError, match="limit") as info:
        stage.move_to(120).wait(2)
    assert info.value.code == "WL"
    assert not stage.homed
    with pytest.raises(NotHomed):
        stage.move_to(10)
    stage.home().wait(2)
    assert stage.move_to(10).wait(2) == pytest.approx(10.0, abs=1e-3)


def test_disconnect_then_reconnect(stage, sim):
    stage.home().wait(2)
    sim.inject("disconnect")
    t0 = time.monotonic()
    with pytest.raises(Disconnected):
        _ = stage.position
    assert time.monotonic() - t0 < TIMEOUT + 0.2
    with pytest.raises(Disconnected):
        _ = stage.position
    sim.reconnect()
    stage.connect()
    assert stage.connected and not stage.homed  # power-cycled
    stage.home().wait(2)
    assert stage.move_to(20).wait(2) == pytest.approx(20.0, abs=1e-3)


def test_disconnect_mid_move_fails_the_status():
    with ZaberSim(fast=False, homed=True, speed_deg_s=30, accel_deg_s2=300) as sim:
        st = ZaberRotaryStage("turntable", sim.port, timeout_s=TIMEOUT, poll_interval_s=0.005)
        st.connect()
        status = st.move_to(90)
        time.sleep(0.1)
        sim.disconnect()
        with pytest.raises(Disconnected):
            status.wait(2)
        st.close()


def test_connect_to_missing_port_is_disconnected(tmp_path):
    st = ZaberRotaryStage("turntable", str(tmp_path / "nope"))
    with pytest.raises(Disconnected, match="cannot open"):
        st.connect()


def test_move_survives_one_garbled_or_lost_poll_but_not_many():
    with ZaberSim(fast=False, homed=True, speed_deg_s=90, accel_deg_s2=900) as sim:
        st = ZaberRotaryStage("turntable", sim.port, timeout_s=0.2, poll_interval_s=0.005)
        st.connect()
        status = st.move_to(30)
        sim.inject("garble")
        sim.inject("no_reply")
        assert status.wait(3) == pytest.approx(30.0, abs=1e-3)
        status = st.move_to(60)
        sim.inject("no_reply", 5)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout):
            status.wait(3)
        assert time.monotonic() - t0 < 3 * 0.2 + 0.4  # poll_retries=2: three lost polls, then fail
        sim.clear_faults()
        st.close()


def test_speed_and_acceleration_settings_change_move_time():
    with ZaberSim(fast=False, homed=True, speed_deg_s=90, accel_deg_s2=900) as sim:
        st = ZaberRotaryStage("turntable", sim.port, timeout_s=TIMEOUT, poll_interval_s=0.005,
                              speed_deg_s=180.0, accel_deg_s2=1800.0)
        st.connect()
        assert st.speed_deg_s == pytest.approx(180.0, rel=1e-4)
        assert st.accel_deg_s2 == pytest.approx(1800.0, rel=1e-3)
        t0 = time.monotonic()
        st.move_to(90).wait(3)
        elapsed = time.monotonic() - t0
        expected = move_time_s(90, 180, 1800)
        assert expected * 0.9 < elapsed < expected + 0.3  # + polling and scheduling slack
        with pytest.raises(ValueError, match="speed"):
            st.set_speed(0)
        st.close()


def _z(sim, text: str) -> bytes:
    """One command through the simulator's firmware, bytes in, bytes out (no checksum)."""
    return sim.handle(text.encode())


def test_simulator_bytes_for_each_reply_form():
    sim = ZaberSim(fast=True)  # not started: handle() is the firmware
    assert _z(sim, "/1 0 get deviceid") == b"@01 0 OK IDLE WR 50419\r\n"
    assert _z(sim, "/1 1 get deviceid") == b"@01 1 RJ IDLE WR DEVICEONLY\r\n"
    assert _z(sim, "/1 5 get pos") == b"@01 5 RJ IDLE WR BADAXIS\r\n"
    assert _z(sim, "/1 1 fly") == b"@01 1 RJ IDLE WR BADCOMMAND\r\n"
    assert _z(sim, "/1 1 move abs 10") == b"@01 1 RJ IDLE WR BADCOMMAND\r\n"  # no reference yet
    assert _z(sim, "/1 1 07 warnings") == b"@01 1 07 OK IDLE WR 01 WR\r\n"
    assert _z(sim, "/1 1 home") == b"@01 1 OK BUSY WR 0\r\n"
    assert _z(sim, "/1 1 ") == b"@01 1 OK IDLE -- 0\r\n"  # fast: homing done by the next request
    assert _z(sim, "/1 1 move abs -1") == b"@01 1 RJ IDLE -- BADDATA\r\n"
    assert _z(sim, "/2 1 get pos") is None  # another device's address
    body = "1 1 12 get pos"
    # comm.checksum = 0 (factory default): a checksummed command is verified, the reply has none
    assert sim.handle(f"/{body}:{checksum(body)}".encode()) == b"@01 1 12 OK IDLE -- 0\r\n"
    assert sim.handle(f"/{body}:00".encode()) is None  # bad checksum: dropped
    assert _z(sim, "/1 1 set comm.checksum 1") == b"@01 1 RJ IDLE -- DEVICEONLY\r\n"
    assert _z(sim, "/1 0 set comm.checksum 2") == b"@01 0 RJ IDLE -- BADDATA\r\n"
    reply = _z(sim, "/1 0 set comm.checksum 1")
    assert reply.startswith(b"@01 0 OK IDLE -- 0:") and parse_message(reply).checksum_ok
    reply = _z(sim, "/1 1 get pos")  # from now on every reply is checksummed, with or without one sent
    assert reply.startswith(b"@01 1 OK IDLE -- 0:") and parse_message(reply).checksum_ok
    sim.on_power_up()
    assert parse_message(_z(sim, "/1 0 get comm.checksum")).data == "1"  # non-volatile
    assert _z(sim, "/1 0 set comm.checksum 0") == b"@01 0 OK IDLE WR 0\r\n"
    sim.inject("busy")
    assert _z(sim, "/1 1 move abs 5") == b"@01 1 RJ IDLE WR STATUSBUSY\r\n"  # after the power cycle


def test_alerts_are_pushed_and_skipped_by_the_driver(stage, sim):
    stage.home().wait(2)
    stage.command("set comm.alert 1")
    assert stage.get("comm.alert") == 1
    stage.move_to(30).wait(2)
    time.sleep(0.05)
    assert stage.position == pytest.approx(30.0, abs=1e-3)
    assert any(a.kind == "!" and a.status == "IDLE" for a in stage.alerts)


def test_multi_setting_get_and_identification_answers():
    """Firmware 7.38's ``get`` of several settings (as zaber-motion sends it: axis number first,
    values back separated by ``;``) and the identification queries, straight on the simulator."""
    sim = ZaberSim(fast=True)
    ask = lambda line: sim.handle(line.encode()).decode().rstrip()  # noqa: E731
    assert ask("/1 0 get 1 maxspeed pos") == f"@01 0 OK IDLE WR {sim.settings['maxspeed']} ; 0"
    assert ask("/1 0 get version.build system.axiscount") == "@01 0 OK IDLE WR 15708 ; 1"
    assert ask("/1 0 get 1 pos nosuch") == "@01 0 RJ IDLE WR BADCOMMAND"
    assert ask("/1 1 get 1 pos accel") == "@01 1 RJ IDLE WR BADCOMMAND"  # axis token at axis scope
    assert ask("/1 0 get 2 pos accel") == "@01 0 RJ IDLE WR BADAXIS"
    assert ask("/1 0 get 1 " + " ".join(["pos"] * 13)) == "@01 0 RJ IDLE WR BADCOMMAND"  # > 12
    assert ask("/1 0 get comm.packet.size.max") == "@01 0 OK IDLE WR 80"
    assert ask("/1 0 tools echo") == "@01 0 OK IDLE WR 0"
    assert ask("/1 1 get peripheralid") == "@01 1 RJ IDLE WR BADCOMMAND"
