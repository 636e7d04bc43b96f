"""The GRBL driver against the REAL GRBL 1.1h firmware (host build, ``../shared/third_party/grbl``).

    python benchmarks/grbl_firmware.py [--trials 5]

Prints, with the host's load average (the firmware runs in real time on two busy threads, so
every figure depends on how much CPU it gets):
- build time, first boot with a blank EEPROM and the settings write, boot to the banner;
- homing time, and a move's time against GRBL's planned time (``rig.grbl.path_time_s``);
- E-stop latency: from ``stop()`` to the byte at the firmware's end of the wire, during a homing
  cycle (Ctrl-X) and during a move (``!``), over ``--trials`` each (the bound the tests use:
  50 ms).

    python benchmarks/grbl_firmware.py --race 2000 [--holds 60]

compares the harness as ``build.sh`` makes it with gonio's (``sims/grbl_sim_interrupts.c``):
``--race`` status polls (a ``$I`` every 50th, whose answer is known) counting replies that are
not a well-formed report or are missing, then ``--holds`` feed holds from the far end through the
driver (as ``test_feed_hold_resume_and_stop_keep_position``), counting holds not complete
(``Hold:0``) within 2 s and cycles that failed.
"""
from __future__ import annotations

import argparse
import os
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path

# benchmarks/rig.py beside this file would shadow the rig package: drop this folder from the path
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]

from rig import LightTarget  # noqa: E402
import serial  # noqa: E402

from rig.grbl import GrblAlarm, GrblPositioner, path_time_s  # noqa: E402
from sims.grbl_firmware import (FAST_SETTINGS, FAST_SWITCHES, GrblFirmware, build_firmware,  # noqa: E402
                                write_eeprom)

GRBL_DIR = Path(__file__).resolve().parents[2] / "shared" / "third_party" / "grbl"
KINEMATICS = {"type": "arm", "azimuth_limits_deg": [-9.0, 9.0], "elevation_limits_deg": [0.0, 15.0]}
OFFSET = {"X": -10.0, "Y": -17.0}


def _home(p: GrblPositioner) -> float:
    """Seconds for a successful homing (repeating a harness-starved early ALARM:9)."""
    for _ in range(3):
        t0 = time.monotonic()
        try:
            p.home().wait(60)
            return time.monotonic() - t0
        except GrblAlarm as exc:
            if exc.alarm != 9:
                raise
            print("  (homing ended early with ALARM:9: the harness starved of CPU; again)")
    raise RuntimeError("homing failed three times")


#: a well-formed report of this machine ($10=1: MPos; WCO, Ov and Pn now and then)
REPORT = re.compile(rb"<(Idle|Run|Hold:[01]|Alarm|Home)\|MPos:(-?\d+\.\d{3},){2}-?\d+\.\d{3}\|FS:\d+,\d+"
                    rb"(\|(WCO:(-?\d+\.\d{3},){2}-?\d+\.\d{3}|Ov:\d+,\d+,\d+|Pn:[XYZPDHRS]+))*>\r\n")
VERSION = b"[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n"


def _read_until(port: serial.Serial, marker: bytes, timeout: float) -> bytes:
    out, deadline = b"", time.monotonic() + timeout
    while marker not in out and time.monotonic() < deadline:
        out += port.read(4096)
    return out


def _polls(fw: GrblFirmware, n: int) -> tuple[int, int, list[bytes]]:
    """``n`` status polls (a ``$I`` every 50th) on a fresh firmware: (garbled: an answer that is
    not exactly the expected lines; unanswered: no complete report within 1 s; examples, each
    with the answer to the poll after it, where a stranded tail would show)."""
    port = serial.Serial(fw.port, 115200, timeout=0.005)
    try:
        _read_until(port, b"unlock]\r\n", 10)
        garbled, lost, seen, bad = 0, 0, [], None
        for i in range(n):
            port.write(b"?")
            got = _read_until(port, b">\r\n", 1.0)
            if bad is not None:
                seen.append(bad + b" then " + got)
                bad = None
            report = got
            if got.endswith(b">\r\n") and i % 50 == 0:
                port.write(b"$I\n")
                got += _read_until(port, b"ok\r\n", 1.0)
                report, _, version = got.partition(b">\r\n")
                report += b">\r\n"
                if version != VERSION:
                    report = got
            if not got.endswith(b"\r\n"):
                lost += 1
                bad = got
            elif not REPORT.fullmatch(report):
                garbled += 1
                bad = got
        return garbled, lost, seen
    finally:
        port.close()


def _holds(p: GrblPositioner, n: int) -> tuple[int, int]:
    """``n`` feed holds 0.15 s into an 18 deg move from the far end: (holds that took over 2 s
    to complete, cycles that failed)."""
    slow = failed = 0
    for _ in range(n):
        try:
            p.move_to(LightTarget(azimuth_deg=9.0, elevation_deg=0.0)).wait(15)
            status = p.move_to(LightTarget(azimuth_deg=-9.0, elevation_deg=0.0))
            time.sleep(0.15)
            p.feed_hold()
            t0 = time.monotonic()
            while (st := p._poll(p.status)).substate != 0 or st.state != "Hold":
                if time.monotonic() - t0 > 15.0:
                    raise TimeoutError(f"no Hold:0 within 15 s: {st}")
                time.sleep(0.01)
            slow += time.monotonic() - t0 > 2.0
            p.resume()
            status.wait(15)
        except Exception as exc:  # noqa: BLE001 - counted and recovered
            failed += 1
            print(f"    {type(exc).__name__}: {exc}")
            p.soft_reset()
            _home(p)
    return slow, failed


def race(exe: Path, eeprom: Path, work: Path, polls: int, holds: int) -> None:
    """Print garbled and missing replies over ``polls`` polls, slow holds and failed cycles over
    ``holds`` holds, for the firmware ``exe``."""
    for name, trial in (("polls", polls), ("holds", holds)):
        folder = work / name
        folder.mkdir(parents=True)
        (folder / "EEPROM.DAT").write_bytes(eeprom.read_bytes())
        fw = GrblFirmware(exe, folder, limits=FAST_SWITCHES, start=(-10.0, -10.0, -1.0))
        fw.start()
        t0 = time.monotonic()
        try:
            if name == "polls":
                garbled, lost, seen = _polls(fw, trial)
                print(f"  {trial} polls: {garbled} garbled, {lost} unanswered ({time.monotonic() - t0:.0f} s, "
                      f"load {os.getloadavg()[0]:.1f}) {seen[:3]}")
            elif trial:
                p = GrblPositioner("positioner", fw.port, kinematics=KINEMATICS, machine_offset=OFFSET,
                                   timeout_s=2.0, poll_interval_s=0.01, poll_retries=6, home_timeout_s=60.0)
                while b"['$' for help]" not in fw.replies:
                    time.sleep(0.005)
                p.connect()
                _home(p)
                slow, failed = _holds(p, trial)
                p.close()
                print(f"  {trial} feed holds: {slow} took over 2 s, {failed} failed ({time.monotonic() - t0:.0f} s, "
                      f"load {os.getloadavg()[0]:.1f})")
        finally:
            fw.stop()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=5, help="E-stop measurements of each kind")
    ap.add_argument("--race", type=int, default=0, help="status polls per harness (0: the timings instead)")
    ap.add_argument("--holds", type=int, default=60, help="with --race: feed holds per harness")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    if args.race:
        with tempfile.TemporaryDirectory(prefix="gonio-grbl-") as tmp:
            for exclusive in (False, True):
                out = Path(tmp) / ("exclusive" if exclusive else "stock")
                exe = build_firmware(GRBL_DIR, out, exclusive=exclusive)
                print("gonio's harness (sims/grbl_sim_interrupts.c)" if exclusive else "build.sh's harness")
                race(exe, write_eeprom(exe, out / "eeprom", FAST_SETTINGS), out / "run", args.race, args.holds)
        return 0
    with tempfile.TemporaryDirectory(prefix="gonio-grbl-") as tmp:
        out = Path(tmp)
        t0 = time.monotonic()
        exe = build_firmware(GRBL_DIR, out)
        print(f"build {time.monotonic() - t0:.1f} s")
        t0 = time.monotonic()
        eeprom = write_eeprom(exe, out / "eeprom", FAST_SETTINGS)
        print(f"first boot + {len(FAST_SETTINGS)} settings {time.monotonic() - t0:.1f} s")
        work = out / "run"
        work.mkdir()
        (work / "EEPROM.DAT").write_bytes(eeprom.read_bytes())
        fw = GrblFirmware(exe, work, limits=FAST_SWITCHES, start=(-10.0, -10.0, -1.0))
        t0 = time.monotonic()
        fw.start()
        while b"['$' for help]" not in fw.replies:
            time.sleep(0.005)
        print(f"boot to banner {time.monotonic() - t0:.2f} s")
        p = GrblPositioner("positioner", fw.port, kinematics=KINEMATICS, machine_offset=OFFSET, timeout_s=2.0,
                           poll_interval_s=0.01, poll_retries=6, home_timeout_s=60.0)
        try:
            p.connect()
            print(f"homing from 9 deg below the switches {_home(p):.2f} s")
            planned = path_time_s((-1.0, -1.0), (-19.0, -17.0), (3000.0, 3000.0), (1000.0, 1000.0))
            t0 = time.monotonic()
            p.move_to(LightTarget(azimuth_deg=-9.0, elevation_deg=0.0)).wait(30)
            print(f"move 18 x 16 deg {time.monotonic() - t0:.3f} s (GRBL's plan {planned:.3f} s; "
                  f"+ status polling every 10 ms)")
            homing, moving = [], []
            for _ in range(args.trials):
                status = p.home()
                time.sleep(0.1)
                t0 = time.monotonic()
                p.stop()
                homing.append(fw.arrival(b"\x18", t0) - t0)
                try:
                    status.wait(10)
                except GrblAlarm:
                    pass  # ALARM:6, as expected
                _home(p)
                target = -9.0 if p.machine_position()["X"] > -10.0 else 9.0
                status = p.move_to(LightTarget(azimuth_deg=target, elevation_deg=0.0))
                time.sleep(0.1)
                t0 = time.monotonic()
                p.stop()
                moving.append(fw.arrival(b"!", t0) - t0)
                try:
                    status.wait(10)
                except Exception:  # noqa: BLE001 - the move ends short of its target, as expected
                    pass
            for label, values in (("during homing (Ctrl-X)", homing), ("during a move (!)", moving)):
                print(f"E-stop to the wire {label}: median {1e3 * statistics.median(values):.1f} ms, "
                      f"max {1e3 * max(values):.1f} ms over {len(values)}")
        finally:
            p.close()
            fw.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
