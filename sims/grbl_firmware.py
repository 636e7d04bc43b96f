"""The real GRBL 1.1h firmware (a grbl-sim host build) behind a pseudo-terminal port.

``../shared/third_party/grbl/build.sh`` compiles gnea/grbl's own C code with the grbl-sim
harness into ``grbl_sim.exe``, which runs GRBL's main loop on stdin/stdout at about real time.
The program prints nothing unless its stdin and stdout are a terminal, so it runs on the slave
side of one raw pty; :class:`GrblFirmware` relays bytes between that pty's master and the port
the driver opens (the slave of a second pty, behind a stable symlink, as every
:class:`~sims.serial_sim.SerialSim` does). Every chunk the driver writes is logged with the time
it reached this end of the wire (:attr:`wire_log`), so a test can measure when an E-stop byte
arrived.

The firmware keeps its settings in ``EEPROM.DAT`` in its working directory (``workdir``):
:func:`write_eeprom` boots it once to store settings, :func:`build_firmware` runs the build. The
harness models the limit switches from the step pulses (``limits``, ``start``; see
``harness_limits.c``). GPL sources, used for testing only: nothing of gonio links them.

:func:`build_firmware` links gonio's ``grbl_sim_interrupts.c`` into the build: grbl-sim runs the
AVR's interrupts on a second thread beside GRBL's main loop, and without it the firmware sent
stale ring-buffer bytes in its replies (2-3 per 2000 status polls at a load of 10-15 on 2 cores),
read stale bytes of commands, lost real-time flags and could strand a reply's last bytes
(docs/vendor-clients.md; ``benchmarks/grbl_firmware.py --race`` measures both builds).
"""
from __future__ import annotations

import os
import select
import shutil
import subprocess
import time
import tty
from pathlib import Path
from typing import Sequence

import serial

from .serial_sim import SerialSim

#: a small, fast machine for tests and benchmarks (the firmware runs in real time): homing on,
#: towards +, 1 unit pull-off; soft and hard limits on; 20 units of travel on X and Y, 2 on Z;
#: 20 steps per unit, 3000 units/min, 1000 units/s^2; homing seek 3000, locate 600 units/min,
#: 10 ms debounce
FAST_SETTINGS: dict[int, float] = {
    22: 1, 20: 1, 21: 1, 23: 0, 27: 1, 130: 20, 131: 20, 132: 2, 25: 3000, 24: 600, 26: 10,
    100: 20, 101: 20, 102: 20, 110: 3000, 111: 3000, 112: 3000, 120: 1000, 121: 1000, 122: 1000}
#: switches of that machine (machine units): the home switch at 0, an end stop at -22 (-4 on Z)
FAST_SWITCHES = ((-22.0, -22.0, -4.0), (0.0, 0.0, 0.0))


#: gonio's own harness change, made to the tree ``build.sh`` leaves in ``OUT/tree/grbl/sim``:
#: ``grbl_sim_interrupts.c`` (beside this file) runs grbl-sim's interrupt thread and GRBL's main
#: loop under one mutex where the firmware relies on the AVR's exclusion (its header says why), by
#: wrapping these functions at link time; GRBL's own code is not touched
INTERRUPTS_C = Path(__file__).with_name("grbl_sim_interrupts.c")
WRAPPED = ("serial_write", "orig_serial_read", "serial_reset_read_buffer", "interrupt_SERIAL_UDRE",
           "interrupt_SERIAL_RX", "system_set_exec_state_flag", "system_clear_exec_state_flag",
           "system_set_exec_alarm", "system_clear_exec_alarm", "system_set_exec_motion_override_flag",
           "system_set_exec_accessory_override_flag", "system_clear_exec_motion_overrides",
           "system_clear_exec_accessory_overrides")
#: build.sh's compiler flags, for the relink
_MAKE_FLAGS = "FLAGS=-g -O2 -fcommon"


def build_firmware(grbl_dir: str | os.PathLike, out: str | os.PathLike, *, exclusive: bool = True) -> Path:
    """Compile ``grbl_dir/build.sh`` (GRBL 1.1h + grbl-sim, needs gcc and make) into ``out``;
    return the path of ``grbl_sim.exe``. ``exclusive``: add :data:`INTERRUPTS_C` and relink
    (False: the harness as ``build.sh`` makes it, whose two threads garble bytes and lose
    real-time flags now and then; for ``benchmarks/grbl_firmware.py --race``). Raises
    ``subprocess.CalledProcessError`` with the build's output on failure."""
    grbl_dir, out = Path(grbl_dir), Path(out)
    subprocess.run(["bash", str(grbl_dir / "build.sh"), str(grbl_dir / "grbl-1.1h"), str(grbl_dir / "grbl-sim"),
                    str(out)], check=True, capture_output=True, timeout=300)
    if exclusive:
        sim = out / "tree" / "grbl" / "sim"
        shutil.copy(INTERRUPTS_C, sim / INTERRUPTS_C.name)
        makefile = (sim / "Makefile").read_text()
        objects, libraries = "SIM_OBJECTS = ", "LINUX_LIBRARIES = -lrt -pthread"
        if objects not in makefile or libraries not in makefile:
            raise RuntimeError(f"{sim / 'Makefile'} changed upstream: no {objects!r} or {libraries!r} to extend")
        wraps = ",".join(f"--wrap={name}" for name in WRAPPED)
        makefile = makefile.replace(objects, f"{objects}{INTERRUPTS_C.stem}.o ", 1)
        makefile = makefile.replace(libraries, f"{libraries} -Wl,{wraps}", 1)
        (sim / "Makefile").write_text(makefile)
        subprocess.run(["make", "main", _MAKE_FLAGS], cwd=sim, check=True, capture_output=True, timeout=300)
        shutil.copy(sim / "grbl_sim.exe", out / "grbl_sim.exe")
    return out / "grbl_sim.exe"


def write_eeprom(exe: str | os.PathLike, folder: str | os.PathLike, settings: dict[int, float],
                 timeout_s: float = 20.0) -> Path:
    """Boot the firmware once in ``folder`` and store ``settings`` (``$n=value``) in its EEPROM;
    return the ``EEPROM.DAT`` to copy into a firmware's working directory."""
    def read_until(port: serial.Serial, marker: bytes) -> bytes:
        out, deadline = b"", time.monotonic() + timeout_s
        while marker not in out:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no {marker!r} from the GRBL firmware within {timeout_s} s: {out!r}")
            out += port.read(4096)
        return out

    fw = GrblFirmware(exe, folder)
    port = serial.Serial(fw.start(), 115200, timeout=0.05)
    try:
        read_until(port, b"['$' for help]")  # first boot: error:7 (blank EEPROM), defaults, banner
        for n, value in settings.items():
            port.write(f"${n}={value}\n".encode())
            if b"ok\r\n" not in (reply := read_until(port, b"\r\n")):
                raise ValueError(f"GRBL refused ${n}={value}: {reply!r}")
    finally:
        port.close()
        fw.stop()
    return Path(folder) / "EEPROM.DAT"


def _triple(values: Sequence[float], what: str) -> list[float]:
    out = [float(v) for v in values]
    if len(out) != 3:
        raise ValueError(f"{what} needs 3 values (X, Y, Z), got {values!r}")
    return out


class GrblFirmware(SerialSim):
    """Run ``grbl_sim.exe`` and serve it on :attr:`port`.

    Parameters
    ----------
    exe : path
        The built ``grbl_sim.exe``.
    workdir : path
        Working directory of the firmware (its ``EEPROM.DAT`` settings live there).
    name : str
        Port symlink name.
    limits : ((3,), (3,)) float, optional
        Physical positions of the low and high limit switch of each axis, machine units
        (``GRBL_SIM_LIMITS``). None: no switch is ever pressed.
    start : (3,) float
        Physical axis position at power-up, machine units (``GRBL_SIM_START``).
    switch_width : float, optional
        A switch reads pressed only within this many units past its position (a flag switch;
        ``GRBL_SIM_SWITCH_WIDTH``). None: pressed everywhere beyond it (an end stop).
    press_file : path, optional
        While a file exists at this path every limit switch reads pressed (``GRBL_SIM_PRESS``).
    max_catchup_ms : float
        Bound on how much simulated time catches up at once after the host descheduled the
        firmware (``GRBL_SIM_MAX_CATCHUP_MS``). Unbounded, a burst drains GRBL's segment buffer
        (6 segments of ~10 ms) and ends a homing approach early (ALARM:9); a small bound makes
        simulated time lag far behind on a loaded host (2 ms: moves took 2-5x their planned time
        at a load average of 10 on 2 cores); 20 ms is below the buffer's depth.
    """

    def __init__(self, exe: str | os.PathLike, workdir: str | os.PathLike, name: str = "positioner", *,
                 limits: tuple[Sequence[float], Sequence[float]] | None = None,
                 start: Sequence[float] = (0.0, 0.0, 0.0), switch_width: float | None = None,
                 press_file: str | os.PathLike | None = None, max_catchup_ms: float = 20.0) -> None:
        super().__init__(name)
        self.exe = Path(exe)
        if not self.exe.is_file():
            raise FileNotFoundError(f"GRBL firmware build {self.exe} does not exist (build it with "
                                    "third_party/grbl/build.sh)")
        self.workdir = Path(workdir)
        self.env = dict(os.environ, GRBL_SIM_START=",".join(f"{v:g}" for v in _triple(start, "start")),
                        GRBL_SIM_MAX_CATCHUP_MS=f"{max_catchup_ms:g}")
        if limits is not None:
            lo, hi = _triple(limits[0], "limits low"), _triple(limits[1], "limits high")
            self.env["GRBL_SIM_LIMITS"] = ",".join(f"{a:g}:{b:g}" for a, b in zip(lo, hi))
        if switch_width is not None:
            self.env["GRBL_SIM_SWITCH_WIDTH"] = f"{switch_width:g}"
        if press_file is not None:
            self.env["GRBL_SIM_PRESS"] = str(press_file)
        self.wire_log: list[tuple[float, bytes]] = []  # (monotonic time, bytes from the driver)
        self.replies = bytearray()  # everything the firmware sent
        self._proc: subprocess.Popen | None = None
        self._fw: int | None = None  # master of the firmware's own pty

    def start(self) -> str:
        self.workdir.mkdir(parents=True, exist_ok=True)
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        try:
            self._proc = subprocess.Popen([str(self.exe), "-n", "-s", "/dev/null", "-b", "/dev/null"],
                                          stdin=slave, stdout=slave, stderr=subprocess.DEVNULL,
                                          cwd=self.workdir, env=self.env, close_fds=True)
        finally:
            os.close(slave)
        self._fw = master
        return super().start()

    def stop(self) -> None:
        super().stop()
        if self._proc is not None:
            self._proc.kill()  # ^F would shut down cleanly, but the settings are already saved
            self._proc.wait(timeout=5)
            self._proc = None
        if self._fw is not None:
            os.close(self._fw)
            self._fw = None

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def _serve(self) -> None:
        """Relay driver <-> firmware until stopped; no framing, bytes go on as they come."""
        while self._running:
            master, fw = self._master, self._fw
            if master is None or fw is None:
                time.sleep(0.005)
                continue
            try:
                ready, _, _ = select.select([master, fw], [], [], 0.05)
            except (OSError, ValueError):
                time.sleep(0.005)
                continue
            if master in ready:
                try:
                    data = os.read(master, 4096)
                except OSError:  # no reader on the port side between driver sessions
                    data = b""
                    time.sleep(0.005)
                if data:
                    self.wire_log.append((time.monotonic(), data))
                    self.requests.append(data)
                    os.write(fw, data)
            if fw in ready:
                try:
                    data = os.read(fw, 4096)
                except OSError:  # the firmware exited
                    self._running = False
                    return
                self.replies += data
                self.send(data)

    def arrival(self, byte: bytes, after: float) -> float | None:
        """Time (monotonic) the first chunk containing ``byte`` reached the firmware's end of
        the wire at or after ``after``; None if it never did."""
        for t, data in list(self.wire_log):
            if t >= after and byte in data:
                return t
        return None
