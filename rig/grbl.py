"""GRBL 1.1 (G-code over serial) and the light-stage positioner driver.

What a host sees from GRBL 1.1 (``gnea/grbl`` doc/markdown/interface.md):

- a welcome banner after power-up or soft reset: ``Grbl 1.1h ['$' for help]``;
- one response per line sent: ``ok`` (parsed and *queued*, not finished) or ``error:N``
  (:data:`ERROR_CODES`);
- push messages at any time: ``ALARM:N`` (:data:`ALARM_CODES`), ``[MSG:...]``, and feedback
  ``[VER:..]`` / ``[OPT:..]`` / ``$n=value`` in answer to ``$I`` / ``$$``;
- real-time commands, single bytes acted on at once without a line end: ``?`` status report
  ``<Idle|MPos:0.000,0.000,0.000|FS:0,0|WCO:...>``, ``!`` feed hold, ``~`` cycle start / resume,
  ``0x18`` (Ctrl-X) soft reset;
- ``$H`` runs the homing cycle (its ``ok`` comes when homing has finished), ``$X`` kills the
  alarm lock. With homing enabled (``$22=1``) GRBL starts in the ``Alarm`` state after power-up.

Completion of a move is found by polling ``?`` until the state is ``Idle`` at the target; a
move is queued with ``G53 G0`` so machine coordinates are used whatever the work offsets.

Measured on the real firmware (gnea/grbl 1.1h on the grbl-sim host harness,
``tests/rig/test_grbl_firmware.py``): a hard or soft limit (``ALARM:1`` / ``ALARM:2``) is
followed by ``[MSG:Reset to continue]`` and then silence, ``?`` included, until a soft reset
(interface.md: "Reset is required before Grbl accepts any other commands ... Only hard or soft
limit errors send this"); a failed homing (``ALARM:6..9``) and a reset in motion (``ALARM:3``)
are followed by GRBL's own reset (``ok`` of the line, banner); ``?`` is not answered during the
``$H`` cycle, and ``!`` is ignored there (limits.c polls only reset, door and cycle stop); after
``$H`` each homed axis stands at minus the pull-off ``$27`` (homing towards +, ``$23`` bit clear)
or at ``-$13x + $27`` (towards -): GRBL's machine space is [-``$13x``, 0].
"""
from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from .device import LightPositioner, LightTarget, reading
from .errors import DeviceBusy, DeviceError, DeviceTimeout, NotHomed, ProtocolError
from .kinematics import Kinematics, MachineMap, kinematics_from_config
from .motion import move_time_s
from .status import MoveStatus
from .transport import SerialDriver, SerialTransport

log = logging.getLogger("gonio.rig.grbl")

#: error:N -> meaning (GRBL 1.1 doc/csv/error_codes_en_US.csv)
ERROR_CODES: dict[int, str] = {
    1: "G-code words consist of a letter and a value; the letter was not found",
    2: "missing the expected G-code word value, or the number format is not valid",
    3: "'$' system command was not recognized or supported",
    4: "negative value received for an expected positive value",
    5: "homing cycle failure: homing is not enabled via settings ($22)",
    6: "minimum step pulse time must be greater than 3 us",
    7: "EEPROM read failed; the affected settings were restored to defaults",
    8: "'$' command cannot be used unless Grbl is idle",
    9: "G-code commands are locked out during alarm or jog state (home with $H or unlock with $X)",
    10: "soft limits cannot be enabled without homing also enabled",
    11: "max characters per line exceeded; the line was not executed",
    12: "'$' setting value would make the step rate exceed the maximum supported",
    13: "safety door detected as opened and door state initiated",
    14: "build info or startup line exceeded the EEPROM line length limit",
    15: "jog target exceeds machine travel; the jog was ignored",
    16: "jog command has no '=' or contains prohibited G-code",
    17: "laser mode requires PWM output",
    20: "unsupported or invalid G-code command found in block",
    21: "more than one G-code command from the same modal group found in block",
    22: "feed rate has not yet been set or is undefined",
    23: "G-code command in block requires an integer value",
    24: "more than one G-code command that requires axis words found in block",
    25: "repeated G-code word found in block",
    26: "no axis words found in block for a G-code command that requires them",
    27: "line number value is invalid",
    28: "G-code command is missing a required value word",
    29: "G59.x work coordinate systems are not supported",
    30: "G53 only allowed with G0 and G1 motion modes",
    31: "axis words found in block when no command or current modal state uses them",
    32: "G2 and G3 arcs require at least one in-plane axis word",
    33: "motion command target is invalid",
    34: "arc radius value is invalid",
    35: "G2 and G3 arcs require at least one in-plane offset word",
    36: "unused value words found in block",
    37: "G43.1 dynamic tool length offset is not assigned to the configured tool length axis",
    38: "tool number greater than max supported value",
}

#: ALARM:N -> meaning (GRBL 1.1 doc/csv/alarm_codes_en_US.csv)
ALARM_CODES: dict[int, str] = {
    1: "hard limit triggered; machine position is likely lost due to the sudden halt, re-homing is "
       "highly recommended",
    2: "soft limit: the G-code motion target exceeds machine travel; machine position retained, the "
       "alarm may be safely unlocked",
    3: "reset while in motion; machine position is likely lost, re-homing is highly recommended",
    4: "probe fail: the probe is not in the expected initial state before the probe cycle",
    5: "probe fail: the probe did not contact the workpiece within the programmed travel",
    6: "homing fail: the active homing cycle was reset",
    7: "homing fail: the safety door was opened during the homing cycle",
    8: "homing fail: pull-off travel failed to clear the limit switch",
    9: "homing fail: could not find the limit switch within the search distance",
}

#: alarms after which GRBL answers nothing (not even ``?``) until a soft reset (protocol.c: "Halt
#: everything upon a critical event flag. Currently hard and soft limits flag this.")
CRITICAL_ALARMS = frozenset({1, 2})
#: alarms GRBL follows with its own reset (the banner): a reset in motion, a failed homing
RESETTING_ALARMS = frozenset({3, 6, 7, 8, 9})
#: alarms after which the machine position is no longer trusted (re-home)
POSITION_LOST_ALARMS = frozenset({1, 3, 6, 7, 8, 9})

#: longest the port lock is held while waiting for a line, seconds: a reply awaited for long (the
#: ``ok`` of ``$H``) must not keep stop() from reading the reset's banner
READ_SLICE_S = 0.05

REALTIME_STATUS, FEED_HOLD, CYCLE_START, SOFT_RESET = b"?", b"!", b"~", b"\x18"
BANNER = re.compile(r"Grbl (\S+) \['\$' for help\]")

AXES = "XYZ"


class GrblAlarm(DeviceError):
    """GRBL entered its alarm state (``ALARM:N``); motion is locked out."""

    hint = "the driver has brought GRBL back to answering; after a hard limit or a failed homing, " \
           "re-home (positioner.home())"

    def __init__(self, alarm: int | None, *, device: str = "") -> None:
        self.alarm = alarm
        meaning = ALARM_CODES.get(alarm, "alarm state (code not seen)") if alarm else \
            "the machine is in the alarm state (locked)"
        super().__init__(f"ALARM:{alarm}" if alarm else "ALARM", meaning, device=device)


# ---------------------------------------------------------------------------------------------
# codec
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GrblStatus:
    """One real-time status report ``<State|MPos:..|FS:..|...>``.

    Attributes
    ----------
    state : str
        ``Idle``, ``Run``, ``Hold``, ``Jog``, ``Alarm``, ``Door``, ``Check``, ``Home``, ``Sleep``.
    substate : int or None
        ``Hold:0`` complete / ``Hold:1`` in progress; ``Door:n``.
    mpos, wpos, wco : tuple of float or None
        Machine position, work position, work coordinate offset (machine units). GRBL sends MPos
        or WPos (``$10``); WCO only now and then, so the driver keeps the last one.
    feed, spindle : float or None
        From ``FS:`` (or ``F:``).
    fields : dict
        Every field as text, e.g. ``{"Bf": "15,128", "Pn": "XY"}``.
    """

    state: str
    substate: int | None = None
    mpos: tuple[float, ...] | None = None
    wpos: tuple[float, ...] | None = None
    wco: tuple[float, ...] | None = None
    feed: float | None = None
    spindle: float | None = None
    fields: dict[str, str] = field(default_factory=dict)

    def machine_position(self, wco: tuple[float, ...] | None = None) -> tuple[float, ...]:
        """MPos, derived from WPos + WCO when the report carries WPos only."""
        if self.mpos is not None:
            return self.mpos
        offset = self.wco or wco
        if self.wpos is None or offset is None:
            raise ProtocolError("status report has neither MPos nor WPos with a known WCO")
        return tuple(w + o for w, o in zip(self.wpos, offset))


STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")


def _floats(text: str, raw: str, count: int) -> tuple[float, ...]:
    """``count`` comma-separated numbers; a garbled byte ('-1,000' for '-1.000', '0.0' for
    '0,0') changes the count or a number, and is a ``ProtocolError`` (retried by a poll)."""
    try:
        out = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ProtocolError("bad number list in status report", raw=raw.encode()) from None
    if len(out) != count:
        raise ProtocolError(f"{len(out)} numbers in {text!r} where the status report has {count}",
                            raw=raw.encode())
    return out


def parse_status(line: str | bytes) -> GrblStatus:
    """Parse ``<Idle|MPos:1.000,2.000,0.000|FS:0,0>`` (raises ``ProtocolError`` if malformed)."""
    text = line.decode("ascii", "replace") if isinstance(line, bytes) else line
    text = text.strip()
    if not (text.startswith("<") and text.endswith(">")):
        raise ProtocolError("not a status report", raw=text.encode())
    parts = text[1:-1].split("|")
    state, _, sub = parts[0].partition(":")
    if state not in STATES:
        raise ProtocolError(f"unknown machine state {state!r}", raw=text.encode())
    fields = {}
    for part in parts[1:]:
        key, sep, value = part.partition(":")
        if not sep:
            raise ProtocolError(f"bad status field {part!r}", raw=text.encode())
        fields[key] = value
    feed = spindle = None
    if "FS" in fields:
        feed, spindle = _floats(fields["FS"], text, 2)
    elif "F" in fields:
        feed, = _floats(fields["F"], text, 1)
    axes = len(AXES)
    return GrblStatus(
        state=state, substate=int(sub) if sub.isdigit() else None,
        mpos=_floats(fields["MPos"], text, axes) if "MPos" in fields else None,
        wpos=_floats(fields["WPos"], text, axes) if "WPos" in fields else None,
        wco=_floats(fields["WCO"], text, axes) if "WCO" in fields else None,
        feed=feed, spindle=spindle, fields=fields)


def parse_code(line: str, prefix: str) -> int | None:
    """``error:9`` -> 9 for ``prefix="error"``; None if the line is not of that kind."""
    if not line.startswith(prefix + ":"):
        return None
    try:
        return int(line[len(prefix) + 1:])
    except ValueError:
        raise ProtocolError(f"bad {prefix} code", raw=line.encode()) from None


def parse_settings(lines: list[str]) -> dict[int, float]:
    """``$$`` output lines (``$110=500.000``) -> {110: 500.0}."""
    out = {}
    for line in lines:
        m = re.fullmatch(r"\$(\d+)=(-?[\d.]+)", line.strip())
        if m:
            out[int(m.group(1))] = float(m.group(2))
    return out


def format_move(machine: dict[str, float], *, rapid: bool = True, feed_mm_min: float | None = None) -> bytes:
    """A machine-coordinate move line: ``G53 G0 X12.500 Y30.000\\n`` (or ``G53 G1 ... F..``)."""
    if not machine:
        raise ValueError("a move needs at least one axis")
    words = ["G53", "G0" if rapid else "G1"]
    for axis in AXES:
        if axis in machine:
            value = float(machine[axis])
            if not math.isfinite(value):
                raise ValueError(f"axis {axis} target must be finite, got {value}")
            words.append(f"{axis}{value:.3f}")
    if not rapid:
        if feed_mm_min is None or feed_mm_min <= 0:
            raise ValueError("a G1 move needs a feed rate > 0")
        words.append(f"F{feed_mm_min:.1f}")
    return (" ".join(words) + "\n").encode("ascii")


def path_time_s(start: tuple[float, ...], end: tuple[float, ...], rate: tuple[float, ...],
                accel: tuple[float, ...]) -> float:
    """Duration of a straight G0 move, seconds, as GRBL plans it: the speed and acceleration along
    the path are limited so that no axis exceeds its own max rate (units/min) or accel (units/s^2).
    """
    delta = [e - s for s, e in zip(start, end)]
    length = math.sqrt(sum(d * d for d in delta))
    if length == 0:
        return 0.0
    v = min(r / 60.0 * length / abs(d) for d, r in zip(delta, rate) if d)
    a = min(ac * length / abs(d) for d, ac in zip(delta, accel) if d)
    return move_time_s(length, v, a)


# ---------------------------------------------------------------------------------------------
# driver
# ---------------------------------------------------------------------------------------------
class GrblPositioner(SerialDriver, LightPositioner):
    """The light-stage positioner on a GRBL 1.1 controller.

    Plans speak :class:`LightTarget` in the world frame; the configured kinematics
    (:mod:`rig.kinematics`) turns a target into axis coordinates (raising ``LimitError`` at once
    if it is out of reach), and the machine map (``machine_offset``, ``machine_sign``) places
    those in GRBL's machine space (``MPos``); a read-back ``MPos`` goes the other way into
    :attr:`light_position_mm`. At :meth:`connect`, with homing enabled, the driver refuses a
    configuration whose axis travel does not lie inside GRBL's machine space (``$130``-``$132``,
    ``$23``, ``$27``; :func:`check_machine_space`).

    ``homed`` (GRBL has no such report) is True when homing is disabled (``$22=0``); when the
    controller was idle, not alarm-locked, at :meth:`connect` (with homing enabled GRBL powers up
    locked, so it has been homed -- or deliberately unlocked with ``$X`` -- since power-up); or
    after this driver's ``$H``. An alarm that loses the position (hard limit, reset in motion,
    failed homing) clears it; :meth:`unlock` does not set it.

    Alarms are recovered by the driver: after a critical alarm (hard or soft limit, silent until
    reset) it soft-resets at once, and after a soft limit (position kept) also unlocks; after
    GRBL's own reset (failed homing) it waits for the banner. The call that met the alarm raises
    :class:`GrblAlarm`; the next one finds GRBL answering. The real-time bytes (``!``, ``~``,
    ``0x18``) go out at once without the port lock, so :meth:`stop` reaches the wire whatever
    else the driver is doing, a homing cycle included.

    Parameters
    ----------
    name : str
        Role in the rig.
    port : str
        Serial port; or ``transport`` for a ready transport (protocol tests).
    kinematics : Kinematics, str or dict
        ``"arm"``, ``"gantry"``, a parameter table, or an instance.
    machine_offset, machine_sign : dict of axis letter -> number, optional
        The machine map (:class:`~rig.kinematics.MachineMap`): ``MPos = offset + sign * axis``.
    baudrate : int
        GRBL's default is 115200.
    timeout_s : float
        Reply timeout per request, seconds.
    poll_interval_s : float
        Status poll period during a move, seconds (GRBL recommends at most 5-10 Hz for a GUI;
        a driver waiting for one move may poll faster).
    poll_retries : int
        Consecutive garbled or unanswered status reports tolerated during a move.
    position_tolerance : float
        How close (machine units) the read-back must be to the target to count as arrived.
    home_timeout_s : float, optional
        Longest wait for the homing cycle, seconds (default: from ``$130``-``$132`` and ``$25``).
    park : dict, optional
        A light target (``{azimuth_deg = 0, elevation_deg = 0}``) the light moves to after each
        homing: the home switches sit at an end of the travel, often not where a lamp is useful.
    """

    def __init__(self, name: str = "positioner", port: str | None = None, *, transport: Any = None,
                 kinematics: Kinematics | str | dict = "arm", machine_offset: dict | None = None,
                 machine_sign: dict | None = None, baudrate: int = 115200, timeout_s: float = 1.0,
                 poll_interval_s: float = 0.02, poll_retries: int = 2,
                 position_tolerance: float = 0.01, home_timeout_s: float | None = None,
                 park: dict | None = None) -> None:
        super().__init__(name)
        if transport is None and not port:
            raise ValueError(f"{name}: give a serial port or a transport")
        self.port = port or getattr(transport, "port", "")
        self.transport = transport or SerialTransport(port, baudrate, timeout_s=timeout_s, device=name)
        self.kinematics = kinematics_from_config(kinematics, device=name)
        try:
            self.machine_map = MachineMap.from_config(machine_offset, machine_sign)
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from None
        self.timeout_s = timeout_s
        self.poll_interval_s = poll_interval_s
        self.poll_retries = poll_retries
        self.position_tolerance = position_tolerance
        self.home_timeout_s = home_timeout_s
        try:
            self.park = None if park is None else LightTarget(**park)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name}: park = {park!r}: {exc}") from None
        self.settings: dict[int, float] = {}
        self.version = ""
        self.build = ""
        self.options = ""
        # [MSG:...] pushes, newest last; bounded so a long session does not grow it forever
        self.messages: deque[str] = deque(maxlen=100)
        self.last_alarm: int | None = None
        self._homed = False
        self._homing = False  # a $H cycle is running: GRBL answers no '?' and ignores '!'
        self._wco: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._connected = False
        self._banner_version = ""
        self._banners = 0  # banners seen (each one is a reset): the reset waiters count them
        self._reset_requested = False  # '[MSG:Reset to continue]' came after the last alarm
        self._alarms = 0  # ALARM lines seen: a waiter notices one another thread read
        self._alarm_mark = 0  # _banners when the last ALARM line arrived
        self._inbox: deque[str] = deque()  # replies a status poll read for a waiting send()
        self._send_lock = threading.RLock()  # one line awaits its 'ok' at a time

    @classmethod
    def from_config(cls, name: str, section: dict[str, Any], **context: Any) -> "GrblPositioner":
        """Build from a rig-file section: ``port``, ``kinematics`` (``"arm"``, ``"gantry"`` or
        an inline table), optional ``machine_offset`` / ``machine_sign`` tables, ``baudrate``,
        ``timeout_s``, ``poll_interval_s``, ``poll_retries``, ``position_tolerance``,
        ``home_timeout_s``, ``park``."""
        from .rig import ConfigError, driver_options
        allowed = {"kinematics", "machine_offset", "machine_sign", "baudrate", "timeout_s",
                   "poll_interval_s", "poll_retries", "position_tolerance", "home_timeout_s", "park"}
        options = driver_options(name, section, "grbl", allowed)
        try:
            return cls(name, section["port"], **options)
        except ValueError as exc:
            raise ConfigError(f"[{name}] {str(exc).removeprefix(name + ': ')}") from None

    # -- wire -------------------------------------------------------------------------------------
    def _read_line(self, timeout: float) -> str:
        """One line from the port (port lock held by the caller), pushes recorded: ALARM, MSG,
        the banner (counted: it marks a reset, and what came before it is stale)."""
        raw = self.transport.read_until(b"\n", timeout)
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise ProtocolError("non-ASCII reply", device=self.name, raw=raw) from None
        if line.startswith("ALARM:"):
            self.last_alarm = parse_code(line, "ALARM")
            self._reset_requested = False
            self._alarms += 1
            self._alarm_mark = self._banners
            if self.last_alarm in POSITION_LOST_ALARMS:
                self._homed = not self.homing_enabled
        elif line.startswith("[MSG:"):
            self.messages.append(line[5:-1])
            self._reset_requested |= line == "[MSG:Reset to continue]"
        elif (m := BANNER.search(line)):
            self._banner_version = m.group(1)
            self._banners += 1
            self._inbox.clear()
        return line

    def _wait_line(self, deadline: float, what: str, timeout: float, alarms: int) -> str:
        """The next non-empty line for a send(): set aside by a status poll, or from the port,
        holding the port lock at most :data:`READ_SLICE_S` at a time. Raises ``GrblAlarm`` if
        another thread read an alarm since ``alarms`` (:attr:`_alarms` when the line was sent)."""
        t = self.transport
        while True:
            if self._alarms != alarms:
                raise GrblAlarm(self.last_alarm, device=self.name)  # that thread recovers
            with t.lock:
                if self._inbox:
                    return self._inbox.popleft()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(f"no reply to {what}", device=self.name, timeout_s=timeout)
                try:
                    line = self._read_line(min(remaining, READ_SLICE_S))
                except DeviceTimeout:
                    line = ""
                if line:
                    return line
            time.sleep(0)  # let a waiting stop() take the lock

    def _await(self, done: Callable[[], bool], what: str, timeout: float) -> None:
        """Read (and drop) lines until ``done()``; the port lock is held one slice at a time."""
        deadline = time.monotonic() + timeout
        while not done():
            with self.transport.lock:
                if done():
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(f"no {what}", device=self.name, timeout_s=timeout)
                try:
                    self._read_line(min(remaining, READ_SLICE_S))
                except DeviceTimeout:
                    pass
            time.sleep(0)

    def _await_banner(self, mark: int, what: str) -> str:
        """Wait for a banner newer than ``mark`` (a reset's end); GRBL's version."""
        timeout = 2.0 * self.timeout_s + 1.0  # the board may still be printing its boot lines
        self._await(lambda: self._banners > mark, f"banner after {what}", timeout)
        return self._banner_version

    def _recover(self, code: int | None) -> GrblAlarm:
        """Bring GRBL back to answering after ``ALARM:code``; the error for the caller to raise."""
        if code in CRITICAL_ALARMS:
            # protocol.c prints the alarm and the message, then drops any pending reset ("Disable
            # any existing reset") before it waits for one: a reset sent on the alarm line alone
            # was lost on the real firmware. Wait for the message, and repeat an unanswered reset.
            try:
                self._await(lambda: self._reset_requested, "'[MSG:Reset to continue]'", self.timeout_s)
            except DeviceTimeout:
                pass  # the message was lost or garbled: reset anyway
            for attempt in range(3):
                mark = self._banners
                self.transport.write(SOFT_RESET)
                try:
                    self._await(lambda: self._banners > mark, "banner after a soft reset", self.timeout_s)
                    break
                except DeviceTimeout:
                    if attempt == 2:
                        raise
            if code == 2 and self._homed:
                self.send("$X")  # soft limit: position retained, "the alarm may be safely unlocked"
        elif code in RESETTING_ALARMS:
            self._await_banner(self._alarm_mark, f"ALARM:{code}")  # GRBL resets itself
        return GrblAlarm(code, device=self.name)

    def send(self, line: str, *, timeout_s: float | None = None) -> list[str]:
        """Send one line and wait for its ``ok``; return the lines that came before it.

        The port lock is held only in short slices while waiting, so :meth:`stop` and status
        polls get through during a long wait (``$H``, ``G4``).

        Raises
        ------
        DeviceError
            On ``error:N``, with GRBL's meaning of N.
        GrblAlarm
            If an ``ALARM:N`` arrives instead of the response (GRBL recovered first).
        """
        if any(c in line for c in "\r\n?!~\x18"):
            raise ValueError(f"{line!r} contains a line end or a real-time character")
        timeout = self.timeout_s if timeout_s is None else timeout_s
        t = self.transport
        with self._send_lock:
            with t.lock:
                self._inbox.clear()  # nothing is awaited: whatever is there belongs to nobody
                alarms = self._alarms
                t.write(line.encode("ascii") + b"\n")
            deadline = time.monotonic() + timeout
            lines = []
            while True:
                text = self._wait_line(deadline, repr(line), timeout, alarms)
                if text == "ok":
                    return lines
                if (code := parse_code(text, "error")) is not None:
                    raise DeviceError(f"error:{code}", f"{line!r}: {ERROR_CODES.get(code, 'unknown error')}",
                                      device=self.name)
                if text.startswith("ALARM:"):
                    raise self._recover(self.last_alarm)
                if text.startswith("<") or BANNER.search(text):
                    continue  # a late status report or a boot banner belongs to nobody
                if not text.startswith(("[", "$")):
                    t.reset_input()
                    raise ProtocolError(f"unexpected reply to {line!r}", device=self.name, raw=text.encode())
                if not text.startswith("[MSG:"):
                    lines.append(text)

    def status(self) -> GrblStatus:
        """Send ``?`` and return the status report (pushes on the way are recorded; replies to a
        line in flight are kept for its send()).

        Raises
        ------
        DeviceBusy
            During the homing cycle, when GRBL does not answer ``?``.
        GrblAlarm
            If an ``ALARM:N`` arrives first (GRBL recovered first).
        """
        if self._homing:
            raise DeviceBusy("homing cycle running; GRBL answers no status report until it ends",
                             device=self.name)
        t = self.transport
        with t.lock:
            t.write(REALTIME_STATUS)
            deadline = time.monotonic() + self.timeout_s
            while True:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout("no reply to '?'", device=self.name, timeout_s=self.timeout_s)
                text = self._read_line(remaining)
                if text.startswith("<"):
                    try:
                        st = parse_status(text)
                    except ProtocolError as exc:
                        t.reset_input()
                        raise ProtocolError(exc.message, device=self.name, raw=exc.raw) from None
                    if st.wco is not None:
                        self._wco = st.wco
                    return st
                if text.startswith("ALARM:"):
                    break  # recovered outside the port lock: a waiting send() must see the alarm
                if text == "ok" or text.startswith(("error:", "$")) or \
                        (text.startswith("[") and not text.startswith("[MSG:")):
                    self._inbox.append(text)  # the reply to a line a send() is waiting for
                elif text and not (text.startswith("[MSG:") or BANNER.search(text)):
                    t.reset_input()  # noise may have split the report: drop the rest of it
                    raise ProtocolError("garbled line while waiting for a status report",
                                        device=self.name, raw=text.encode())
        raise self._recover(self.last_alarm)

    def soft_reset(self) -> str:
        """Ctrl-X, at once (without the port lock): abort motion, flush buffers; wait for the
        banner and return GRBL's version."""
        mark = self._banners
        self.transport.write(SOFT_RESET)
        return self._await_banner(mark, "soft reset")

    def feed_hold(self) -> None:
        """``!``, at once: decelerate and pause the running motion (resume with :meth:`resume`)."""
        self.transport.write(FEED_HOLD)

    def resume(self) -> None:
        """``~``, at once: cycle start / resume after a feed hold."""
        self.transport.write(CYCLE_START)

    def sync(self, timeout_s: float = 60.0) -> None:
        """Block until every queued motion has finished: ``G4 P0`` is answered only once the
        planner is empty (GRBL's documented way to synchronise with motion)."""
        self.send("G4 P0", timeout_s=timeout_s)

    def unlock(self) -> None:
        """``$X``: kill the alarm lock without homing (the position may be wrong)."""
        self.send("$X")

    # -- link -------------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port, soft-reset to a known state, read build info and settings, and check
        that the configured travel lies in GRBL's machine space (:func:`check_machine_space`)."""
        self.close()
        self.transport.open()
        try:
            self.transport.reset_input()
            self._inbox.clear()
            self._homing = False
            self.version = self.soft_reset()
            for line in self.send("$I"):
                if line.startswith("[VER:"):  # [VER:1.1h.20190825:<optional build string>]
                    self.build = line[5:-1].partition(":")[0]
                elif line.startswith("[OPT:"):
                    self.options = line[5:-1]
            self.settings = parse_settings(self.send("$$"))
            missing = [n for n in (22, 110, 111, 120, 121) if n not in self.settings]
            if missing:
                raise ProtocolError(f"$$ did not report settings {missing}", device=self.name)
            check_machine_space(self.settings, self.kinematics, self.machine_map, device=self.name)
            state = self._poll(self.status).state
        except BaseException:
            self.transport.close()
            raise
        # GRBL does not report "homed": with homing enabled it powers up locked in Alarm, so an
        # Idle controller has been homed (or deliberately unlocked) since power-up
        self._homed = not self.homing_enabled or state != "Alarm"
        self._connected = True
        log.info("%s: Grbl %s, state %s", self.name, self.version, state)

    # -- state ------------------------------------------------------------------------------------
    @property
    def homing_enabled(self) -> bool:
        return bool(self.settings.get(22, 0))

    @property
    def homed(self) -> bool:
        return self._homed

    def machine_position(self) -> dict[str, float]:
        """Machine coordinates (``MPos``) by axis letter, machine units."""
        self._require()
        mpos = self._poll(self.status).machine_position(self._wco)
        return dict(zip(AXES, mpos))

    def _light(self, machine: dict[str, float]) -> tuple[float, float, float]:
        return self.kinematics.forward(self.machine_map.to_axes(machine))

    @property
    def light_position_mm(self) -> tuple[float, float, float]:
        return self._light(self.machine_position())

    def _rates(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        rate = tuple(self.settings.get(110 + i, 0.0) for i in range(3))
        accel = tuple(self.settings.get(120 + i, 0.0) for i in range(3))
        return rate, accel

    def _timeout_for(self, start: dict[str, float], end: dict[str, float]) -> float:
        axes = [a for a in AXES if a in end]
        rate, accel = self._rates()
        idx = [AXES.index(a) for a in axes]
        return 1.5 * path_time_s(tuple(start[a] for a in axes), tuple(end[a] for a in axes),
                                 tuple(rate[i] for i in idx), tuple(accel[i] for i in idx)) + 1.0

    # -- motion -----------------------------------------------------------------------------------
    def _check_ready(self, st: GrblStatus) -> None:
        if st.state == "Alarm":
            if self.last_alarm is None and self.homing_enabled and not self._homed:
                raise NotHomed("GRBL is locked in the alarm state; home it first", device=self.name)
            raise GrblAlarm(self.last_alarm, device=self.name)
        if self.homing_enabled and not self._homed:
            raise NotHomed("the machine has not been homed by this driver", device=self.name)

    def move_to(self, target: LightTarget) -> MoveStatus:
        """Queue a rapid move that puts the light on ``target`` and return at once.

        Raises ``LimitError`` (from the kinematics) or ``NotHomed`` / ``GrblAlarm`` /
        ``DeviceError`` before anything moves. The status completes with the light position
        (world frame, mm) when GRBL is idle at the target, or fails with the alarm, a timeout
        computed from the travel and GRBL's max rates and accelerations, or an interruption.
        """
        self._require()
        if not isinstance(target, LightTarget):
            raise TypeError(f"{self.name}: move_to takes a LightTarget, got {type(target).__name__}")
        end = self.machine_map.to_machine(self.kinematics.inverse(target))
        st = self._poll(self.status)
        self._check_ready(st)
        start = dict(zip(AXES, st.machine_position(self._wco)))
        self.send(format_move(end).decode("ascii").strip())
        timeout = self._timeout_for(start, end)
        return MoveStatus.run(lambda: self._wait_arrived(end, timeout), target=target,
                              device=self.name, name="move")

    def _wait_arrived(self, end: dict[str, float], timeout: float) -> tuple[float, float, float]:
        """Poll until idle at ``end``. ``timeout`` (s) is the planned time with a margin; it is
        extended while the position keeps changing (a rapid override ``Ov:`` below 100 %, or a
        controller slower than planned), so only a stalled move times out."""
        deadline = time.monotonic() + timeout
        moved = False
        grace = time.monotonic() + 0.25  # GRBL may report Idle for a moment before the block starts
        last = None
        while True:
            st = self._poll(self.status)
            if st.state == "Run" and st.mpos != last:
                deadline = max(deadline, time.monotonic() + max(1.0, self.timeout_s))
            last = st.mpos
            if st.state == "Alarm":
                raise GrblAlarm(self.last_alarm, device=self.name)
            if st.state == "Idle":
                here = dict(zip(AXES, st.machine_position(self._wco)))
                miss = max(abs(here[a] - v) for a, v in end.items())
                if miss <= self.position_tolerance:
                    return self._light(here)
                if moved or time.monotonic() > grace:
                    raise DeviceError("stopped", f"motion ended {miss:.3f} units from the target "
                                      f"(stopped or flushed by a reset)", device=self.name)
            else:
                moved = True
            if time.monotonic() > deadline:
                self.stop()
                raise DeviceTimeout(f"move did not finish (state {st.state})", device=self.name,
                                    timeout_s=timeout)
            time.sleep(self.poll_interval_s)

    def home(self) -> MoveStatus:
        """Run the homing cycle ``$H``; the status completes with the light position there.

        ``$H`` is written before this returns, so a :meth:`stop` right after it soft-resets the
        cycle; the wait for its ``ok`` does not hold the port. After ``ALARM:9`` (no switch found
        within the search distance) the driver waits for GRBL's own reset and homes once more;
        a failed homing otherwise (``ALARM:6..9``) fails the status with :class:`GrblAlarm` once
        GRBL's reset is over.
        """
        self._require()
        if not self.homing_enabled:
            raise DeviceError("error:5", ERROR_CODES[5], device=self.name)
        travel = [self.settings.get(130 + i, 500.0) for i in range(3)]
        seek = self.settings.get(25, 500.0) / 60.0  # $25 homing seek rate, units/min -> /s
        # GRBL answers nothing during the cycle, so only a fixed bound: a search of 1.5 x travel
        # per cycle (Z, then X and Y), with a margin
        timeout = self.home_timeout_s or 2.0 * 1.5 * max(travel) / max(seek, 1e-6) + 5.0
        try:
            self._poll(self.status)  # reads (and recovers from) any alarm pushed since the last call
        except GrblAlarm:
            pass
        self.last_alarm = None
        self._homing = True
        try:
            with self.transport.lock:
                alarms = self._alarms
                self.transport.write(b"$H\n")
        except BaseException:
            self._homing = False
            raise

        def _wait() -> tuple[float, float, float]:
            nonlocal alarms
            try:
                try:
                    self._await_ok("'$H'", timeout, alarms)
                except GrblAlarm as exc:
                    if exc.alarm != 9:
                        raise
                    # no switch within 1.5 x $13x: GRBL has reset itself; a second search goes on
                    # from where the first one ended (a machine powered up far from its switches)
                    log.warning("%s: homing found no limit switch (ALARM:9); searching again", self.name)
                    with self.transport.lock:
                        alarms = self._alarms
                        self.transport.write(b"$H\n")
                    self._await_ok("'$H'", timeout, alarms)
            finally:
                self._homing = False
            self._homed = True
            if self.park is not None:
                return self.move_to(self.park).wait(60.0)
            return self.light_position_mm

        return MoveStatus.run(_wait, target="home", device=self.name, name="home")

    def _await_ok(self, what: str, timeout: float, alarms: int) -> None:
        """Wait for the ``ok`` of a line already written (``$H``) when :attr:`_alarms` was
        ``alarms``; recover from an alarm."""
        deadline = time.monotonic() + timeout
        with self._send_lock:
            while True:
                text = self._wait_line(deadline, what, timeout, alarms)
                if text == "ok":
                    return
                if text.startswith("ALARM:"):
                    raise self._recover(self.last_alarm)
                if (code := parse_code(text, "error")) is not None:
                    raise DeviceError(f"error:{code}", f"{what}: {ERROR_CODES.get(code, 'unknown error')}",
                                      device=self.name)

    def stop(self) -> None:
        """Stop now. During a move: feed hold (at once), wait for the hold to complete, then a
        soft reset to flush the planner (a reset after the hold keeps the position). During
        homing, where GRBL ignores the feed hold: a soft reset at once (the position is lost;
        ``ALARM:6``, re-home)."""
        self._require()
        if self._homing:
            self.soft_reset()
            return
        self.feed_hold()
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            try:
                st = self.status()
            except (DeviceBusy, GrblAlarm):  # a homing cycle began, or an alarm halted the motion
                break
            except (ProtocolError, DeviceTimeout):  # noise must not keep the reset from going out
                continue
            if st.state in ("Idle", "Alarm") or (st.state == "Hold" and st.substate == 0):
                break
            time.sleep(self.poll_interval_s)
        self.soft_reset()

    # -- description ------------------------------------------------------------------------------
    def read(self) -> dict[str, dict[str, Any]]:
        self._require()
        st = self._poll(self.status)
        mpos = dict(zip(AXES, st.machine_position(self._wco)))
        return {
            "light_position": reading(self._light(mpos), "mm"),
            "machine_position": reading(mpos, "deg" if self.kinematics.kind == "arm" else "mm"),
            "state": reading(st.state if st.substate is None else f"{st.state}:{st.substate}"),
            "homed": reading(self._homed),
        }

    def describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {"driver": "grbl", "port": self.port, "units": "mm",
                               "kinematics": self.kinematics.to_config(),
                               **self.machine_map.to_config(),
                               "axis_limits": self.kinematics.limits()}
        if self.version:
            out.update({"model": f"GRBL {self.kinematics.kind} positioner", "firmware": f"Grbl {self.version}",
                        "build": self.build, "serial": "", "options": self.options,
                        "homing_enabled": self.homing_enabled})
        return out


def machine_space(settings: dict[int, float], axis: str) -> tuple[float, float]:
    """Where GRBL (without ``HOMING_FORCE_SET_ORIGIN``) lets axis ``axis`` go after homing,
    machine units: [-``$13x``, -``$27``] homing towards + (``$23`` bit clear: the switch is at 0,
    the pull-off clears it), [-``$13x`` + ``$27``, 0] homing towards -."""
    i = AXES.index(axis)
    travel, pull_off = settings.get(130 + i, 0.0), settings.get(27, 0.0)
    if int(settings.get(23, 0)) & (1 << i):
        return (-travel + pull_off, 0.0)
    return (-travel, 0.0 - pull_off)  # 0.0 - : no '-0' in messages


def check_machine_space(settings: dict[int, float], kinematics: Kinematics, machine_map: MachineMap, *,
                        device: str = "positioner") -> None:
    """Refuse a configuration whose axis travel, placed by the machine map, leaves GRBL's machine
    space (:func:`machine_space`): such targets are soft-limit alarms with ``$20=1`` and run
    through the home switch with hard limits on. Only with homing enabled (``$22=1``): without
    homing GRBL has no machine space.

    Raises
    ------
    rig.rig.ConfigError
        Naming each axis, the settings involved and what to change.
    """
    if not int(settings.get(22, 0)):
        return
    problems = []
    for axis, (lo, hi) in kinematics.limits().items():
        mlo, mhi = machine_map.machine_range(axis, lo, hi)
        slo, shi = machine_space(settings, axis)
        if slo - 1e-6 <= mlo and mhi <= shi + 1e-6:
            continue
        i = AXES.index(axis)
        direction = "-" if int(settings.get(23, 0)) & (1 << i) else "+"
        sign = machine_map.sign.get(axis, 1)
        offset = machine_map.offset.get(axis, 0.0)
        advice = f"change $13{i} or the axis limits"
        if mhi - mlo <= shi - slo:
            centred = (slo + shi) / 2 - sign * (lo + hi) / 2
            advice = f"set machine_offset {axis} = {centred:g} (centred), or change $13{i}"
        problems.append(
            f"axis {axis} travel {lo:g}..{hi:g} maps to machine {mlo:g}..{mhi:g} "
            f"(machine_offset {axis} = {offset:g}, machine_sign {axis} = {sign:+d}), outside GRBL's "
            f"machine space {slo:g}..{shi:g} after homing towards {direction} "
            f"($13{i}={settings.get(130 + i, 0.0):g}, $27={settings.get(27, 0.0):g}, "
            f"$23={int(settings.get(23, 0))}): {advice}")
    if problems:
        from .rig import ConfigError
        raise ConfigError(f"[{device}] " + "; ".join(problems))
