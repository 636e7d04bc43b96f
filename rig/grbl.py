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
"""
from __future__ import annotations

import logging
import math
import re
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from .device import LightPositioner, LightTarget, reading
from .errors import DeviceError, DeviceTimeout, NotHomed, ProtocolError
from .kinematics import Kinematics, kinematics_from_config
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

#: alarms after which GRBL only answers a soft reset, and the position is lost
CRITICAL_ALARMS = frozenset({1, 3})

REALTIME_STATUS, FEED_HOLD, CYCLE_START, SOFT_RESET = b"?", b"!", b"~", b"\x18"
BANNER = re.compile(r"Grbl (\S+) \['\$' for help\]")

AXES = "XYZ"


class GrblAlarm(DeviceError):
    """GRBL entered its alarm state (``ALARM:N``); motion is locked out."""

    hint = "re-home (positioner.home(), which soft-resets first when needed)"

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


def _floats(text: str, raw: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ProtocolError("bad number list in status report", raw=raw.encode()) from None


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
        feed, spindle = _floats(fields["FS"], text)[:2]
    elif "F" in fields:
        feed = _floats(fields["F"], text)[0]
    return GrblStatus(
        state=state, substate=int(sub) if sub.isdigit() else None,
        mpos=_floats(fields["MPos"], text) if "MPos" in fields else None,
        wpos=_floats(fields["WPos"], text) if "WPos" in fields else None,
        wco=_floats(fields["WCO"], text) if "WCO" in fields else None,
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
    (:mod:`rig.kinematics`) turns a target into machine coordinates (raising ``LimitError`` at
    once if it is out of reach) and a read-back ``MPos`` into :attr:`light_position_mm`.

    ``homed`` (GRBL has no such report) is True when homing is disabled (``$22=0``); when the
    controller was idle, not alarm-locked, at :meth:`connect` (with homing enabled GRBL powers up
    locked, so it has been homed -- or deliberately unlocked with ``$X`` -- since power-up); or
    after this driver's ``$H``. An alarm that loses the position (hard limit, reset in motion)
    clears it; :meth:`unlock` does not set it.

    Parameters
    ----------
    name : str
        Role in the rig.
    port : str
        Serial port; or ``transport`` for a ready transport (protocol tests).
    kinematics : Kinematics, str or dict
        ``"arm"``, ``"gantry"``, a parameter table, or an instance.
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
    """

    def __init__(self, name: str = "positioner", port: str | None = None, *, transport: Any = None,
                 kinematics: Kinematics | str | dict = "arm", baudrate: int = 115200,
                 timeout_s: float = 1.0, poll_interval_s: float = 0.02, poll_retries: int = 2,
                 position_tolerance: float = 0.01) -> None:
        super().__init__(name)
        if transport is None and not port:
            raise ValueError(f"{name}: give a serial port or a transport")
        self.port = port or getattr(transport, "port", "")
        self.transport = transport or SerialTransport(port, baudrate, timeout_s=timeout_s, device=name)
        self.kinematics = kinematics_from_config(kinematics, device=name)
        self.timeout_s = timeout_s
        self.poll_interval_s = poll_interval_s
        self.poll_retries = poll_retries
        self.position_tolerance = position_tolerance
        self.settings: dict[int, float] = {}
        self.version = ""
        self.build = ""
        self.options = ""
        # [MSG:...] pushes, newest last; bounded so a long session does not grow it forever
        self.messages: deque[str] = deque(maxlen=100)
        self.last_alarm: int | None = None
        self._homed = False
        self._wco: tuple[float, ...] = (0.0, 0.0, 0.0)
        self._connected = False

    @classmethod
    def from_config(cls, name: str, section: dict[str, Any], **context: Any) -> "GrblPositioner":
        """Build from a rig-file section: ``port``, ``kinematics`` (``"arm"``, ``"gantry"`` or
        an inline table), optional ``baudrate``, ``timeout_s``, ``poll_interval_s``."""
        from .rig import driver_options
        allowed = {"kinematics", "baudrate", "timeout_s", "poll_interval_s", "poll_retries",
                   "position_tolerance"}
        return cls(name, section["port"], **driver_options(name, section, "grbl", allowed))

    # -- wire -------------------------------------------------------------------------------------
    def _readline(self, deadline: float, what: str, timeout: float) -> str:
        """Next non-empty line before ``deadline``; pushes (ALARM, MSG) are recorded and returned
        too. ``timeout`` (s) is only for the error message."""
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(f"no reply to {what}", device=self.name, timeout_s=timeout)
            raw = self.transport.read_until(b"\n", remaining)
            try:
                line = raw.decode("ascii").strip()
            except UnicodeDecodeError:
                raise ProtocolError(f"non-ASCII reply to {what}", device=self.name, raw=raw) from None
            if not line:
                continue
            if line.startswith("ALARM:"):
                self.last_alarm = parse_code(line, "ALARM")
                if self.last_alarm in CRITICAL_ALARMS:
                    self._homed = False
            elif line.startswith("[MSG:"):
                self.messages.append(line[5:-1])
            return line

    def send(self, line: str, *, timeout_s: float | None = None) -> list[str]:
        """Send one line and wait for its ``ok``; return the lines that came before it.

        Raises
        ------
        DeviceError
            On ``error:N``, with GRBL's meaning of N.
        GrblAlarm
            If an ``ALARM:N`` arrives instead of the response.
        """
        if any(c in line for c in "\r\n?!~\x18"):
            raise ValueError(f"{line!r} contains a line end or a real-time character")
        timeout = self.timeout_s if timeout_s is None else timeout_s
        t = self.transport
        with t.lock:
            t.write(line.encode("ascii") + b"\n")
            deadline = time.monotonic() + timeout
            lines = []
            while True:
                text = self._readline(deadline, repr(line), timeout)
                if text == "ok":
                    return lines
                if (code := parse_code(text, "error")) is not None:
                    raise DeviceError(f"error:{code}", f"{line!r}: {ERROR_CODES.get(code, 'unknown error')}",
                                      device=self.name)
                if text.startswith("ALARM:"):
                    raise GrblAlarm(self.last_alarm, device=self.name)
                if text.startswith("<") or BANNER.search(text):
                    continue  # a late status report or banner belongs to nobody
                if not text.startswith(("[", "$")):
                    t.reset_input()
                    raise ProtocolError(f"unexpected reply to {line!r}", device=self.name, raw=text.encode())
                lines.append(text)

    def status(self) -> GrblStatus:
        """Send ``?`` and return the status report (pushes on the way are recorded)."""
        t = self.transport
        with t.lock:
            t.write(REALTIME_STATUS)
            deadline = time.monotonic() + self.timeout_s
            while True:
                text = self._readline(deadline, "'?'", self.timeout_s)
                if text.startswith("<"):
                    try:
                        st = parse_status(text)
                    except ProtocolError as exc:
                        t.reset_input()
                        raise ProtocolError(exc.message, device=self.name, raw=exc.raw) from None
                    if st.wco is not None:
                        self._wco = st.wco
                    return st
                if not (text.startswith(("[", "ALARM:", "ok", "error:")) or BANNER.search(text)):
                    t.reset_input()  # noise may have split the report: drop the rest of it
                    raise ProtocolError("garbled line while waiting for a status report",
                                        device=self.name, raw=text.encode())

    def soft_reset(self) -> str:
        """Ctrl-X: abort motion, flush buffers, wait for the banner; return GRBL's version."""
        t = self.transport
        with t.lock:
            t.write(SOFT_RESET)
            timeout = 2.0 * self.timeout_s + 1.0  # the board may still be printing its boot lines
            deadline = time.monotonic() + timeout
            while True:
                text = self._readline(deadline, "soft reset", timeout)
                m = BANNER.search(text)
                if m:
                    return m.group(1)

    def feed_hold(self) -> None:
        """``!``: decelerate and pause the running motion (resume with :meth:`resume`)."""
        with self.transport.lock:
            self.transport.write(FEED_HOLD)

    def resume(self) -> None:
        """``~``: cycle start / resume after a feed hold."""
        with self.transport.lock:
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
        """Open the port, soft-reset to a known state, read build info and settings."""
        self.close()
        self.transport.open()
        try:
            self.transport.reset_input()
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
            state = self.status().state
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
        """Machine coordinates by axis letter, machine units."""
        self._require()
        mpos = self.status().machine_position(self._wco)
        return dict(zip(AXES, mpos))

    @property
    def light_position_mm(self) -> tuple[float, float, float]:
        return self.kinematics.forward(self.machine_position())

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
        end = self.kinematics.inverse(target)
        st = self.status()
        self._check_ready(st)
        start = dict(zip(AXES, st.machine_position(self._wco)))
        self.send(format_move(end).decode("ascii").strip())
        timeout = self._timeout_for(start, end)
        return MoveStatus.run(lambda: self._wait_arrived(end, timeout), target=target,
                              device=self.name, name="move")

    def _wait_arrived(self, end: dict[str, float], timeout: float) -> tuple[float, float, float]:
        deadline = time.monotonic() + timeout
        moved = False
        grace = time.monotonic() + 0.25  # GRBL may report Idle for a moment before the block starts
        while True:
            st = self._poll(self.status)
            if st.state == "Alarm":
                raise GrblAlarm(self.last_alarm, device=self.name)
            if st.state == "Idle":
                here = dict(zip(AXES, st.machine_position(self._wco)))
                miss = max(abs(here[a] - v) for a, v in end.items())
                if miss <= self.position_tolerance:
                    return self.kinematics.forward(here)
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
        """Run the homing cycle ``$H`` (soft-resetting first after a critical alarm)."""
        self._require()
        if not self.homing_enabled:
            raise DeviceError("error:5", ERROR_CODES[5], device=self.name)
        travel = [self.settings.get(130 + i, 500.0) for i in range(3)]
        seek = self.settings.get(25, 500.0) / 60.0  # $25 homing seek rate, units/min -> /s
        timeout = 2.0 * max(travel) / max(seek, 1e-6) + 5.0

        def _run() -> tuple[float, float, float]:
            if self.last_alarm in CRITICAL_ALARMS or self.status().state == "Alarm":
                self.soft_reset()  # critical alarms answer nothing but a reset
            self.last_alarm = None
            self.send("$H", timeout_s=timeout)
            self._homed = True
            return self.light_position_mm

        return MoveStatus.run(_run, target="home", device=self.name, name="home")

    def stop(self) -> None:
        """Stop now keeping the position: feed hold, wait for the hold to complete, then soft
        reset to flush the planner (a reset after the hold does not lose steps)."""
        self._require()
        self.feed_hold()
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            st = self.status()
            if st.state in ("Idle", "Alarm") or (st.state == "Hold" and st.substate == 0):
                break
            time.sleep(self.poll_interval_s)
        self.soft_reset()

    # -- description ------------------------------------------------------------------------------
    def read(self) -> dict[str, dict[str, Any]]:
        self._require()
        st = self.status()
        mpos = dict(zip(AXES, st.machine_position(self._wco)))
        return {
            "light_position": reading(self.kinematics.forward(mpos), "mm"),
            "machine_position": reading(mpos, "deg" if self.kinematics.kind == "arm" else "mm"),
            "state": reading(st.state if st.substate is None else f"{st.state}:{st.substate}"),
            "homed": reading(self._homed),
        }

    def describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {"driver": "grbl", "port": self.port, "units": "mm",
                               "kinematics": self.kinematics.to_config(),
                               "axis_limits": self.kinematics.limits()}
        if self.version:
            out.update({"model": f"GRBL {self.kinematics.kind} positioner", "firmware": f"Grbl {self.version}",
                        "build": self.build, "serial": "", "options": self.options,
                        "homing_enabled": self.homing_enabled})
        return out
