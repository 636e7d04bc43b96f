"""GRBL 1.1 firmware simulator: the light-stage positioner on a pty.

Byte for byte what ``gnea/grbl`` 1.1h sends: the banner ``Grbl 1.1h ['$' for help]`` after
power-up and soft reset, ``ok`` when a line is parsed and queued (not when it has finished),
``error:N``, pushed ``ALARM:N`` and ``[MSG:...]``, ``$$`` settings, ``$I`` build info, and the
real-time bytes ``?`` (status report), ``!`` (feed hold), ``~`` (resume) and ``0x18`` (soft reset)
picked out of the stream wherever they appear, without a line end.

Model: moves run through a queue with a trapezoidal profile along the straight path, speed and
acceleration limited per axis by ``$110..$112`` (units/min) and ``$120..$122`` (units/s^2);
``G4 P..`` answers ``ok`` once the queue has drained and the dwell elapsed. With ``$22=1``
(homing enabled) the firmware starts in ``Alarm`` after power-up; a reset during motion raises
``ALARM:3`` and keeps the lock.

As the real firmware (gnea/grbl 1.1h, measured on the grbl-sim build in
``tests/rig/test_grbl_firmware.py``; where the two differ on a command the driver sends, the
firmware is right):

- ``$H`` moves each axis to its home switch at the ``$25`` seek rate and leaves it at minus the
  pull-off ``$27`` (towards +, ``$23`` bit clear) or at ``-$13x + $27`` (towards -): GRBL's
  machine space is [-``$13x``, 0]; its ``ok`` comes when the cycle has finished, and ``?`` is
  not answered during the cycle (one report, state ``Home``, just before the ``ok``); a reset
  during the cycle gives ``ALARM:6``, the ``ok`` of ``$H``, then the banner;
- soft limits (``$20=1``): a motion target outside [-``$13x``, 0] is ``ALARM:2``,
  ``[MSG:Reset to continue]``; hard-limit switches sit at the edges of ``travel`` (the home
  switch at the + end): a move that reaches one stops there with ``ALARM:1``. Both are critical:
  nothing, ``?`` included, is answered until a soft reset; the line rejected by a soft limit gets
  its ``ok`` on the reset, before the banner;
- a status request sets a flag: ``?`` bytes that arrive together give one report; the ``WCO:``
  and ``Ov:`` fields come as GRBL's refresh counters send them (report.c: every 10th report when
  idle, 30th / 20th when busy);
- ``error:N`` with GRBL's own numbers for ``$`` commands (``$Z`` -> ``error:2``, a negative
  setting -> ``error:4``); every line end (``\r`` or ``\n``) ends a line, and an empty line is
  answered ``ok``.

A feed hold brakes along the path (``Hold:1``), then holds (``Hold:0``); ``~`` re-plans the rest
of the move (and is ignored while still braking); a reset after the hold keeps the position.

Simplifications, stated: work coordinates equal machine coordinates (no G92/G10 offsets; WCO is
reported as zero); no ``Pn:`` field; all three axes home together (GRBL homes Z first, then X
and Y); the planner never fills (``ok`` is immediate for every motion line); moves
are planned one at a time (no junction speed carried between queued blocks).

Faults for :meth:`inject` besides ``no_reply``, ``garble``, ``disconnect``:

- ``alarm`` the next move trips a hard limit half way: ``ALARM:1``, ``[MSG:Reset to continue]``;
- ``error`` the next line is answered ``error:N`` with ``N = error_code`` (default 33).

:attr:`light_position_mm` gives the light's world position through the same kinematics table the
driver is configured with (:func:`light_position_mm`; sims may not import rig, so the forward
maps and the machine map are repeated here and a test keeps them equal to ``rig.kinematics``).
"""
from __future__ import annotations

import math
import re
import time
from collections import deque
from typing import Any, Mapping

import numpy as np

from .serial_sim import SerialSim
from .zaber_sim import trapezoid_distance, trapezoid_duration, trapezoid_speed

VERSION = "1.1h"
BUILD = "1.1h.20190825"
BANNER = f"\r\nGrbl {VERSION} ['$' for help]\r\n".encode()
REALTIME = frozenset(b"?!~\x18")

#: default settings (GRBL's $-numbers); units of the arm: degrees, of the gantry: millimetres
#: (the arm's elevation, Y, homes towards - ($23 bit 1): to the horizontal, where jogs go up)
ARM_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0, 20: 0, 21: 1,
    22: 1, 23: 2, 24: 25.0, 25: 3600.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
    100: 80.0, 101: 80.0, 102: 80.0, 110: 5400.0, 111: 5400.0, 112: 5400.0,
    120: 360.0, 121: 360.0, 122: 360.0, 130: 370.0, 131: 95.0, 132: 1.0,
}
GANTRY_SETTINGS: dict[int, float] = {
    **ARM_SETTINGS, 23: 0, 100: 80.0, 101: 80.0, 102: 400.0, 110: 12000.0, 111: 12000.0, 112: 6000.0,
    120: 500.0, 121: 500.0, 122: 300.0, 130: 1000.0, 131: 1000.0, 132: 1000.0, 25: 6000.0,
}

_WORD = re.compile(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))")
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")


def light_position_mm(kinematics: str | Mapping[str, Any], machine: Any,
                      machine_map: Mapping[str, Mapping[str, float]] | None = None) -> tuple[float, float, float]:
    """World-frame light position (mm) for machine coordinates ``machine`` = (x, y, z).

    ``kinematics`` is the rig-file table of ``rig.kinematics`` (``"arm"`` / ``"gantry"`` or
    ``{type = ..., ...}``) with the same defaults: arm X = azimuth deg, Y = elevation deg, light at
    ``radius_mm`` (500) about ``centre_mm``; gantry ``origin_mm + R @ machine`` with ``R`` from
    ``rotation`` or ``yaw_deg`` about +z. ``machine_map`` holds the rig file's
    ``machine_offset`` / ``machine_sign`` tables: axis = (machine - offset) * sign.
    """
    cfg: dict[str, Any] = {"type": kinematics} if isinstance(kinematics, str) else dict(kinematics)
    m = np.asarray(machine, dtype=float).copy()
    offset = (machine_map or {}).get("machine_offset", {})
    sign = (machine_map or {}).get("machine_sign", {})
    for i, axis in enumerate("XYZ"):
        m[i] = (m[i] - offset.get(axis, 0.0)) * sign.get(axis, 1)
    if cfg.get("type") == "arm":
        az, el = math.radians(m[0]), math.radians(m[1])
        centre = np.asarray(cfg.get("centre_mm", (0.0, 0.0, 0.0)), dtype=float)
        p = centre + float(cfg.get("radius_mm", 500.0)) * np.array(
            [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    elif cfg.get("type") == "gantry":
        if "rotation" in cfg:
            rot = np.asarray(cfg["rotation"], dtype=float)
        else:
            c, s = math.cos(math.radians(cfg.get("yaw_deg", 0.0))), math.sin(math.radians(cfg.get("yaw_deg", 0.0)))
            rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        p = np.asarray(cfg.get("origin_mm", (0.0, 0.0, 0.0)), dtype=float) + rot @ m
    else:
        raise ValueError(f"kinematics type {cfg.get('type')!r} is unknown; use 'arm' or 'gantry'")
    return (float(p[0]), float(p[1]), float(p[2]))


class GrblSim(SerialSim):
    """A GRBL 1.1h controller driving the light positioner, behind a pseudo-terminal.

    Parameters
    ----------
    name : str
        Role (port symlink name).
    fast : bool
        Moves and homing complete at once.
    kinematics : str or mapping
        Kinematics table (as in the rig file) for :attr:`light_position_mm`; also picks the
        default settings (arm: degrees, gantry: millimetres).
    machine_map : mapping, optional
        The rig file's ``machine_offset`` / ``machine_sign`` tables (machine = offset + sign *
        axis), for :attr:`light_position_mm`.
    settings : mapping, optional
        ``$n`` overrides, e.g. ``{22: 0}`` to disable homing.
    travel : ((3,), (3,)) float, optional
        Limit switch positions in the homed machine frame (machine units), low and high per
        axis. Default: the home switch at the end ``$23`` homes towards (0, or -``$13x``) and an
        end stop 2 units beyond the other end; none when homing is disabled (``$22=0``).
    power_up_position : (3,) float, optional
        Physical position at power-up in the homed machine frame; GRBL reports 0,0,0 there
        until homed. Default: where homing leaves the axes (0 with homing disabled).
    error_code : int
        Code returned by the ``error`` fault.
    """

    FAULTS = SerialSim.FAULTS | {"alarm", "error"}

    terminator = None  # framing by split(): lines, plus real-time bytes anywhere

    def __init__(self, name: str = "positioner", *, fast: bool = False,
                 kinematics: str | Mapping[str, Any] = "arm", machine_map: Mapping[str, Any] | None = None,
                 settings: Mapping[int, float] | None = None, travel: Any = None,
                 power_up_position: Any = None, error_code: int = 33) -> None:
        super().__init__(name, fast=fast)
        self.kinematics = {"type": kinematics} if isinstance(kinematics, str) else dict(kinematics)
        self.machine_map = {k: dict(v) for k, v in (machine_map or {}).items()}
        light_position_mm(self.kinematics, (0.0, 0.0, 0.0), self.machine_map)  # validate the tables now
        defaults = ARM_SETTINGS if self.kinematics["type"] == "arm" else GANTRY_SETTINGS
        self.defaults = {**defaults, **(settings or {})}
        self.settings = dict(self.defaults)
        if travel is None and self.settings[22]:  # the home switch at its end, an end stop 2 beyond the other
            towards_minus = [bool(int(self.settings[23]) & (1 << i)) for i in range(3)]
            travel = (tuple(-self.settings[130 + i] - (0.0 if m else 2.0) for i, m in enumerate(towards_minus)),
                      tuple(2.0 if m else 0.0 for m in towards_minus))
        elif travel is None:  # homing disabled: a machine without switches
            travel = ((-math.inf,) * 3, (math.inf,) * 3)
        self.travel = (np.asarray(travel[0], dtype=float), np.asarray(travel[1], dtype=float))
        if power_up_position is None:  # where the last homing left it; without homing, MPos 0
            power_up_position = self.home_position() if self.settings[22] else np.zeros(3)
        self.power_up_position = np.asarray(power_up_position, dtype=float)
        self.error_code = error_code
        self.on_power_up()

    # -- firmware state ---------------------------------------------------------------------------
    def on_power_up(self) -> None:
        with self._lock:
            self.mpos = np.zeros(3)
            self._offset = self.power_up_position.copy()  # physical = reported + offset
            self.queue: deque[tuple[str, Any]] = deque()  # ("move", target) / ("dwell", seconds)
            self._active: tuple | None = None  # (kind, t0, start, end, duration, vmax, amax, trip)
            self.hold: str | None = None  # None, "braking" (Hold:1) or "held" (Hold:0)
            self._resume: tuple[np.ndarray, bool] | None = None  # (end, trip) of the held move
            self.state = "Alarm" if self.settings[22] else "Idle"
            self.critical = False
            self.hard_limit_next = False
            self._late_oks = 0  # lines held by a critical alarm: answered 'ok' on the reset
            self._report_after_home = False  # a '?' during the homing cycle, answered at its end
            self._wco_counter = self._ovr_counter = 0  # report.c's refresh counters
            self._pending: bytearray = bytearray()  # pushes for tick()
        self._boot_message = BANNER + (b"[MSG:'$H'|'$X' to unlock]\r\n" if self.state == "Alarm" else b"")

    def start(self) -> str:
        port = super().start()
        self.send(self._boot_message)  # nobody may be listening yet: a real board prints it anyway
        return port

    def reconnect(self) -> None:
        super().reconnect()
        self.send(self._boot_message)

    def on_disconnect(self) -> None:
        with self._lock:
            self._advance(time.monotonic())
            self._active = None
            self.queue.clear()

    def home_position(self) -> np.ndarray:
        """Where ``$H`` leaves each axis (machine units): -``$27`` homing towards +,
        -``$13x`` + ``$27`` towards - (``$23`` bit set)."""
        pull_off = self.settings[27]
        return np.array([-self.settings[130 + i] + pull_off if int(self.settings[23]) & (1 << i)
                         else -pull_off for i in range(3)])

    @property
    def physical_position(self) -> np.ndarray:
        """Where the axes really are, machine units (differs from MPos until homed)."""
        with self._lock:
            self._advance(time.monotonic())
            return self.mpos + self._offset

    @property
    def light_position_mm(self) -> tuple[float, float, float]:
        """World-frame light position (mm) from the physical axis positions."""
        return light_position_mm(self.kinematics, self.physical_position, self.machine_map)

    def _rates(self) -> tuple[np.ndarray, np.ndarray]:
        rate = np.array([self.settings[110 + i] for i in range(3)]) / 60.0
        accel = np.array([self.settings[120 + i] for i in range(3)])
        return rate, accel

    def _begin(self, kind: str, end: np.ndarray, now: float, trip: bool = False) -> None:
        start = self.mpos.copy()
        phys_end = end + self._offset
        lo, hi = self.travel
        if kind == "move" and (np.any(phys_end < lo) or np.any(phys_end > hi) or self.hard_limit_next):
            # stop where the path first meets a limit switch (or half way for an injected trip)
            phys_start = start + self._offset
            d = phys_end - phys_start
            with np.errstate(divide="ignore", invalid="ignore"):
                f_lo = np.where(d < 0, (lo - phys_start) / d, np.inf)
                f_hi = np.where(d > 0, (hi - phys_start) / d, np.inf)
            frac = min(1.0, float(np.min(np.minimum(f_lo, f_hi))))
            if self.hard_limit_next:
                frac, self.hard_limit_next = min(frac, 0.5), False
            end = start + max(frac, 0.0) * (end - start)
            trip = True
        delta = end - start
        length = float(np.linalg.norm(delta))
        if kind == "home":
            vmax = amax = None
            duration = 0.0 if self.fast else float(np.max(np.abs(phys_end - (start + self._offset)))) / (
                self.settings[25] / 60.0) + 0.05
        elif length > 0:
            rate, accel = self._rates()
            nz = np.abs(delta) > 0
            vmax = float(np.min(rate[nz] * length / np.abs(delta[nz])))
            amax = float(np.min(accel[nz] * length / np.abs(delta[nz])))
            duration = 0.0 if self.fast else trapezoid_duration(length, vmax, amax)
        else:
            vmax = amax = None
            duration = 0.0
        self._active = (kind, now, start, end, duration, vmax, amax, trip)

    def _advance(self, now: float) -> None:
        """Run the motion model up to ``now``: finish moves, start queued ones, push messages."""
        while True:
            if self.hold == "held" or self.critical:
                return
            if self._active is None:
                if not self.queue:
                    if self.state in ("Run", "Home"):
                        self.state = "Idle"
                    return
                kind, arg = self.queue.popleft()
                if kind == "dwell":
                    self._active = ("dwell", now, self.mpos.copy(), self.mpos.copy(),
                                    0.0 if self.fast else arg, None, None, False)
                elif kind == "sync":
                    self._pending += b"ok\r\n"
                    continue
                elif kind == "resume":
                    self._begin("move", arg[0], now, trip=arg[1])
                    self.state = "Run"
                else:
                    self._begin(kind, np.asarray(arg, dtype=float), now)
                    self.state = "Home" if kind == "home" else "Run"
            kind, t0, start, end, duration, vmax, amax, trip = self._active
            if kind == "brake":
                t = min(now - t0, duration)
                length = float(np.linalg.norm(end - start))
                s = vmax * t - 0.5 * amax * t * t  # vmax holds the speed when the hold began
                self.mpos = start + (end - start) * (s / length if length else 0.0)
                if now - t0 >= duration:
                    self.mpos = end.copy()
                    self._active = None
                    self.hold = "held"
                return
            if now - t0 < duration:
                if vmax is not None:
                    length = float(np.linalg.norm(end - start))
                    s = trapezoid_distance(length, vmax, amax, now - t0)
                    self.mpos = start + (end - start) * (s / length)
                elif kind == "home":
                    self.mpos = start + (end - start) * ((now - t0) / duration)
                return
            self.mpos = end.copy()
            self._active = None
            if kind == "home":  # GRBL sets MPos to where the axes physically stand
                self.mpos = self.mpos + self._offset
                self._offset = np.zeros(3)
                if self._report_after_home:
                    self._report_after_home = False
                    self._pending += self._status_report()
                self._pending += b"ok\r\n"
            if trip:
                self.queue.clear()
                self.state = "Alarm"
                self.critical = True
                self._pending += b"ALARM:1\r\n[MSG:Reset to continue]\r\n"
                return

    def tick(self) -> bytes | None:
        with self._lock:
            self._advance(time.monotonic())
            out, self._pending = bytes(self._pending), bytearray()
        return out or None

    # -- framing ----------------------------------------------------------------------------------
    def split(self, buf: bytearray) -> list[bytes]:
        """Real-time bytes become requests of their own, wherever they are (``?`` bytes that
        arrive together are one request: GRBL's status request is a flag); the rest is lines,
        each ``\r`` or ``\n`` ending one (an empty line too: GRBL answers it ``ok``)."""
        out, line = [], bytearray()
        for byte in buf:
            if byte in REALTIME:
                if not (byte == ord("?") and b"?" in out):
                    out.append(bytes([byte]))
            elif byte in b"\r\n":
                out.append(bytes(line))
                line = bytearray()
            else:
                line.append(byte)
        buf[:] = line  # an unfinished line waits for its end
        return out

    # -- protocol ---------------------------------------------------------------------------------
    def handle(self, request: bytes) -> bytes | None:
        with self._lock:
            now = time.monotonic()
            self._advance(now)
            if len(request) == 1 and request[0] in REALTIME:
                return self._realtime(request, now)
            if self.critical:
                return None  # after a critical alarm only a soft reset is answered
            line = request.decode("ascii", "replace").strip().upper().replace(" ", "")
            if not line:
                return b"ok\r\n"
            if self.take_fault("error"):
                return f"error:{self.error_code}\r\n".encode()
            reply = self._system(line) if line.startswith("$") else self._gcode(line, now)
            return None if reply is None else reply.encode()

    def _status_report(self) -> bytes:
        state = self.state
        if state == "Hold":
            state = "Hold:1" if self.hold == "braking" else "Hold:0"
        pos = self.mpos  # WCO is zero, so WPos == MPos
        label = "MPos" if int(self.settings[10]) & 1 else "WPos"
        feed = 0.0
        if self._active is not None and self._active[5] is not None and not self.fast:
            kind, t0, start, end, duration, vmax, amax, _ = self._active
            t = time.monotonic() - t0
            if kind == "brake":
                feed = max(0.0, vmax - amax * t) * 60.0
            else:
                feed = trapezoid_speed(float(np.linalg.norm(end - start)), vmax, amax, t) * 60.0
        text = f"<{state}|{label}:{pos[0]:.3f},{pos[1]:.3f},{pos[2]:.3f}|FS:{feed:.0f},0"
        busy = self.state in ("Run", "Hold", "Home", "Jog", "Door")
        if self._wco_counter > 0:  # report.c: WCO every 10th report idle, 30th busy
            self._wco_counter -= 1
        else:
            self._wco_counter = 29 if busy else 9
            self._ovr_counter = self._ovr_counter or 1  # overrides on the next report
            text += "|WCO:0.000,0.000,0.000"
        if self._ovr_counter > 0:  # Ov every 10th report idle, 20th busy
            self._ovr_counter -= 1
        else:
            self._ovr_counter = 19 if busy else 9
            text += "|Ov:100,100,100"
        return (text + ">\r\n").encode()

    def _realtime(self, byte: bytes, now: float) -> bytes | None:
        if byte == b"?":
            if self.critical:
                return None  # the critical-alarm loop in protocol.c prints no report
            if self.state == "Home":
                self._report_after_home = True  # limits.c polls only reset, door and cycle stop
                return None
            return self._status_report()
        if byte == b"!":
            if self.state == "Run" and self._active is not None and self._active[0] == "move" \
                    and self._active[5] is not None:
                self._hold(now)
            return None
        if byte == b"~":
            if self.state == "Hold" and self.hold == "held":  # ignored while still braking
                self.hold = None
                if self._resume is not None:  # re-plan the rest of the held move from here
                    self.queue.appendleft(("resume", self._resume))
                    self._resume = None
                self.state = "Run"
                self._advance(now)
            return None
        # soft reset
        moving = self.state in ("Run", "Home", "Jog") or self.hold == "braking"
        self._advance(now)
        self._active = None
        self.queue.clear()
        self.hold = None
        self._resume = None
        out = b""
        if moving:
            # a reset ends the homing cycle with ALARM:6, then $H gets its 'ok'
            out += b"ALARM:3\r\n" if self.state != "Home" else b"ALARM:6\r\nok\r\n"
            self.state = "Alarm"
        elif self.state != "Alarm":
            self.state = "Idle"
        self.critical = False
        self._report_after_home = False
        self._wco_counter = self._ovr_counter = 0  # GRBL clears its system state on a reset
        out += b"ok\r\n" * self._late_oks + BANNER
        self._late_oks = 0
        if self.state == "Alarm":
            out += b"[MSG:'$H'|'$X' to unlock]\r\n"
        return out

    def _hold(self, now: float) -> None:
        """Feed hold: brake along the path at the move's acceleration (``Hold:1``), then stay
        (``Hold:0``) until ``~``; queued moves wait."""
        _, t0, start, end, duration, vmax, amax, trip = self._active
        length = float(np.linalg.norm(end - start))
        t = now - t0
        v = 0.0 if self.fast else trapezoid_speed(length, vmax, amax, t)
        here = start + (end - start) * (trapezoid_distance(length, vmax, amax, t) / length)
        stop = here + (end - start) / length * min(v * v / (2 * amax), length - float(np.linalg.norm(here - start)))
        self.mpos = here
        self._resume = (end.copy(), trip)
        self._active = ("brake", now, here, stop, v / amax, v, amax, False)
        self.hold = "braking"
        self.state = "Hold"
        self._advance(now)

    def _system(self, line: str) -> str | None:
        if line == "$":
            return "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]\r\nok\r\n"
        if line == "$$":
            body = "".join(f"${n}={self._fmt(n)}\r\n" for n in sorted(self.settings))
            return body + "ok\r\n"
        if line == "$I":
            return f"[VER:{BUILD}:]\r\n[OPT:V,15,128]\r\nok\r\n"
        if line == "$G":
            return "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\nok\r\n"
        if line == "$#":
            return "[G54:0.000,0.000,0.000]\r\n[G28:0.000,0.000,0.000]\r\n[G92:0.000,0.000,0.000]\r\n" \
                   "[TLO:0.000]\r\n[PRB:0.000,0.000,0.000:0]\r\nok\r\n"
        if line == "$X":
            if self.state == "Alarm":
                self.state = "Idle"
                return "[MSG:Caution: Unlocked]\r\nok\r\n"
            return "ok\r\n"
        if line == "$H":
            if not self.settings[22]:
                return "error:5\r\n"
            if self.state not in ("Idle", "Alarm"):
                return "error:8\r\n"
            self.queue.append(("home", self.home_position() - self._offset))  # in reported units
            self._advance(time.monotonic())
            return None  # 'ok' is pushed when the cycle has finished
        if line[1] in "$GCXJ#HSIRN":
            return "error:3\r\n"  # a known command letter in a form not modelled here
        # system.c's default branch: $<number>=<value>
        m = _NUMBER.match(line, 1)
        if m is None:
            return "error:2\r\n"  # bad number format ($Z)
        if line[m.end():m.end() + 1] != "=":
            return "error:3\r\n"
        v = _NUMBER.fullmatch(line, m.end() + 1)
        if v is None:
            return "error:2\r\n"
        if self.state not in ("Idle", "Alarm"):
            return "error:8\r\n"
        if float(v.group()) < 0:
            return "error:4\r\n"  # settings.c: negative value
        n = float(m.group())
        if not n.is_integer() or int(n) not in self.settings:
            return "error:3\r\n"
        if int(n) == 20 and float(v.group()) and not self.settings[22]:
            return "error:10\r\n"  # soft limits need homing
        self.settings[int(n)] = float(v.group())
        return "ok\r\n"

    def _fmt(self, n: int) -> str:
        value = self.settings[n]
        return f"{value:.3f}" if n >= 11 and n not in (13, 20, 21, 22, 23, 26, 30, 31, 32) \
            else str(int(value))

    def _gcode(self, line: str, now: float) -> str | None:
        if self.state == "Alarm":
            return "error:9\r\n"
        pos, words = 0, []
        while pos < len(line):
            m = _WORD.match(line, pos)
            if m is None:
                return "error:1\r\n" if not line[pos].isalpha() else "error:2\r\n"
            words.append((m.group(1), float(m.group(2))))
            pos = m.end()
        g = [v for k, v in words if k == "G"]
        axes = {k: v for k, v in words if k in "XYZ"}
        if len(axes) != len([k for k, _ in words if k in "XYZ"]):
            return "error:25\r\n"
        for k, v in words:
            if k not in "GXYZFPN":
                return "error:20\r\n"
        if any(code not in (0, 1, 4, 17, 21, 53, 90, 91, 94) for code in g):
            return "error:20\r\n"
        if 4 in g:
            p = [v for k, v in words if k == "P"]
            if not p:
                return "error:28\r\n"
            if p[0] < 0:
                return "error:4\r\n"
            self.queue.append(("dwell", p[0]))
            self.queue.append(("sync", None))
            self._advance(now)
            return None  # 'ok' after the queue drains and the dwell ends
        if not axes:
            return "ok\r\n"
        if 53 in g and not (0 in g or 1 in g):
            return "error:30\r\n"
        if 1 in g and not any(k == "F" for k, _ in words):
            return "error:22\r\n"
        base = self.queue[-1][1] if self.queue and self.queue[-1][0] == "move" else \
            (self._active[3] if self._active is not None else self.mpos)
        target = np.array(base, dtype=float)
        for i, axis in enumerate("XYZ"):
            if axis in axes:
                target[i] = target[i] + axes[axis] if 91 in g and 53 not in g else axes[axis]
        if self.settings[20] and any(not -self.settings[130 + i] <= target[i] <= 0.0 for i in range(3)):
            # system.c: a target outside [-max travel, 0] is a soft-limit critical alarm; the line
            # gets its 'ok' once a reset has ended the alarm
            self.queue.clear()
            self._active = None
            self.state = "Alarm"
            self.critical = True
            self._late_oks += 1
            return "ALARM:2\r\n[MSG:Reset to continue]\r\n"
        if self.take_fault("alarm"):
            self.hard_limit_next = True
        self.queue.append(("move", target))
        self._advance(now)
        return "ok\r\n"
