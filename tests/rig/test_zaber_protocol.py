"""Zaber ASCII codec and driver against scripted byte exchanges (no port).

Frames follow the Zaber ASCII protocol manual (firmware 7): ``/dev axis id command:CC\\n`` out,
``@dd a id OK|RJ IDLE|BUSY flag data:CC\\r\\n`` back. The checksum here is computed independently
of the code under test: the byte sum of the body plus the checksum must be 0 mod 256.
"""
from __future__ import annotations

import pytest

from rig import DeviceBusy, DeviceError, DeviceTimeout, NotHomed, ProtocolError
from rig.transport import ScriptedTransport
from rig.zaber import (REJECTION_REASONS, WARNING_FLAGS, ZaberRotaryStage, checksum, encode_command,
                       flag_error, move_time_s, parse_message, rejection_error)

CYCLE = 1_536_000  # microsteps per revolution of the scripted stage (0.000234375 deg each)


def ck(body: str) -> str:
    return f"{(256 - sum(body.encode()) % 256) % 256:02X}"


def req(mid: int, command: str, axis: int = 1) -> bytes:
    body = f"1 {axis} {mid:02d}" + (f" {command}" if command else "")
    return f"/{body}:{ck(body)}\n".encode()


def rep(mid: int, data: str = "0", *, axis: int = 1, flag: str = "OK", status: str = "IDLE",
        warn: str = "--") -> bytes:
    body = f"01 {axis} {mid:02d} {flag} {status} {warn} {data}"
    return f"@{body}:{ck(body)}\r\n".encode()


def connect_script(start: int = 0) -> list[tuple[bytes, bytes]]:
    answers = [("get deviceid", "50419", 0), ("get version", "7.38", 0), ("get system.serial", "4242", 0),
               ("get resolution", "64", 1), ("get limit.cycle.dist", str(CYCLE), 1),
               ("get limit.min", "0", 1), ("get limit.max", str(CYCLE - 1), 1),
               ("get maxspeed", "629146", 1), ("get accel", "1049", 1), ("get comm.checksum", "1", 0)]
    return [(req(start + i, c, axis), rep(start + i, d, axis=axis)) for i, (c, d, axis) in enumerate(answers)]


def stage(script, **kw) -> tuple[ZaberRotaryStage, ScriptedTransport]:
    t = ScriptedTransport(connect_script() + script, device="turntable")
    s = ZaberRotaryStage("turntable", transport=t, poll_interval_s=0.0, **kw)
    s.connect()
    return s, t


# -- codec ------------------------------------------------------------------------------------------
def test_checksum_is_twos_complement_of_byte_sum():
    for body in ["1 0 get pos", "01 1 OK IDLE -- 0", "1 1 07 move abs 1000", ""]:
        c = checksum(body)
        assert len(c) == 2 and c == c.upper()
        assert (sum(body.encode()) + int(c, 16)) % 256 == 0
    assert checksum("1 1 move abs 1000") == ck("1 1 move abs 1000")


def test_checksum_matches_published_worked_examples():
    # Worked examples from public Zaber ASCII implementations (not derived from our code):
    # zproto (Rust) pins "/01 tools echo:8F" and "/1 tools echo:BF" (command side);
    # Zaber's own Python library (zaber.serial) pins the replies "@01 0 OK IDLE -- 0:8D" and
    # "@01 0 OK IDLE -- 7z:0C" (a checksum below 0x10 keeps its leading zero).
    assert checksum("01 tools echo") == "8F"
    assert checksum(b"1 tools echo") == "BF"
    for line, data in ((b"@01 0 OK IDLE -- 0:8D\r\n", "0"), (b"@01 0 OK IDLE -- 7z:0C\r\n", "7z")):
        msg = parse_message(line)
        assert msg.checksum_ok is True and msg.data == data and not msg.busy
    with pytest.raises(ProtocolError, match="checksum"):
        parse_message(b"@01 0 OK IDLE -- 0:8E\r\n")


def test_encode_command_forms():
    assert encode_command("move abs 1000", device=1, axis=1, with_checksum=False) == b"/1 1 move abs 1000\n"
    assert encode_command("", device=2, axis=0, message_id=7, with_checksum=False) == b"/2 0 07\n"
    assert encode_command("get pos", device=1, axis=1, message_id=5) == req(5, "get pos")
    with pytest.raises(ValueError, match="device"):
        encode_command("get pos", device=100)
    with pytest.raises(ValueError, match="axis"):
        encode_command("get pos", axis=10)
    with pytest.raises(ValueError, match="message_id"):
        encode_command("get pos", message_id=100)
    with pytest.raises(ValueError, match="reserved"):
        encode_command("get pos:12")


def test_parse_reply_ok_busy_with_id_and_checksum():
    msg = parse_message(rep(12, "0", status="BUSY"))
    assert (msg.kind, msg.device, msg.axis, msg.message_id) == ("@", 1, 1, 12)
    assert (msg.reply_flag, msg.status, msg.warning, msg.data) == ("OK", "BUSY", "--", "0")
    assert msg.busy and not msg.rejected and msg.checksum_ok is True


def test_parse_reply_without_id_or_checksum():
    msg = parse_message(b"@01 0 OK IDLE WR 384000\r\n")
    assert msg.message_id is None and msg.checksum_ok is None
    assert msg.warning == "WR" and msg.value() == 384000


def test_parse_rejection_info_and_alert():
    rj = parse_message(b"@01 1 RJ IDLE -- BADDATA\r\n")
    assert rj.rejected and rj.data == "BADDATA"
    info = parse_message(b"#01 1 03 storage: key value\r\n")
    assert (info.kind, info.message_id, info.data) == ("#", 3, "storage: key value")
    alert = parse_message(b"!01 1 IDLE FS\r\n")
    assert (alert.kind, alert.status, alert.warning) == ("!", "IDLE", "FS")


def test_parse_bad_checksum_and_garbage_raise_protocol_error():
    good = rep(3, "100")
    bad = good.replace(b"100", b"101")  # data changed, checksum not
    with pytest.raises(ProtocolError, match="checksum"):
        parse_message(bad)
    with pytest.raises(ProtocolError, match="not a Zaber"):
        parse_message(b"@01 X OK\r\n")
    with pytest.raises(ProtocolError):
        parse_message(b"\xff\xfe\r\n")
    with pytest.raises(ProtocolError, match="number"):
        parse_message(b"@01 1 OK IDLE -- abc\r\n").value()


@pytest.mark.parametrize("reason,error", [("STATUSBUSY", DeviceBusy), ("AGAIN", DeviceBusy),
                                          ("FULL", DeviceBusy), ("BADDATA", DeviceError),
                                          ("BADCOMMAND", DeviceError), ("PARKED", DeviceError),
                                          ("DEVICEONLY", DeviceError), ("BADAXIS", DeviceError)])
def test_rejection_reasons_map_to_typed_errors(reason, error):
    exc = rejection_error(parse_message(f"@01 1 RJ IDLE -- {reason}".encode()), "move abs 1",
                          device="turntable")
    assert type(exc) is error
    assert reason in str(exc) and "turntable" in str(exc)
    if error is DeviceError:
        assert exc.code == reason and exc.meaning


def test_rejection_without_reference_is_not_homed():
    exc = rejection_error(parse_message(b"@01 1 RJ IDLE WR BADCOMMAND"), "move abs 5")
    assert isinstance(exc, NotHomed)


def test_warning_flag_table():
    assert isinstance(flag_error("FS"), DeviceError) and flag_error("FS").code == "FS"
    assert isinstance(flag_error("FQ"), DeviceError)
    assert isinstance(flag_error("FD"), DeviceError)
    assert isinstance(flag_error("WL"), DeviceError)
    assert isinstance(flag_error("WR"), NotHomed)
    assert flag_error("--") is None and flag_error("NI") is None and flag_error("WV") is None
    assert all(sev in ("fault", "warning", "notice") for sev, _ in WARNING_FLAGS.values())
    # the flag set of Zaber Motion Library's WarningFlags (firmware 6/7), names checked there
    assert set(WARNING_FLAGS) == {"FF", "FN", "FZ", "FH", "FV", "FO", "FC", "FM", "FD", "FQ", "FI", "FA",
                                  "FR", "FS", "FB", "FP", "FE", "FT", "WL", "WV", "WT", "WS", "WM", "WP",
                                  "WR", "WH", "NC", "NI", "ND", "NR", "NT", "NU", "NJ", "NB"}
    assert "motor temperature" in WARNING_FLAGS["FM"][1] and "overdrive" in WARNING_FLAGS["FR"][1]
    assert "displaced when stationary" in WARNING_FLAGS["WM"][1]
    assert isinstance(flag_error("FM"), DeviceError) and flag_error("WS") is None
    assert isinstance(flag_error("FX"), DeviceError)  # an unknown fault flag is still a fault
    assert {"STATUSBUSY", "BADDATA", "BADCOMMAND", "PARKED", "DEVICEONLY"} <= set(REJECTION_REASONS)


def test_move_time_trapezoid_and_triangle():
    # trapezoid: 1 s ramps at v=10, a=10 cover 10 units; 90 more at 10/s
    assert move_time_s(100, 10, 10) == pytest.approx(10.0 + 1.0)
    # triangle: d = a t^2 / 4 per half -> t = 2 sqrt(d / a)
    assert move_time_s(4, 10, 1) == pytest.approx(4.0)
    with pytest.raises(ValueError):
        move_time_s(1, 0, 1)


# -- driver over a scripted transport ---------------------------------------------------------------
def test_connect_reads_conversion_from_device():
    s, t = stage([])
    d = s.describe()
    assert d["firmware"] == "7.38" and d["serial"] == "4242" and "50419" in d["model"]
    assert s.cyclic and s.microstep_deg == pytest.approx(360 / CYCLE)
    assert s.speed_deg_s == pytest.approx(629146 / 1.6384 * 360 / CYCLE)
    assert s.accel_deg_s2 == pytest.approx(1049 / 1.6384 * 10000 * 360 / CYCLE)
    assert s.limits == (0.0, 360.0)
    t.assert_done()


def test_position_and_homed():
    s, t = stage([(req(10, "get pos"), rep(10, str(CYCLE // 4))),
                  (req(11, "warnings"), rep(11, "01 WR", warn="WR")),
                  (req(12, "warnings"), rep(12, "00"))])
    assert s.position == pytest.approx(90.0)
    assert s.homed is False
    assert s.homed is True
    t.assert_done()


def test_move_polls_until_idle_and_returns_angle():
    target = CYCLE // 4
    s, t = stage([(req(10, "get pos"), rep(10, "0")),
                  (req(11, f"move abs {target}"), rep(11, status="BUSY")),
                  (req(12, ""), rep(12, status="BUSY")),
                  (req(13, ""), rep(13, status="BUSY")),
                  (req(14, ""), rep(14)),
                  (req(15, "get pos"), rep(15, str(target)))])
    assert s.move_to(90.0).wait(2) == pytest.approx(90.0)
    t.assert_done()


def test_move_wraps_negative_angle_onto_the_circle():
    target = round(CYCLE * 350 / 360)
    s, t = stage([(req(10, "get pos"), rep(10, "0")),
                  (req(11, f"move abs {target}"), rep(11, status="BUSY")),
                  (req(12, ""), rep(12)),
                  (req(13, "get pos"), rep(13, str(target)))])
    assert s.move_to(-10.0).wait(2) == pytest.approx(350.0)
    t.assert_done()


def test_busy_rejection_is_retried_then_succeeds():
    s, t = stage([(req(10, "get pos"), rep(10, "0")),
                  (req(11, "move abs 0"), rep(11, "STATUSBUSY", flag="RJ", status="BUSY")),
                  (req(12, "move abs 0"), rep(12, "STATUSBUSY", flag="RJ", status="BUSY")),
                  (req(13, "move abs 0"), rep(13, status="BUSY")),
                  (req(14, ""), rep(14)),
                  (req(15, "get pos"), rep(15, "0"))], busy_backoff_s=0.001)
    assert s.move_to(0.0).wait(2) == pytest.approx(0.0)
    t.assert_done()


def test_busy_rejection_gives_device_busy_after_retries():
    script = [(req(10, "get pos"), rep(10, "0"))]
    script += [(req(11 + i, "move abs 0"), rep(11 + i, "STATUSBUSY", flag="RJ", status="BUSY")) for i in range(3)]
    s, t = stage(script, busy_retries=2, busy_backoff_s=0.001)
    with pytest.raises(DeviceBusy, match="STATUSBUSY"):
        s.move_to(0.0)
    t.assert_done()


def test_not_homed_rejection_raises_at_once():
    s, t = stage([(req(10, "get pos"), rep(10, "0")),
                  (req(11, f"move abs {CYCLE // 2}"), rep(11, "BADCOMMAND", flag="RJ", warn="WR"))])
    with pytest.raises(NotHomed):
        s.move_to(180.0)
    t.assert_done()


def test_stall_fault_at_end_of_move_is_raised_and_cleared():
    s, t = stage([(req(10, "get pos"), rep(10, "0")),
                  (req(11, f"move abs {CYCLE // 4}"), rep(11, status="BUSY")),
                  (req(12, ""), rep(12, warn="FS")),
                  (req(13, "warnings clear"), rep(13, "01 FS", warn="FS"))])
    status = s.move_to(90.0)
    with pytest.raises(DeviceError, match="stalled") as info:
        status.wait(2)
    assert info.value.code == "FS"
    t.assert_done()


def test_interrupted_move_fails_with_position():
    s, t = stage([(req(10, "get pos"), rep(10, "0")),
                  (req(11, f"move abs {CYCLE // 4}"), rep(11, status="BUSY")),
                  (req(12, ""), rep(12, warn="NI")),
                  (req(13, "get pos"), rep(13, str(CYCLE // 8)))])
    with pytest.raises(DeviceError, match="45.0000 deg, not at the target 90.0000") as info:
        s.move_to(90.0).wait(2)
    assert info.value.code == "NI"
    t.assert_done()


def test_alerts_info_and_stale_replies_are_skipped():
    stale = rep(3, "777")  # a late answer to an earlier, timed-out request
    s, t = stage([(req(10, "get pos"), b"!01 1 IDLE --\r\n" + stale + b"#01 1 10 note\r\n" + rep(10, "0"))])
    assert s.position == 0.0
    assert [a.kind for a in s.alerts] == ["!"]
    t.assert_done()


def test_garbled_reply_is_protocol_error():
    good = rep(10, "1000")
    s, t = stage([(req(10, "get pos"), good[:5] + b"\x7f" + good[6:])])
    with pytest.raises(ProtocolError, match="get pos"):
        _ = s.position
    t.assert_done()


def test_missing_reply_is_timeout_not_hang():
    s, t = stage([(req(10, "get pos"), None)])
    with pytest.raises(DeviceTimeout):
        _ = s.position
    t.assert_done()


def test_non_cyclic_stage_needs_microstep_size_and_checks_limits():
    answers = [("get deviceid", "1", 0), ("get version", "7.10", 0), ("get system.serial", "1", 0),
               ("get resolution", "64", 1), ("get limit.cycle.dist", "0", 1),
               ("get limit.min", "-1000", 1), ("get limit.max", "100000", 1),
               ("get maxspeed", "1000", 1), ("get accel", "100", 1), ("get comm.checksum", "1", 0)]
    script = [(req(i, c, a), rep(i, d, axis=a)) for i, (c, d, a) in enumerate(answers)]
    t = ScriptedTransport(list(script))
    with pytest.raises(DeviceError, match="microstep_deg"):
        ZaberRotaryStage("turntable", transport=t).connect()
    t = ScriptedTransport(list(script))
    s = ZaberRotaryStage("turntable", transport=t, microstep_deg=0.001)
    s.connect()
    assert s.limits == pytest.approx((-1.0, 100.0))
    from rig import LimitError
    with pytest.raises(LimitError, match="120 deg is outside the limits -1..100 deg"):
        s.move_to(120.0)


def test_firmware_without_cycle_setting_is_a_limited_travel_stage():
    answers = [("get deviceid", "1", 0), ("get version", "6.28", 0), ("get system.serial", "1", 0),
               ("get resolution", "64", 1)]
    script = [(req(i, c, a), rep(i, d, axis=a)) for i, (c, d, a) in enumerate(answers)]
    script.append((req(4, "get limit.cycle.dist"), rep(4, "BADCOMMAND", flag="RJ")))
    later = [("get limit.min", "0", 1), ("get limit.max", "360000", 1), ("get maxspeed", "1000", 1),
             ("get accel", "100", 1), ("get comm.checksum", "1", 0)]
    script += [(req(5 + i, c, a), rep(5 + i, d, axis=a)) for i, (c, d, a) in enumerate(later)]
    s = ZaberRotaryStage("turntable", transport=ScriptedTransport(script), microstep_deg=0.001)
    s.connect()
    assert not s.cyclic and s.limits == pytest.approx((0.0, 360.0))


def test_from_config_rejects_unknown_keys():
    from rig import ConfigError
    with pytest.raises(ConfigError, match="speed"):
        ZaberRotaryStage.from_config("turntable", {"driver": "zaber", "port": "/dev/null", "speed": 3})
    s = ZaberRotaryStage.from_config("turntable", {"driver": "zaber", "port": "/dev/x", "device": 2})
    assert s.address == 2


def _plain(mid: int, data: str = "0", axis: int = 0) -> bytes:
    """A reply as a device with comm.checksum = 0 (the factory default) sends it: no ':CC'."""
    return f"@01 {axis} {mid:02d} OK IDLE -- {data}\r\n".encode()


def test_connect_turns_on_reply_checksums_then_requires_them():
    script = connect_script()[:-1] + [(req(9, "get comm.checksum", 0), _plain(9, "0")),
                                      (req(10, "set comm.checksum 1", 0), rep(10, axis=0)),
                                      (req(11, "get pos"), rep(11, "0")),
                                      (req(12, "get pos"), _plain(12, "1000", axis=1))]
    t = ScriptedTransport(script, device="turntable")
    s = ZaberRotaryStage("turntable", transport=t)
    s.connect()
    assert s.describe()["reply_checksums"] is True
    assert s.position == 0.0
    with pytest.raises(ProtocolError, match="no checksum"):
        _ = s.position  # a reply that lost its ':CC' is not believed
    t.assert_done()


def test_reply_checksums_off_leaves_the_device_setting_alone():
    script = connect_script()[:-1] + [(req(9, "get pos"), _plain(9, str(CYCLE // 2), axis=1))]
    t = ScriptedTransport(script, device="turntable")
    s = ZaberRotaryStage("turntable", transport=t, reply_checksums=False)
    s.connect()
    assert s.position == pytest.approx(180.0) and s.describe()["reply_checksums"] is False
    t.assert_done()
