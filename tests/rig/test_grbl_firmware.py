"""GrblPositioner against the REAL GRBL 1.1h firmware (gnea/grbl built for the host with grbl-sim,
``../shared/third_party/grbl``), on a pseudo-terminal, and GrblSim against the same exchanges.

The firmware runs in real time, so the machine is small and fast: 20 steps per degree, 3000
deg/min, 1000 deg/s^2, 20 deg of travel on X and Y, 2 on Z, homing towards + with a 1 deg pull-off.
The harness models the switches from the step pulses: the home switch at machine 0, an end stop
at -22. The arm's azimuth -9..9 deg and
elevation 0..15 deg sit at MPos -19..-1 and -17..-2 (machine_offset X = -10, Y = -17).

Evidence recorded from the firmware (these bytes are asserted below):
- soft limit: ``ALARM:2\\r\\n[MSG:Reset to continue]\\r\\n``, no answer to ``?`` until Ctrl-X,
  then ``ok`` (the rejected line's), the banner, ``[MSG:'$H'|'$X' to unlock]``;
- after ``$H``: ``MPos:-1.000,-1.000,-1.000`` (minus the pull-off $27);
- failed homing: ``ALARM:9\\r\\nok\\r\\n`` and the banner of GRBL's own reset;
- ``$Z`` -> ``error:2``, ``$100=-1`` -> ``error:4``, an empty line -> ``ok``;
- a reset sent the moment ``ALARM:2`` arrived, before ``[MSG:Reset to continue]``, was lost
  (protocol.c clears a pending reset after printing the alarm): the driver waits for the message;
- ``??`` in one write was answered with one or with two reports, depending on timing (a status
  request is a flag the main loop polls); the driver never sends it.
GRBL's interface.md on ALARM: "Reset is required before Grbl accepts any other commands ... Only
hard or soft limit errors send this".
"""
from __future__ import annotations

import re
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from rig import DeviceBusy, LightTarget
from rig.grbl import GrblAlarm, GrblPositioner
from rig.rig import ConfigError
from sims.grbl_firmware import (FAST_SETTINGS, FAST_SWITCHES, WRAPPED, GrblFirmware, build_firmware,
                                write_eeprom)
from sims.grbl_sim import GrblSim

GRBL_DIR = Path(__file__).resolve().parents[3] / "shared" / "third_party" / "grbl"

SETTINGS, SWITCHES = FAST_SETTINGS, FAST_SWITCHES  # written to the firmware's EEPROM once
KINEMATICS = {"type": "arm", "radius_mm": 500.0, "azimuth_limits_deg": [-9.0, 9.0],
              "elevation_limits_deg": [0.0, 15.0]}
MACHINE_OFFSET = {"X": -10.0, "Y": -17.0}
#: reply timeout: generous, the firmware's two busy threads compete with whatever else runs
TIMEOUT = 2.0


def _read_until(port, marker: bytes, timeout: float = 10.0) -> bytes:
    out, deadline = b"", time.monotonic() + timeout
    while marker not in out and time.monotonic() < deadline:
        out += port.read(4096)
    assert marker in out, f"no {marker!r} from the firmware within {timeout} s, got {out!r}"
    return out


@pytest.fixture(scope="session")
def grbl_build(tmp_path_factory) -> Path:
    """Build grbl_sim.exe once per session and write SETTINGS into an EEPROM image; the folder."""
    if shutil.which("gcc") is None or shutil.which("make") is None:
        pytest.skip("no C compiler (gcc, make): the real GRBL firmware cannot be built")
    if not (GRBL_DIR / "build.sh").is_file():
        pytest.skip(f"{GRBL_DIR} is absent (the GRBL sources ship beside the repository, not in it)")
    out = tmp_path_factory.mktemp("grbl")
    write_eeprom(build_firmware(GRBL_DIR, out), out / "eeprom", SETTINGS)
    return out


def start_firmware(build: Path, folder: Path, **opts) -> GrblFirmware:
    """A fresh firmware process with the configured EEPROM, axes at -10, -10, -1 at power-up;
    the file ``folder / "press"`` presses every switch while it exists."""
    work = folder / "grbl"
    work.mkdir()
    shutil.copy(build / "eeprom" / "EEPROM.DAT", work / "EEPROM.DAT")
    # end stops (pressed everywhere beyond the switch): a narrow flag switch can pass unseen
    # while the harness's main-loop thread waits for a CPU, failing the homing with ALARM:9
    fw = GrblFirmware(build / "grbl_sim.exe", work, press_file=folder / "press",
                      **{"start": (-10.0, -10.0, -1.0), "limits": SWITCHES, **opts})
    fw.start()
    return fw


@pytest.fixture
def firmware(grbl_build, tmp_path, request):
    fw = start_firmware(grbl_build, tmp_path, **getattr(request, "param", {}))
    yield fw
    fw.stop()


@dataclass
class HomedArm:
    """One firmware and driver for the tests that start and end homed and idle (homing takes
    about a second of firmware time, so it is done once)."""

    firmware: GrblFirmware
    driver: GrblPositioner
    press: Path  # every limit switch reads pressed while this file exists
    power_up_state: str
    homed_mpos: tuple[float, ...]


@pytest.fixture(scope="module")
def arm(grbl_build, tmp_path_factory):
    folder = tmp_path_factory.mktemp("arm")
    fw = start_firmware(grbl_build, folder)
    p = driver(fw)
    state = report(p).state
    home(p)
    yield HomedArm(fw, p, folder / "press", state, report(p).mpos)
    p.close()
    fw.stop()


@pytest.fixture
def homed(arm) -> GrblPositioner:
    """The shared arm, checked homed and idle (each test using it leaves it so)."""
    if not arm.driver.connected:
        arm.driver.connect()
    assert arm.driver.homed and report(arm.driver).state == "Idle"
    return arm.driver


def driver(fw: GrblFirmware, **kw) -> GrblPositioner:
    p = GrblPositioner("positioner", fw.port, kinematics=KINEMATICS, timeout_s=TIMEOUT,
                       poll_interval_s=0.01, poll_retries=6, home_timeout_s=30.0,
                       **{"machine_offset": MACHINE_OFFSET, **kw})
    deadline = time.monotonic() + 20.0
    while b"['$' for help]" not in fw.replies:  # the firmware boots in about a second
        assert time.monotonic() < deadline, f"firmware did not boot: {bytes(fw.replies)!r}"
        time.sleep(0.02)
    p.connect()
    return p


def report(p: GrblPositioner):
    """A status report, retried like the driver's own polls (``_poll``), as a real serial line
    needs. The harness's own garbling (the TX interrupt thread sending a ring-buffer slot before
    the main loop's byte landed: ``<Ho8d:1|...>``, ``-l.000``) is gone with
    ``sims/grbl_sim_interrupts.c``: 0 garbled or late in 2000 polls, 3 before (``Fr:0,0``; a
    report stranded until the next one; ``benchmarks/grbl_firmware.py --race``)."""
    return p._poll(p.status)


def home(p: GrblPositioner) -> None:
    """``home()``, repeated on ALARM:9 (approach) or 8 (pull-off) ended early: on a loaded host the
    harness's stepper thread can drain GRBL's segment buffer while the main loop waits for a CPU,
    which ends that motion short (third_party/grbl/README.md; seen: ALARM:8 from a second homing
    at a load of 17 on 2 cores). The driver's own recovery is tested strictly below."""
    for attempt in range(3):
        try:
            p.home().wait(30)
            return
        except GrblAlarm as exc:
            if exc.alarm not in (8, 9) or attempt == 2:
                raise


def test_build_links_the_interrupt_exclusion(grbl_build):
    """GRBL's printing and grbl-sim's interrupt thread reach the serial ring only through gonio's
    wrappers (``sims/grbl_sim_interrupts.c``, ``ld --wrap``): without them the two threads race
    (``benchmarks/grbl_firmware.py --race``: 3 bad replies in 2000 polls)."""
    if shutil.which("objdump") is None:
        pytest.skip("no objdump (binutils): cannot read the firmware's call sites")
    code = subprocess.run(["objdump", "-d", str(grbl_build / "grbl_sim.exe")], capture_output=True,
                          text=True, check=True).stdout
    def calls(function: str) -> set[str]:
        body = code.split(f"<{function}>:\n", 1)[1].split("\n\n", 1)[0]
        return set(re.findall(r"(?:call|jmp)\s+[0-9a-f]+ <([\w.]+)>", body))
    assert "__wrap_serial_write" in calls("printString") and "serial_write" not in calls("printString")
    assert "__wrap_interrupt_SERIAL_UDRE" in calls("simulate_serial")
    assert {f"__wrap_{name}" for name in WRAPPED} <= set(re.findall(r"<(__wrap_\w+)>:", code))


def test_connect_home_and_moves_by_status_polling(arm, homed):
    p = homed
    assert p.version == "1.1h" and p.build == "1.1h.20190830"
    assert p.settings[130] == 20 and p.settings[27] == 1 and p.homing_enabled
    assert arm.power_up_state == "Alarm"  # homing enabled: locked at power-up
    assert arm.homed_mpos == (-1.0, -1.0, -1.0)  # minus the pull-off, all three axes
    for az, el in [(5.0, 3.0), (-8.0, 14.0)]:
        final = p.move_to(LightTarget(azimuth_deg=az, elevation_deg=el)).wait(15)
        mpos = p.machine_position()
        # GRBL moves in whole steps (1/20 deg): within half a step of the target
        assert mpos["X"] == pytest.approx(MACHINE_OFFSET["X"] + az, abs=0.026)
        assert mpos["Y"] == pytest.approx(MACHINE_OFFSET["Y"] + el, abs=0.026)
        assert final == pytest.approx(p.kinematics.forward({"X": az, "Y": el}), abs=0.3)


def test_feed_hold_resume_and_stop_keep_position(arm, homed):
    p, firmware = homed, arm.firmware
    mark = len(firmware.replies)
    # from the far end, whatever the test before left: the hold lands while cruising. Before
    # sims/grbl_sim_interrupts.c this hold read "Hold:1" for over 2 s in 2 of 60 (--race) and
    # failed this file about 1 run in 3: the harness's TX thread could clear its interrupt-enable
    # bit over the main loop's fresh setting of it, stranding a report in the ring until GRBL next
    # wrote, so the driver read it after its 2 s timeout (and a '$H' whose 'ok' stranded, never)
    p.move_to(LightTarget(azimuth_deg=9.0, elevation_deg=0.0)).wait(15)
    status = p.move_to(LightTarget(azimuth_deg=-9.0, elevation_deg=0.0))  # 18 deg: ~0.5 s
    time.sleep(0.15)
    p.feed_hold()
    deadline = time.monotonic() + 2
    # GRBL's protocol_exec_rt_system() serves EXEC_STATUS_REPORT before EXEC_FEED_HOLD when both
    # flags are set in one pass, so a '?' that arrives with the '!' may still read Run (seen in
    # the suite, 2026-11-26): Run until the hold lands, then Hold:1 decelerating, Hold:0 complete
    seen = []
    while (st := report(p)).substate != 0 or st.state != "Hold":
        seen.append(st.state)
        assert st.state in ("Run", "Hold") and time.monotonic() < deadline, seen
        assert "Hold" not in seen or st.state == "Hold", seen   # once held, held
        time.sleep(0.01)
    held = st.mpos
    time.sleep(0.1)
    assert report(p).mpos == held and -19.0 < held[0] < -1.0  # holding part way
    p.resume()
    status.wait(15)
    assert p.machine_position()["X"] == pytest.approx(-19.0, abs=0.026)
    status = p.move_to(LightTarget(azimuth_deg=9.0, elevation_deg=0.0))
    time.sleep(0.15)
    p.stop()
    with pytest.raises(Exception, match="from the target"):
        status.wait(3)
    st = report(p)
    assert st.state == "Idle" and -19.0 < st.mpos[0] < -1.0  # hold, then reset: no ALARM:3
    assert b"ALARM" not in firmware.replies[mark:]
    assert p.move_to(LightTarget(azimuth_deg=0.0, elevation_deg=5.0)).wait(15)


def test_soft_limit_alarm_2_is_recovered_by_the_driver(arm, homed):
    p, firmware = homed, arm.firmware
    before = p.machine_position()
    with pytest.raises(GrblAlarm, match="soft limit") as info:
        p.send("G53 G0 X5.000")  # beyond machine space [-20, 0]: $20=1 rejects it
    assert info.value.alarm == 2
    assert b"ALARM:2\r\n[MSG:Reset to continue]\r\n" in firmware.replies
    assert b"ok\r\n\r\nGrbl 1.1h ['$' for help]\r\n" in firmware.replies  # the late ok, then banner
    assert p.homed and report(p).state == "Idle"  # reset and $X by the driver: position kept
    assert p.machine_position() == before
    assert p.move_to(LightTarget(azimuth_deg=3.0, elevation_deg=5.0)).wait(15)


def test_hard_limit_alarm_1_is_an_alarm_not_a_timeout(arm, homed):
    p, firmware, press = homed, arm.firmware, arm.press
    mark = len(firmware.replies)
    press.touch()  # every switch pressed while idle: hard limit
    t0 = time.monotonic()
    while b"ALARM:1" not in firmware.replies[mark:]:
        assert time.monotonic() - t0 < 2, "no ALARM:1 from the firmware"
        time.sleep(0.01)
    press.unlink()
    time.sleep(0.02)  # the harness polls the press file every ~4 ms
    with pytest.raises(GrblAlarm, match="hard limit") as info:
        p.status()
    assert info.value.alarm == 1 and not p.homed
    assert report(p).state == "Alarm"  # answered again: the driver's reset ended the silence
    home(p)
    # the same during a move: the driver's status poll meets the alarm and fails the move
    status = p.move_to(LightTarget(azimuth_deg=-9.0, elevation_deg=0.0))
    time.sleep(0.1)
    mark = len(firmware.replies)
    press.touch()
    t0 = time.monotonic()
    while b"ALARM:" not in firmware.replies[mark:]:
        assert time.monotonic() - t0 < 2, "no alarm from the firmware"
        time.sleep(0.01)
    press.unlink()
    with pytest.raises(GrblAlarm) as info:
        status.wait(15)
    # GRBL's limit ISR calls mc_reset() (ALARM:3 in motion) and then sets ALARM:1; on the AVR
    # the main loop cannot run in between, on the host harness's two threads it sometimes does
    # (third_party/grbl/README.md), and GRBL then reports the reset in motion
    assert info.value.alarm in (1, 3)
    assert not p.homed
    time.sleep(0.02)
    home(p)
    assert p.homed and report(p).mpos == (-1.0, -1.0, -1.0)


@pytest.mark.parametrize("firmware", [{"start": (-19.5, -19.5, -1.0)}], indirect=True)
def test_stop_during_homing_reaches_the_wire_at_once(firmware):
    p = driver(firmware)
    status = p.home()  # ~0.4 s of seeking from -19.5 at 50 deg/s
    time.sleep(0.15)
    with pytest.raises(DeviceBusy):
        p.status()  # GRBL answers no '?' during homing; the driver says so instead of waiting
    t0 = time.monotonic()
    p.stop()
    arrived = firmware.arrival(b"\x18", t0)
    assert arrived is not None and arrived - t0 < 0.050, f"E-stop took {arrived - t0:.3f} s"
    with pytest.raises(GrblAlarm) as info:
        status.wait(3)
    # "homing fail: the active homing cycle was reset"; a reset during a pull-off, with the switch
    # still pressed, is reported as ALARM:8 (limits.c sets 6, then overwrites it with the pull-off check)
    assert info.value.alarm in (6, 8)
    assert not p.homed and report(p).state == "Alarm"
    p.close()


# the end stop moved out of the way (-60): X powered up beyond it would have its pin pressed
@pytest.mark.parametrize("firmware", [{"start": (-35.0, -10.0, -1.0),
                                       "limits": ((-60.0, -22.0, -4.0), (0.0, 0.0, 0.0))}], indirect=True)
def test_failed_homing_alarm_9_is_recovered(firmware):
    # X powered up 35 deg from its switch: the first search (1.5 x $130 = 30 deg) ends short
    p = driver(firmware)
    try:
        p.home().wait(30)  # ALARM:9, GRBL's own reset, then the driver's second $H
    except GrblAlarm as exc:
        # only if the harness also cut the second search short (CPU-starved; see home())
        assert exc.alarm == 9
    assert b"ALARM:9\r\nok\r\n\r\nGrbl 1.1h ['$' for help]\r\n" in firmware.replies
    assert sum(data.count(b"$H\n") for _, data in firmware.wire_log) == 2  # searched again unasked
    assert report(p).state in ("Idle", "Alarm")  # answered at once: no '?' lost in GRBL's reset
    home(p)
    assert p.homed and report(p).mpos == (-1.0, -1.0, -1.0)
    p.close()


def test_inconsistent_configuration_is_refused_naming_the_settings(arm, homed):
    homed.close()  # the port for the drivers under test; the fixture reconnects it
    with pytest.raises(ConfigError, match=r"axis X .*\$130=20, \$27=1, \$23=0.*machine_offset X = -10"):
        driver(arm.firmware, machine_offset={"Y": -17.0})  # azimuth -9..9 at MPos -9..9: beyond 0
    p = driver(arm.firmware)  # the consistent one connects, and finds the machine homed
    assert p.homed
    p.close()


#: (request, the bytes that end its answer; None: the answer is silence), and ``$H``
EXCHANGE: list[tuple[bytes, bytes | None]] = [
    (b"\x18", b"unlock]\r\n"), (b"?", b">\r\n"), (b"$Z\n", b"\r\n"), (b"$100=-1\n", b"\r\n"),
    (b"\n", b"\r\n"), (b"$H\n", b"ok\r\n"), (b"?", b">\r\n"), (b"?", b">\r\n"),
    (b"G53 G0 X5.000\n", b"continue]\r\n"), (b"?", None), (b"\x18", b"unlock]\r\n"), (b"?", b">\r\n"),
    (b"$X\n", b"ok\r\n"), (b"?", b">\r\n"), (b"?", b">\r\n")]


def _exchange(port) -> list[bytes]:
    """Each request of EXCHANGE and its answer (plus whatever follows within 30 ms)."""
    out = []
    for request, end in EXCHANGE:
        if request == b"$H\n":
            out.append(_home_until_it_works(port))
            continue
        port.write(request)
        got = _read_until(port, end) if end is not None else b""
        quiet = time.monotonic() + (0.3 if end is None else 0.03)
        while time.monotonic() < quiet:
            got += port.read(4096)
        out.append(got)
    return out


def test_simulator_answers_as_the_firmware(firmware):
    """The same bytes to the real firmware and to GrblSim (same settings, same switches): equal
    answers where the driver relies on them."""
    import serial
    driver(firmware).close()  # booted and reset
    with GrblSim(fast=False, kinematics=KINEMATICS, settings=SETTINGS, travel=SWITCHES,
                 power_up_position=(-10.0, -10.0, -1.0)) as sim:
        answers = {}
        for name, path in (("firmware", firmware.port), ("sim", sim.port)):
            port = serial.Serial(path, 115200, timeout=0.02)
            try:
                answers[name] = _exchange(port)
            finally:
                port.close()
    real, simulated = answers["firmware"], answers["sim"]
    requests = [r for r, _ in EXCHANGE]
    assert real[0] == simulated[0] == b"\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n"
    for i in (2, 3, 4, 8, 9, 10, 12):  # errors, empty line, soft limit, silence, late ok, unlock
        assert simulated[i] == real[i], (requests[i], real[i], simulated[i])
    assert real[8] == b"ALARM:2\r\n[MSG:Reset to continue]\r\n" and real[9] == b""
    assert real[10].startswith(b"ok\r\n\r\nGrbl 1.1h")
    for i in (1, 11, 13, 14):  # status reports after a reset: state, position, WCO / Ov as GRBL's
        assert _fields(simulated[i]) == _fields(real[i]), (requests[i], real[i], simulated[i])
    for i in (6, 7):  # after homing (GRBL may have reset itself on a harness ALARM:9 before it)
        assert _fields(simulated[i], ("FS", "WCO", "Ov")) == _fields(real[i], ("FS", "WCO", "Ov"))
    assert _fields(real[6], ("FS", "WCO", "Ov")) == ["Idle|MPos:-1.000,-1.000,-1.000"]


def _home_until_it_works(port) -> bytes:
    """``$H`` until it succeeds: under load the harness can end a homing approach early
    (ALARM:9; third_party/grbl/README.md); GRBL then resets itself and homes again on request."""
    for _ in range(3):
        port.write(b"$H\n")
        out = _read_until(port, b"ok\r\n", timeout=30)
        if b"ALARM" not in out:
            return out
        _read_until(port, b"unlock]\r\n")
    raise AssertionError(f"homing failed three times: {out!r}")


def _fields(reply: bytes, drop: tuple[str, ...] = ("FS",)) -> list[str]:
    """Status reports of ``reply`` without the fields ``drop`` (the feed depends on timing):
    ``State|MPos:...|WCO:...``."""
    out = []
    for line in reply.decode().split("\r\n"):
        if line.startswith("<"):
            out.append("|".join(f for f in line[1:-1].split("|") if f.partition(":")[0] not in drop))
        elif line:
            out.append(line)
    return out
