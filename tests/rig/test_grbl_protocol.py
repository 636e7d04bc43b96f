"""GRBL 1.1 codec and GrblPositioner against scripted byte exchanges (gnea/grbl interface.md)."""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from rig import DeviceBusy, DeviceError, DeviceTimeout, LightTarget, LimitError, NotHomed, ProtocolError
from rig.grbl import (ALARM_CODES, ERROR_CODES, GrblAlarm, GrblPositioner, check_machine_space,
                      format_move, machine_space, parse_code, parse_settings, parse_status, path_time_s)
from rig.kinematics import MachineMap, kinematics_from_config
from rig.rig import ConfigError
from rig.transport import ScriptedTransport

BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"
SETTINGS = b"".join(f"${n}={v}\r\n".encode() for n, v in [
    (10, 1), (20, 0), (22, 1), (25, "3600.000"), (27, "1.000"), (110, "5400.000"), (111, "5400.000"),
    (112, "5400.000"), (120, "360.000"), (121, "360.000"), (122, "360.000"), (130, "370.000"),
    (131, "95.000"), (132, "1.000")]) + b"ok\r\n"


def connect_script(state: str = "Alarm") -> list:
    return [(b"\x18", BANNER + (b"[MSG:'$H'|'$X' to unlock]\r\n" if state == "Alarm" else b"")),
            (b"$I\n", b"[VER:1.1h.20190825:]\r\n[OPT:V,15,128]\r\nok\r\n"),
            (b"$$\n", SETTINGS),
            (b"?", f"<{state}|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n".encode())]


#: the arm's azimuth -180..180 and elevation 0..85 deg inside GRBL's machine space [-$13x, -$27]
MACHINE_OFFSET = {"X": -185.0, "Y": -90.0}


def positioner(script, state="Alarm") -> tuple[GrblPositioner, ScriptedTransport]:
    t = ScriptedTransport(connect_script(state) + script, device="positioner")
    p = GrblPositioner("positioner", transport=t, poll_interval_s=0.0, machine_offset=MACHINE_OFFSET)
    p.connect()
    return p, t


# -- codec ------------------------------------------------------------------------------------------
def test_parse_status_mpos_fs_and_fields():
    st = parse_status(b"<Run|MPos:12.500,-3.000,0.000|FS:5400,0|Pn:X|Ov:100,100,100>\r\n")
    assert st.state == "Run" and st.substate is None
    assert st.mpos == (12.5, -3.0, 0.0) and st.feed == 5400 and st.spindle == 0
    assert st.fields["Pn"] == "X"
    assert st.machine_position() == (12.5, -3.0, 0.0)


def test_parse_status_wpos_with_wco_and_hold_substate():
    st = parse_status("<Hold:0|WPos:1.000,2.000,3.000|F:500|WCO:10.000,20.000,30.000>")
    assert (st.state, st.substate, st.feed) == ("Hold", 0, 500)
    assert st.machine_position() == (11.0, 22.0, 33.0)
    later = parse_status("<Idle|WPos:1.000,2.000,3.000|FS:0,0>")  # WCO only now and then
    assert later.machine_position(wco=(10.0, 20.0, 30.0)) == (11.0, 22.0, 33.0)
    with pytest.raises(ProtocolError, match="WCO"):
        later.machine_position()


# the last three: one byte garbled on the wire, as the host-built firmware's harness did before
# sims/grbl_sim_interrupts.c ('.' for ',' and ',' for '.': a number list of another length)
@pytest.mark.parametrize("bad", ["Idle|MPos:0,0,0", "<Dancing|MPos:0,0,0>", "<Idle|MPos:a,b,c>",
                                 "<Idle|MPos>", "<Idle|MPos:-1.000,-1.000,-1.000|FS:0.0>",
                                 "<Idle|MPos:-1,000,-1.000,-1.000|FS:0,0>", "<Idle|MPos:0.000,0.000o0.000|FS:0,0>"])
def test_parse_status_rejects_malformed(bad):
    with pytest.raises(ProtocolError):
        parse_status(bad)


def test_codes_tables_and_parse_code():
    assert parse_code("error:9", "error") == 9 and parse_code("ok", "error") is None
    assert parse_code("ALARM:1", "ALARM") == 1
    with pytest.raises(ProtocolError):
        parse_code("error:x", "error")
    assert set(ERROR_CODES) == set(range(1, 18)) | set(range(20, 39))
    assert set(ALARM_CODES) == set(range(1, 10))
    assert "hard limit" in ALARM_CODES[1].lower() and "locked out" in ERROR_CODES[9]


def test_settings_and_move_formatting():
    assert parse_settings(["$110=5400.000", "$22=1", "junk", "[MSG:x]"]) == {110: 5400.0, 22: 1.0}
    assert format_move({"Y": 30, "X": 45.12345}) == b"G53 G0 X45.123 Y30.000\n"
    assert format_move({"Z": -1}, rapid=False, feed_mm_min=600) == b"G53 G1 Z-1.000 F600.0\n"
    with pytest.raises(ValueError):
        format_move({})
    with pytest.raises(ValueError, match="finite"):
        format_move({"X": float("nan")})
    with pytest.raises(ValueError, match="feed"):
        format_move({"X": 1}, rapid=False)


def test_path_time_limits_each_axis():
    # X alone at 60 units/s, accel 100: trapezoid
    t = path_time_s((0, 0), (120, 0), (3600, 3600), (100, 100))
    assert t == pytest.approx(60 / 100 + 120 / 60)
    # a diagonal: the path speed is limited so neither axis exceeds its max rate
    t_diag = path_time_s((0, 0), (120, 120), (3600, 3600), (1e9, 1e9))
    assert t_diag == pytest.approx(120 / 60, rel=1e-6)


# -- driver over a scripted transport ---------------------------------------------------------------
def test_connect_reads_banner_build_settings_and_state():
    p, t = positioner([])
    assert p.version == "1.1h" and p.build == "1.1h.20190825" and p.options == "V,15,128"
    assert p.homing_enabled and not p.homed
    assert p.settings[110] == 5400.0
    assert list(p.messages) == ["'$H'|'$X' to unlock"]
    d = p.describe()
    assert d["firmware"] == "Grbl 1.1h" and d["kinematics"]["type"] == "arm"
    t.assert_done()


def test_move_before_homing_is_refused_without_sending_gcode():
    p, t = positioner([(b"?", b"<Alarm|MPos:0.000,0.000,0.000|FS:0,0>\r\n")])
    with pytest.raises(NotHomed, match="alarm"):
        p.move_to(LightTarget(azimuth_deg=10, elevation_deg=20))
    t.assert_done()


def test_home_then_move_queues_gcode_and_polls_until_idle():
    # $H is accepted in the alarm state (no reset first); the real firmware leaves each homed
    # axis at minus the pull-off $27 (tests/rig/test_grbl_firmware.py): MPos -1 is azimuth 184,
    # elevation 89 deg through the machine offset
    script = [(b"?", b"<Alarm|MPos:0.000,0.000,0.000|FS:0,0>\r\n"),
              (b"$H\n", b"ok\r\n"),
              (b"?", b"<Idle|MPos:-1.000,-1.000,-1.000|FS:0,0>\r\n"),
              # move: state check, queue, poll
              (b"?", b"<Idle|MPos:-1.000,-1.000,-1.000|FS:0,0>\r\n"),
              (b"G53 G0 X-140.000 Y-60.000\n", b"ok\r\n"),
              (b"?", b"<Run|MPos:-160.000,-77.000,-1.000|FS:5400,0>\r\n"),
              (b"?", b"<Idle|MPos:-140.000,-60.000,-1.000|FS:0,0>\r\n")]
    p, t = positioner(script)
    az, el = np.radians(184.0), np.radians(89.0)
    assert p.home().wait(2) == pytest.approx(
        tuple(500 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])), abs=1e-6)
    assert p.homed
    x, y, z = p.move_to(LightTarget(azimuth_deg=45, elevation_deg=30)).wait(2)
    assert (x, y, z) == pytest.approx((306.186, 306.186, 250.0), abs=1e-3)
    t.assert_done()


def test_limit_error_raised_before_anything_is_sent():
    p, t = positioner([])
    with pytest.raises(LimitError, match="elevation .*90 deg is outside the limits 0..85 deg"):
        p.move_to(LightTarget(azimuth_deg=0, elevation_deg=90))
    t.assert_done()


def test_error_reply_maps_to_device_error_with_meaning():
    p, t = positioner([(b"G4 X1\n", b"error:20\r\n")], state="Idle")
    with pytest.raises(DeviceError, match="unsupported or invalid G-code") as info:
        p.send("G4 X1")
    assert info.value.code == "error:20"
    t.assert_done()


def test_alarm_during_move_fails_the_status():
    # real GRBL after a hard limit: the alarm, the message, then no status report until a soft
    # reset, which the driver sends itself (tests/rig/test_grbl_firmware.py)
    script = [(b"?", b"<Idle|MPos:-185.000,-90.000,0.000|FS:0,0>\r\n"),
              (b"G53 G0 X-95.000 Y-80.000\n", b"ok\r\n"),
              (b"?", b"<Run|MPos:-175.000,-89.000,0.000|FS:5400,0>\r\n"),
              (b"?", b"ALARM:1\r\n[MSG:Reset to continue]\r\n"),
              (b"\x18", BANNER + b"[MSG:'$H'|'$X' to unlock]\r\n"),
              (b"?", b"<Alarm|MPos:-160.000,-87.000,0.000|FS:0,0>\r\n")]
    p, t = positioner(script, state="Idle")
    p._homed = True
    with pytest.raises(GrblAlarm, match="hard limit") as info:
        p.move_to(LightTarget(azimuth_deg=90, elevation_deg=10)).wait(2)
    assert info.value.alarm == 1 and info.value.code == "ALARM:1"
    assert not p.homed  # a hard limit loses the position
    assert "Reset to continue" in p.messages
    assert p.status().state == "Alarm"  # answering again: recovered by the driver's reset
    t.assert_done()


def test_soft_limit_alarm_is_recovered_by_reset_and_unlock():
    # bytes of the real firmware (test_grbl_firmware.py): ALARM:2 and the critical-event message
    # instead of 'ok'; the rejected line's 'ok' comes on the reset, before the banner; the
    # position is kept, so the driver unlocks ("the alarm may be safely unlocked")
    p, t = positioner([(b"G53 G0 X1.000\n", b"ALARM:2\r\n[MSG:Reset to continue]\r\n"),
                       (b"\x18", b"ok\r\n" + BANNER + b"[MSG:'$H'|'$X' to unlock]\r\n"),
                       (b"$X\n", b"[MSG:Caution: Unlocked]\r\nok\r\n"),
                       (b"?", b"<Idle|MPos:-5.000,-5.000,-1.000|FS:0,0>\r\n")], state="Idle")
    with pytest.raises(GrblAlarm, match="soft limit") as info:
        p.send("G53 G0 X1.000")
    assert info.value.alarm == 2 and p.homed
    assert p.status().state == "Idle"
    t.assert_done()


def test_failed_homing_waits_for_grbls_own_reset_and_searches_again():
    # real GRBL after ALARM:9: the 'ok' of $H, then its own reset's banner; a '?' sent before the
    # banner is dropped, so the driver reads up to the banner, then homes once more
    fail = b"ALARM:9\r\nok\r\n" + BANNER + b"[MSG:'$H'|'$X' to unlock]\r\n"
    p, t = positioner([(b"?", b"<Alarm|MPos:0.000,0.000,0.000|FS:0,0>\r\n"), (b"$H\n", fail),
                       (b"$H\n", b"ok\r\n"),
                       (b"?", b"<Idle|MPos:-1.000,-1.000,-1.000|FS:0,0>\r\n")])
    p.home().wait(2)
    assert p.homed and p.last_alarm == 9
    t.assert_done()
    # a second ALARM:9 fails the homing, after GRBL's reset, and the next call is answered
    p, t = positioner([(b"?", b"<Alarm|MPos:0.000,0.000,0.000|FS:0,0>\r\n"), (b"$H\n", fail),
                       (b"$H\n", fail), (b"?", b"<Alarm|MPos:-30.000,-30.000,-1.000|FS:0,0>\r\n")])
    with pytest.raises(GrblAlarm, match="could not find the limit switch") as info:
        p.home().wait(2)
    assert info.value.alarm == 9 and not p.homed
    assert p.status().state == "Alarm"
    t.assert_done()


def test_stop_during_homing_is_a_reset_at_once():
    # GRBL ignores '!' in the homing cycle and answers no '?': the stop is Ctrl-X, not a hold
    p, t = positioner([(b"?", b"<Alarm|MPos:0.000,0.000,0.000|FS:0,0>\r\n"), (b"$H\n", None),
                       (b"\x18", b"ALARM:6\r\nok\r\n" + BANNER + b"[MSG:'$H'|'$X' to unlock]\r\n"),
                       (b"?", b"<Alarm|MPos:-3.000,-3.000,-1.000|FS:0,0>\r\n")])
    status = p.home()
    with pytest.raises(DeviceBusy, match="homing"):
        p.status()
    p.stop()
    with pytest.raises(GrblAlarm, match="homing cycle was reset"):
        status.wait(2)
    assert not p.homed and t.written[-1] == b"\x18"
    assert p.status().state == "Alarm"
    t.assert_done()


def test_stop_is_feed_hold_then_reset():
    script = [(b"!", None), (b"?", b"<Hold:1|MPos:5.000,0.000,0.000|FS:100,0>\r\n"),
              (b"?", b"<Hold:0|MPos:6.000,0.000,0.000|FS:0,0>\r\n"), (b"\x18", BANNER)]
    p, t = positioner(script, state="Idle")
    p.stop()
    t.assert_done()


def test_status_timeout_is_typed():
    p, t = positioner([(b"?", None)], state="Idle")
    with pytest.raises(DeviceTimeout):
        p.status()
    t.assert_done()


def test_send_rejects_realtime_characters():
    p, t = positioner([], state="Idle")
    with pytest.raises(ValueError, match="real-time"):
        p.send("G0 X1?")


def test_unlock_resume_and_sync_bytes():
    script = [(b"$X\n", b"[MSG:Caution: Unlocked]\r\nok\r\n"),
              (b"~", None),
              (b"G4 P0\n", b"ok\r\n")]
    p, t = positioner(script)
    p.unlock()
    assert p.messages[-1] == "Caution: Unlocked"
    p.resume()
    p.sync(timeout_s=1)
    t.assert_done()


def test_status_poll_keeps_a_reply_for_the_waiting_line():
    # a status poll reading the 'ok' of a line another thread waits for hands it over
    p, t = positioner([(b"G4 P0\n", None), (b"?", b"ok\r\n<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n")],
                      state="Idle")
    p.transport.write(b"G4 P0\n")  # as send() does, then a poll before it reads
    assert p.status().state == "Idle"
    assert list(p._inbox) == ["ok"]
    t.assert_done()


def test_late_status_report_and_banner_do_not_confuse_a_response():
    p, t = positioner([(b"$G\n", b"<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n" + BANNER
                        + b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\nok\r\n")], state="Idle")
    assert p.send("$G") == ["[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"]
    t.assert_done()


# -- machine space ----------------------------------------------------------------------------------
def test_machine_space_follows_homing_direction_and_pull_off():
    settings = {22: 1, 23: 0b010, 27: 1.0, 130: 365.0, 131: 90.0, 132: 2.0}
    assert machine_space(settings, "X") == (-365.0, -1.0)  # towards +: switch at 0, pulled off
    assert machine_space(settings, "Y") == (-89.0, 0.0)  # towards -: switch at -$131


def test_machine_map_round_trip_and_bad_tables():
    m = MachineMap.from_config({"X": -182.0}, {"Y": -1})
    assert m.to_machine({"X": 10.0, "Y": 20.0, "Z": 1.0}) == {"X": -172.0, "Y": -20.0, "Z": 1.0}
    assert m.to_axes(m.to_machine({"X": 10.0, "Y": 20.0})) == {"X": 10.0, "Y": 20.0}
    assert m.machine_range("Y", 0.0, 85.0) == (-85.0, 0.0)
    for offset, sign, message in [({"Q": 1.0}, None, "axis 'Q'"), ({"X": "a"}, None, "finite number"),
                                  (None, {"X": 2}, "1 or -1"), ([1.0], None, "table")]:
        with pytest.raises(ValueError, match=message):
            MachineMap.from_config(offset, sign)


def test_docs_worked_example_passes_the_check_and_a_wrong_offset_is_refused():
    """The GRBL arm of docs/rig-file.md: its settings and rig-file section are consistent; the
    same arm without the machine map is refused with a message naming the settings."""
    doc = (Path(__file__).resolve().parents[2] / "docs" / "rig-file.md").read_text()
    toml_block = doc.split("**Worked example.**")[1].split("```toml")[1].split("```")[0]
    section = tomllib.loads(toml_block)["positioner"]
    settings = {int(n): float(v) for n, v in re.findall(r"\$(\d+)=([\d.]+)",
                                                         doc.split("**Worked example.**")[1].split("```toml")[0])}
    assert settings[130] == 365 and settings[23] == 0
    kin = kinematics_from_config(section["kinematics"])
    check_machine_space(settings, kin, MachineMap.from_config(section["machine_offset"], None))
    with pytest.raises(ConfigError, match=r"axis X .*\$130=365, \$27=1, \$23=0\): set machine_offset X = "
                                          r"-183 \(centred\), or change \$130; axis Y .*\$131=90"):
        check_machine_space(settings, kin, MachineMap.from_config(None, None))
    # the variant homed towards -: $23 bit 0 set, offset -183
    check_machine_space({**settings, 23: 1}, kin, MachineMap.from_config({"X": -183.0, "Y": -88.0}, None))
    check_machine_space({**settings, 22: 0}, kin, MachineMap.from_config(None, None))  # no homing: no check


def test_rig_file_machine_map_keys():
    p = GrblPositioner.from_config("positioner", {"driver": "grbl", "port": "/dev/null",
                                                  "machine_offset": {"X": -182.0}, "machine_sign": {"Y": -1}})
    assert p.describe()["machine_offset"] == {"X": -182.0} and p.machine_map.sign == {"Y": -1}
    with pytest.raises(ConfigError, match=r"\[positioner\] machine_sign X = 3 must be 1 or -1"):
        GrblPositioner.from_config("positioner", {"driver": "grbl", "port": "/dev/null",
                                                  "machine_sign": {"X": 3}})


def test_home_then_park_moves_the_light_to_the_park_target():
    script = [(b"?", b"<Alarm|MPos:0.000,0.000,0.000|FS:0,0>\r\n"), (b"$H\n", b"ok\r\n"),
              (b"?", b"<Idle|MPos:-1.000,-1.000,-1.000|FS:0,0>\r\n"),
              (b"G53 G0 X-185.000 Y-90.000\n", b"ok\r\n"),
              (b"?", b"<Idle|MPos:-185.000,-90.000,-1.000|FS:0,0>\r\n")]
    t = ScriptedTransport(connect_script() + script, device="positioner")
    p = GrblPositioner("positioner", transport=t, poll_interval_s=0.0, machine_offset=MACHINE_OFFSET,
                       park={"azimuth_deg": 0.0, "elevation_deg": 0.0})
    p.connect()
    assert p.home().wait(2) == pytest.approx((500.0, 0.0, 0.0))
    t.assert_done()
    with pytest.raises(ConfigError, match=r"\[positioner\] park = \{'azimuth_deg': 0\}"):
        GrblPositioner.from_config("positioner", {"driver": "grbl", "port": "/dev/null",
                                                  "park": {"azimuth_deg": 0}})
