"""Zaber ASCII protocol (firmware 6/7) and a rotary-stage driver for the turntable.

Frames (one line each; the host may end a command with ``\\n``, the device ends with ``\\r\\n``)::

    command   /<dev> <axis> [<id>] <command> [<data>][:<CC>]\\n      /1 1 07 move abs 1000:4B
    reply     @<dd> <a> [<id>] <OK|RJ> <IDLE|BUSY> <flag> <data>[:<CC>]   @01 1 07 OK BUSY -- 0
    info      #<dd> <a> [<id>] <text>
    alert     !<dd> <a> <IDLE|BUSY> <flag>

- ``dev`` is the daisy-chain address (1..99, 0 = all), ``axis`` 0 (device scope) or 1..9;
  ``id`` an optional message id 0..99 echoed in the reply, used here to match replies to
  requests so that a late or stale line can never be mistaken for the answer.
- ``:CC`` is the optional checksum: the two's complement of the byte sum (mod 256) of every
  character after the leading ``/`` ``@`` ``#`` ``!`` and before the ``:``, as two upper-case hex
  digits (``/01 tools echo:8F``). A device checks a command's checksum when it is present; it
  appends one to its own replies only when the device setting ``comm.checksum`` is 1 (the
  factory default is 0), which the driver turns on at connect (``reply_checksums``) so that a
  reply damaged on the wire -- a flipped digit in a position -- is detected, not believed.
- ``RJ`` replies carry the rejection reason in the data field (:data:`REJECTION_REASONS`).
- ``flag`` is the most urgent active warning (``--`` none); faults ``F*``, warnings ``W*``,
  notices ``N*`` (:data:`WARNING_FLAGS`). ``warnings`` lists all of them, ``warnings clear``
  clears the latched ones.

Units on the wire are microsteps; speeds are ``microsteps/s * 1.6384`` and accelerations
``microsteps/s^2 * 1.6384 / 10000`` (firmware 7 data units).
"""
from __future__ import annotations

import itertools
import logging
import math
import re
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from .device import Axis, reading
from .errors import (DeviceBusy, DeviceError, DeviceTimeout, LimitError, NotHomed,
                     ProtocolError, RigError)
from .motion import move_time_s
from .status import MoveStatus
from .transport import SerialDriver, SerialTransport

log = logging.getLogger("gonio.rig.zaber")

#: speed data units per (microstep/s) and acceleration data units per (microstep/s^2)
SPEED_UNITS = 1.6384
ACCEL_UNITS = 1.6384 / 10000.0

#: rejection reasons (data field of an ``RJ`` reply) -> meaning and what to do
REJECTION_REASONS: dict[str, str] = {
    "AGAIN": "the device cannot process the command right now; send it again",
    "BADAXIS": "the axis number does not exist or does not support the command",
    "BADCOMMAND": "unknown command, or not allowed in the current state "
                  "(e.g. an absolute move without a reference position: home first)",
    "BADDATA": "the data is malformed or outside the allowed range",
    "BADMESSAGEID": "the message id is not a number 0..99",
    "BADSPLIT": "a split (continued) command was malformed",
    "DEVICEONLY": "the command is device-scope only; send it to axis 0",
    "DRIVERDISABLED": "the motor driver is disabled (see fault FD); send 'driver enable'",
    "FULL": "the device's command buffer is full; wait and resend",
    "INACTIVE": "the axis is inactive (no peripheral connected or it is disabled)",
    "LOCKSTEP": "the axis is part of a lockstep group; command the group instead",
    "NOACCESS": "the command or setting needs a higher access level",
    "NOTSUPPORTED": "the command is not supported by this device or firmware",
    "PARKED": "the axis is parked; send 'tools parking unpark' first",
    "REMOTE": "the axis is under remote (manual/knob) control",
    "STATUSBUSY": "the axis is busy and the command needs it idle; retry when idle",
    "SYSTEMERROR": "the device has a system error; power-cycle it",
}

#: rejection reasons that clear by themselves; the request can be repeated after a short wait
BUSY_REASONS = frozenset({"AGAIN", "FULL", "STATUSBUSY"})

#: warning flags -> (severity, meaning). Severity: "fault" stops motion and must be cleared,
#: "warning" means the result may be wrong, "notice" is informational. The set and names are those
#: of Zaber Motion Library's ``WarningFlags`` (firmware 6/7); the hints are ours.
WARNING_FLAGS: dict[str, tuple[str, str]] = {
    "FF": ("fault", "critical system error: power-cycle the device; contact Zaber if it persists"),
    "FN": ("fault", "peripheral not supported by this controller or firmware"),
    "FZ": ("fault", "peripheral inactive: the stage is disconnected or not configured; check the "
                    "cable and the peripheral id"),
    "FH": ("fault", "hardware emergency stop: the driver was disabled by the e-stop input; release "
                    "it, then 'driver enable'"),
    "FV": ("fault", "over- or under-voltage: the driver was disabled; check the power supply"),
    "FO": ("fault", "driver disabled at start-up or by command; send 'driver enable'"),
    "FC": ("fault", "current inrush error: the driver was disabled; check the motor and cable"),
    "FM": ("fault", "motor temperature error: the motor overheated; let it cool, reduce the current "
                    "or duty cycle"),
    "FD": ("fault", "driver disabled (firmware <= 7.10): over-temperature, over-current or supply "
                    "fault; check the motor, then 'driver enable'"),
    "FQ": ("fault", "encoder error: the encoder reading is invalid; check the encoder cable"),
    "FI": ("fault", "index error: the encoder index was not where expected; home the axis again"),
    "FA": ("fault", "analog encoder sync error; home the axis again"),
    "FR": ("fault", "overdrive limit exceeded: the motor was driven beyond its rated load"),
    "FS": ("fault", "stalled and stopped: the axis hit an obstruction or was overloaded; "
                    "clear the load and repeat the move"),
    "FB": ("fault", "stream bounds error: a streamed move ran outside the travel limits"),
    "FP": ("fault", "interpolated path deviation: a streamed path could not be followed"),
    "FE": ("fault", "limit error: a limit sensor did not behave as expected during homing"),
    "FT": ("fault", "excessive twist: lockstep axes are out of alignment"),
    "WL": ("warning", "unexpected limit trigger: a limit sensor fired during a move; the "
                      "position may be lost, home the axis"),
    "WV": ("warning", "supply voltage out of range"),
    "WT": ("warning", "controller temperature high"),
    "WS": ("warning", "stalled with recovery: the axis stalled during the move and recovered"),
    "WM": ("warning", "displaced when stationary: the axis was pushed out of position while idle"),
    "WP": ("warning", "invalid calibration type: the stored calibration does not fit; recalibrate"),
    "WR": ("warning", "no reference position: the axis has not been homed since power-up; home it"),
    "WH": ("warning", "device not homed: the axis has a position but was not homed; home it"),
    "NC": ("notice", "manual control: the knob or joystick moved the axis"),
    "NI": ("notice", "movement interrupted: a move was interrupted by a stop or a new command"),
    "ND": ("notice", "stream discontinuity: a streamed path was interrupted"),
    "NR": ("notice", "value rounded: a setting or target was rounded to what the device supports"),
    "NT": ("notice", "value truncated: a setting or target was truncated"),
    "NU": ("notice", "setting update pending: a setting changes after the current move"),
    "NJ": ("notice", "joystick calibrating"),
    "NB": ("notice", "device in firmware update mode (firmware 6)"),
}


# ---------------------------------------------------------------------------------------------
# codec: pure functions, no I/O
# ---------------------------------------------------------------------------------------------
def checksum(body: bytes | str) -> str:
    """Zaber ASCII checksum of ``body`` (the message without its leading type character).

    Returns the two's complement of the byte sum modulo 256 as two upper-case hex digits.
    """
    data = body.encode("ascii") if isinstance(body, str) else body
    return f"{(-sum(data)) & 0xFF:02X}"


def encode_command(command: str, *, device: int = 1, axis: int = 0, message_id: int | None = None,
                   with_checksum: bool = True) -> bytes:
    """Frame one command: ``/<device> <axis> [<id>] <command>[:CC]\\n``.

    Parameters
    ----------
    command : str
        Command and data, e.g. ``"move abs 1000"``; ``""`` is the status poll.
    device, axis : int
        Address (1..99, 0 = all devices) and axis (0 = device scope, 1..9).
    message_id : int or None
        0..99, echoed in the reply; None sends none.
    with_checksum : bool
        Append ``:CC`` (the device then rejects corrupted commands).
    """
    if not 0 <= device <= 99:
        raise ValueError(f"device must be 0..99, got {device}")
    if not 0 <= axis <= 9:
        raise ValueError(f"axis must be 0..9, got {axis}")
    if message_id is not None and not 0 <= message_id <= 99:
        raise ValueError(f"message_id must be 0..99, got {message_id}")
    if any(c in command for c in "\r\n:/@#!"):
        raise ValueError(f"command {command!r} contains a reserved character")
    parts = [str(device), str(axis)]
    if message_id is not None:
        parts.append(f"{message_id:02d}")
    if command:
        parts.append(command)
    body = " ".join(parts)
    if with_checksum:
        body += ":" + checksum(body)
    return b"/" + body.encode("ascii") + b"\n"


@dataclass(frozen=True)
class ZaberMessage:
    """One parsed line from a device.

    Attributes
    ----------
    kind : str
        ``"@"`` reply, ``"#"`` info, ``"!"`` alert.
    device, axis : int
        Who sent it.
    message_id : int or None
        The echoed message id (replies and info lines), if the command carried one.
    reply_flag : str
        ``"OK"`` or ``"RJ"`` (replies only, else ``""``).
    status : str
        ``"IDLE"`` or ``"BUSY"`` (replies and alerts).
    warning : str
        Most urgent warning flag, ``"--"`` for none.
    data : str
        The data field (a value, ``"0"``, the rejection reason, or an info text).
    checksum_ok : bool or None
        None if the line carried no checksum.
    """

    kind: str
    device: int
    axis: int
    message_id: int | None
    reply_flag: str
    status: str
    warning: str
    data: str
    checksum_ok: bool | None = None

    @property
    def rejected(self) -> bool:
        return self.reply_flag == "RJ"

    @property
    def busy(self) -> bool:
        return self.status == "BUSY"

    def value(self) -> float:
        """The data field as a number (raises ``ProtocolError`` if it is not one)."""
        try:
            return float(self.data)
        except ValueError:
            raise ProtocolError(f"expected a number in the reply, got {self.data!r}") from None


_REPLY = re.compile(r"@(\d{2}) (\d)(?: (\d{2}))? (OK|RJ) (IDLE|BUSY) (--|[A-Z]{2}) ?(.*)")
_INFO = re.compile(r"#(\d{2}) (\d)(?: (\d{2}))?(?: (.*))?")
_ALERT = re.compile(r"!(\d{2}) (\d) (IDLE|BUSY) (--|[A-Z]{2})(?: (.*))?")


def parse_message(line: bytes | str) -> ZaberMessage:
    """Parse one line (reply, info or alert), verifying its checksum when present.

    Raises
    ------
    ProtocolError
        If the line is not a well-formed Zaber message or its checksum is wrong.
    """
    raw = line if isinstance(line, bytes) else line.encode("ascii", "replace")
    try:
        text = raw.decode("ascii").rstrip("\r\n")
    except UnicodeDecodeError:
        raise ProtocolError("non-ASCII bytes in reply", raw=raw) from None
    checksum_ok = None
    if len(text) >= 4 and text[-3] == ":" and re.fullmatch(r"[0-9A-Fa-f]{2}", text[-2:]):
        checksum_ok = checksum(text[1:-3]) == text[-2:].upper()
        if not checksum_ok:
            raise ProtocolError("checksum mismatch", raw=raw)
        text = text[:-3]
    if text.startswith("@"):
        m = _REPLY.fullmatch(text)
        if m:
            dev, ax, mid, flag, status, warn, data = m.groups()
            return ZaberMessage("@", int(dev), int(ax), None if mid is None else int(mid), flag,
                                status, warn, data, checksum_ok)
    elif text.startswith("#"):
        m = _INFO.fullmatch(text)
        if m:
            dev, ax, mid, data = m.groups()
            return ZaberMessage("#", int(dev), int(ax), None if mid is None else int(mid), "", "",
                                "--", data or "", checksum_ok)
    elif text.startswith("!"):
        m = _ALERT.fullmatch(text)
        if m:
            dev, ax, status, warn, data = m.groups()
            return ZaberMessage("!", int(dev), int(ax), None, "", status, warn, data or "",
                                checksum_ok)
    raise ProtocolError("not a Zaber ASCII message", raw=raw)


def rejection_error(msg: ZaberMessage, command: str, *, device: str = "") -> RigError:
    """The typed error for an ``RJ`` reply to ``command``."""
    reason = msg.data.strip()
    if reason in BUSY_REASONS:
        return DeviceBusy(f"{command!r} rejected: {reason} ({REJECTION_REASONS[reason]})", device=device)
    if msg.warning in ("WR", "WH") and reason == "BADCOMMAND":
        return NotHomed(f"{command!r} rejected: the axis has no reference position", device=device)
    meaning = REJECTION_REASONS.get(reason, "unknown rejection reason")
    return DeviceError(reason, f"{command!r} rejected: {meaning}", device=device)


def flag_error(flag: str, *, device: str = "") -> RigError | None:
    """The typed error a warning flag stands for at the end of a move, or None if harmless.

    Faults (``F*``) and a lost position (``WL``) are ``DeviceError``; no reference (``WR`` /
    ``WH``) is ``NotHomed``; other warnings and notices are not errors.
    """
    if flag == "--":
        return None
    severity, meaning = WARNING_FLAGS.get(flag, ("fault" if flag.startswith("F") else "notice",
                                                 "unknown flag"))
    if flag in ("WR", "WH"):
        return NotHomed(meaning, device=device)
    if severity == "fault" or flag == "WL":
        return DeviceError(flag, meaning, device=device)
    return None


# ---------------------------------------------------------------------------------------------
# driver
# ---------------------------------------------------------------------------------------------
class ZaberRotaryStage(SerialDriver, Axis):
    """A Zaber rotary stage (X-RSW, X-RST, RSM ...) as the turntable, over the ASCII protocol.

    Angles are degrees. The conversion microsteps <-> degrees is read from the device at
    :meth:`connect`: a continuous rotary stage reports ``limit.cycle.dist`` (microsteps per
    revolution at the current ``resolution``), so one microstep is ``360 / cycle`` degrees.
    A stage without a cycle distance (limited travel) needs ``microstep_deg`` from its data sheet.

    Wrap-around: on a continuous stage every angle is accepted and reduced modulo 360; the
    firmware then moves the shorter way round (``move abs`` on a cyclic axis), so a move from
    350 deg to 10 deg turns 20 deg, and :attr:`position` reads back in [0, 360). On a stage with
    limited travel a target outside ``[limit.min, limit.max]`` raises ``LimitError``.

    Parameters
    ----------
    name : str
        Role in the rig.
    port : str
        Serial port (``/dev/ttyUSB0`` or a simulator's pty).
    transport : object, optional
        A ready transport (e.g. :class:`rig.transport.ScriptedTransport`) instead of ``port``.
    device, axis : int
        Daisy-chain address and axis number.
    baudrate : int
        115200 is the Zaber ASCII default.
    timeout_s : float
        Reply timeout per request, seconds.
    use_checksum : bool
        Send checksums (the device then rejects a command corrupted on the wire).
    reply_checksums : bool
        Make the device checksum its replies: at :meth:`connect` the device setting
        ``comm.checksum`` is set to 1 if it is not (a persistent device setting; Zaber's own
        software reads such replies), and from then on a reply without a checksum is a
        ``ProtocolError``. False leaves the setting alone and accepts replies without one.
    microstep_deg : float, optional
        Degrees per microstep for stages without ``limit.cycle.dist``.
    poll_interval_s : float
        Status poll period while a move runs, seconds.
    poll_retries : int
        Consecutive garbled or unanswered status polls tolerated during a move before its status
        fails with the ``ProtocolError`` / ``DeviceTimeout``.
    speed_deg_s, accel_deg_s2 : float, optional
        Speed (deg/s) and acceleration (deg/s^2) to set at :meth:`connect`; default: keep the
        device's settings.
    busy_retries : int
        How often a command rejected as busy (STATUSBUSY, AGAIN, FULL) is repeated, with a
        doubling back-off from ``busy_backoff_s``, before ``DeviceBusy`` is raised.
    """

    units = "deg"

    def __init__(self, name: str = "turntable", port: str | None = None, *, transport: Any = None,
                 device: int = 1, axis: int = 1, baudrate: int = 115200, timeout_s: float = 0.5,
                 use_checksum: bool = True, reply_checksums: bool = True,
                 microstep_deg: float | None = None,
                 poll_interval_s: float = 0.01, poll_retries: int = 2, busy_retries: int = 3,
                 busy_backoff_s: float = 0.02, speed_deg_s: float | None = None,
                 accel_deg_s2: float | None = None) -> None:
        super().__init__(name)
        if transport is None and not port:
            raise ValueError(f"{name}: give a serial port or a transport")
        if not 1 <= device <= 99:
            raise ValueError(f"{name}: device address must be 1..99, got {device}")
        if not 1 <= axis <= 9:
            raise ValueError(f"{name}: axis must be 1..9, got {axis}")
        if microstep_deg is not None and microstep_deg <= 0:
            raise ValueError(f"{name}: microstep_deg must be > 0, got {microstep_deg}")
        self.port = port or getattr(transport, "port", "")
        self.transport = transport or SerialTransport(port, baudrate, timeout_s=timeout_s, device=name)
        self.address = device
        self.axis_number = axis
        self.timeout_s = timeout_s
        self.use_checksum = use_checksum
        self.reply_checksums = reply_checksums
        self._require_reply_checksum = False  # set once comm.checksum = 1 is confirmed
        self.poll_interval_s = poll_interval_s
        self.poll_retries = poll_retries
        self.busy_retries = busy_retries
        self.busy_backoff_s = busy_backoff_s
        self._microstep_deg_config = microstep_deg
        self._speed_deg_s = speed_deg_s
        self._accel_deg_s2 = accel_deg_s2
        self._ids = itertools.cycle(range(100))
        self._id_lock = threading.Lock()
        self._stray: dict[int, ZaberMessage] = {}  # replies read by a request they were not for
        self._connected = False
        # unsolicited alerts seen (comm.alert = 1), newest last; bounded: one per move otherwise
        self.alerts: deque[ZaberMessage] = deque(maxlen=100)
        self.info: dict[str, Any] = {}

    @classmethod
    def from_config(cls, name: str, section: dict[str, Any], **context: Any) -> "ZaberRotaryStage":
        """Build from a rig-file section: ``port`` and optional ``device``, ``axis``,
        ``baudrate``, ``timeout_s``, ``use_checksum``, ``reply_checksums``, ``microstep_deg``, ``speed_deg_s``,
        ``accel_deg_s2``, ``poll_interval_s``, ``poll_retries``, ``busy_retries``."""
        from .rig import driver_options
        allowed = {"device", "axis", "baudrate", "timeout_s", "use_checksum", "reply_checksums",
                   "microstep_deg", "poll_interval_s", "poll_retries", "busy_retries", "speed_deg_s",
                   "accel_deg_s2"}
        return cls(name, section["port"], **driver_options(name, section, "zaber", allowed))

    # -- wire -------------------------------------------------------------------------------------
    def _next_id(self) -> int:
        """A message id for a new request; a stale reply kept for its last use is dropped."""
        with self._id_lock:
            mid = next(self._ids)
            self._stray.pop(mid, None)
            return mid

    def request(self, command: str, *, scope_device: bool = False,
                timeout_s: float | None = None) -> ZaberMessage:
        """Send one command and return its reply (``OK`` or ``RJ``, not raised).

        Stale lines (other message ids, other axes), info lines and alerts are skipped;
        alerts are kept in :attr:`alerts`.

        Raises
        ------
        DeviceTimeout, Disconnected, ProtocolError
        """
        axis = 0 if scope_device else self.axis_number
        timeout = self.timeout_s if timeout_s is None else timeout_s
        with self.transport.lock:
            mid = self._next_id()
            self.transport.write(encode_command(command, device=self.address, axis=axis, message_id=mid,
                                                with_checksum=self.use_checksum))
            return self._await_reply(command, mid, axis, timeout)

    def _await_reply(self, command: str, mid: int, axis: int, timeout: float) -> ZaberMessage:
        """The reply with message id ``mid``: kept aside by another request that read it, or read
        from the port (under the port lock). Replies to other ids are kept for their waiter."""
        t = self.transport
        with t.lock:
            deadline = time.monotonic() + timeout
            while True:
                if (kept := self._stray.pop(mid, None)) is not None:
                    return kept
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(f"no reply to {command!r}", device=self.name, timeout_s=timeout)
                line = t.read_until(b"\n", remaining)
                try:
                    msg = parse_message(line)
                except ProtocolError as exc:
                    t.reset_input()  # noise may have split the reply: drop the rest of it
                    raise ProtocolError(f"bad reply to {command!r} ({exc.message})", device=self.name,
                                        raw=line) from None
                if msg.kind == "!":
                    self.alerts.append(msg)
                    continue
                if msg.kind == "@" and msg.message_id == mid and msg.device == self.address \
                        and msg.axis == axis:
                    if msg.checksum_ok is None and self._require_reply_checksum:
                        # comm.checksum is on: a reply without one lost its ':CC' on the wire
                        t.reset_input()
                        raise ProtocolError(f"reply to {command!r} carries no checksum although "
                                            "comm.checksum = 1", device=self.name, raw=line)
                    return msg
                if msg.kind == "@" and msg.device == self.address and msg.message_id is not None:
                    self._stray[msg.message_id] = msg  # e.g. the reply to a stop() written meanwhile
                    continue
                log.debug("%s: skipped %r while waiting for id %d", self.name, line, mid)

    def command(self, command: str, *, scope_device: bool = False) -> ZaberMessage:
        """Send a command, repeat it while the device answers busy, raise on rejection."""
        backoff = self.busy_backoff_s
        for attempt in range(self.busy_retries + 1):
            msg = self.request(command, scope_device=scope_device)
            if not msg.rejected:
                return msg
            error = rejection_error(msg, command, device=self.name)
            if not isinstance(error, DeviceBusy) or attempt == self.busy_retries:
                raise error
            time.sleep(backoff)
            backoff *= 2
        raise AssertionError("unreachable")

    def get(self, setting: str, *, scope_device: bool = False) -> float:
        """Read a numeric setting (``get <setting>``)."""
        return self.command(f"get {setting}", scope_device=scope_device).value()

    def get_text(self, setting: str, *, scope_device: bool = False) -> str:
        return self.command(f"get {setting}", scope_device=scope_device).data

    # -- link -------------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port and read identity, resolution, travel and speed from the device."""
        self.close()
        self.transport.open()
        self._require_reply_checksum = False
        try:
            self.transport.reset_input()
            info: dict[str, Any] = {
                "device_id": int(self.get("deviceid", scope_device=True)),
                "firmware": self.get_text("version", scope_device=True),
                "serial": self.get_text("system.serial", scope_device=True),
                "resolution": int(self.get("resolution")),
                "cycle_microsteps": self._cycle_microsteps(),
                "limit_min": int(self.get("limit.min")),
                "limit_max": int(self.get("limit.max")),
                "maxspeed": self.get("maxspeed"),
                "accel": self.get("accel"),
            }
            if self.reply_checksums:
                self._enable_reply_checksums()
        except BaseException:
            self.transport.close()
            raise
        if info["cycle_microsteps"] > 0:
            info["microstep_deg"] = 360.0 / info["cycle_microsteps"]
        elif self._microstep_deg_config is not None:
            info["microstep_deg"] = float(self._microstep_deg_config)
        else:
            self.transport.close()
            raise DeviceError("limit.cycle.dist", "this stage is not a continuous rotary stage "
                              "(limit.cycle.dist = 0); set microstep_deg from its data sheet",
                              device=self.name)
        if info["maxspeed"] <= 0 or info["accel"] <= 0:
            self.transport.close()
            raise DeviceError("maxspeed", f"maxspeed={info['maxspeed']:g}, accel={info['accel']:g}: "
                              "the axis cannot move with zero speed or acceleration", device=self.name)
        self.info = info
        self._connected = True
        if self._speed_deg_s is not None:
            self.set_speed(self._speed_deg_s)
        if self._accel_deg_s2 is not None:
            self.set_accel(self._accel_deg_s2)

    def _cycle_microsteps(self) -> int:
        """``limit.cycle.dist``, or 0 where the firmware has no such setting (a linear axis on
        firmware 6 rejects it with BADCOMMAND: not a continuous rotary stage)."""
        try:
            return int(self.get("limit.cycle.dist"))
        except DeviceError as exc:
            if exc.code != "BADCOMMAND":
                raise
            return 0

    def _enable_reply_checksums(self) -> None:
        """Set the device's ``comm.checksum`` to 1 (if needed) and require checksummed replies."""
        if int(self.get("comm.checksum", scope_device=True)) != 1:
            self.command("set comm.checksum 1", scope_device=True)
            log.info("%s: turned on reply checksums (device setting comm.checksum = 1)", self.name)
        self._require_reply_checksum = True

    # -- conversions ------------------------------------------------------------------------------
    @property
    def cyclic(self) -> bool:
        """True for a continuous rotary stage (positions wrap at 360 deg)."""
        return self.info.get("cycle_microsteps", 0) > 0

    @property
    def microstep_deg(self) -> float:
        return self.info["microstep_deg"]

    @property
    def speed_deg_s(self) -> float:
        """Maximum speed (``maxspeed``), degrees per second."""
        return self.info["maxspeed"] / SPEED_UNITS * self.microstep_deg

    @property
    def accel_deg_s2(self) -> float:
        """Acceleration (``accel``), degrees per second squared."""
        return self.info["accel"] / ACCEL_UNITS * self.microstep_deg

    def _to_deg(self, microsteps: float) -> float:
        deg = microsteps * self.microstep_deg
        return deg % 360.0 if self.cyclic else deg

    @property
    def limits(self) -> tuple[float, float]:
        if self.cyclic:
            return (0.0, 360.0)
        return (self.info["limit_min"] * self.microstep_deg, self.info["limit_max"] * self.microstep_deg)

    def _target_microsteps(self, deg: float) -> tuple[int, float]:
        """Microstep target for ``deg`` and the travel to it in degrees (shortest way if cyclic)."""
        if not math.isfinite(deg):
            raise ValueError(f"{self.name}: target angle must be finite, got {deg}")
        if self.cyclic:
            cycle = self.info["cycle_microsteps"]
            target = round((deg % 360.0) / self.microstep_deg) % cycle
            here = self.position
            travel = abs((deg - here + 180.0) % 360.0 - 180.0)
            return target, travel
        lo, hi = self.limits
        if not lo <= deg <= hi:
            raise LimitError(deg, (lo, hi), "deg", device=self.name)
        return round(deg / self.microstep_deg), abs(deg - self.position)

    def set_speed(self, deg_s: float) -> float:
        """Set the maximum speed (``set maxspeed``), degrees per second; return the value the
        device took (its data units are whole numbers)."""
        self._require()
        if not (math.isfinite(deg_s) and deg_s > 0):
            raise ValueError(f"{self.name}: speed must be > 0 deg/s, got {deg_s}")
        data = max(1, round(deg_s / self.microstep_deg * SPEED_UNITS))
        self.command(f"set maxspeed {data}")
        self.info["maxspeed"] = self.get("maxspeed")
        return self.speed_deg_s

    def set_accel(self, deg_s2: float) -> float:
        """Set the acceleration (``set accel``), degrees per second squared; return the value the
        device took."""
        self._require()
        if not (math.isfinite(deg_s2) and deg_s2 > 0):
            raise ValueError(f"{self.name}: acceleration must be > 0 deg/s^2, got {deg_s2}")
        data = max(1, round(deg_s2 / self.microstep_deg * ACCEL_UNITS))
        self.command(f"set accel {data}")
        self.info["accel"] = self.get("accel")
        return self.accel_deg_s2

    # -- state ------------------------------------------------------------------------------------
    @property
    def position(self) -> float:
        """Read-back angle, degrees ([0, 360) on a continuous stage)."""
        self._require()
        return self._to_deg(self.get("pos"))

    def warnings(self) -> list[str]:
        """All active warning flags (``warnings``)."""
        self._require()
        fields = self.command("warnings").data.split()
        return fields[1:] if fields else []

    def clear_warnings(self) -> list[str]:
        """Clear latched warnings; return the flags that were active."""
        self._require()
        fields = self.command("warnings clear").data.split()
        return fields[1:] if fields else []

    @property
    def homed(self) -> bool:
        return not {"WR", "WH"} & set(self.warnings())

    @property
    def busy(self) -> bool:
        self._require()
        return self.request("").busy

    # -- motion -----------------------------------------------------------------------------------
    def _timeout_for(self, travel_deg: float) -> float:
        return 1.5 * move_time_s(travel_deg, self.speed_deg_s, self.accel_deg_s2) + 1.0

    def move_to(self, value: float) -> MoveStatus:
        """Start an absolute move to ``value`` degrees and return at once.

        The command is sent before returning, so a rejection (``NotHomed``, ``DeviceBusy``
        after retries, ``DeviceError``) or a ``LimitError`` raises here; the returned status
        completes with the final angle when the axis is idle again, or with the fault that
        stopped it (stall ``FS``, interruption by :meth:`stop`, a timeout computed from the
        travel, speed and acceleration).
        """
        self._require()
        target, travel = self._target_microsteps(float(value))
        self.command(f"move abs {target}")
        target_deg = self._to_deg(target)
        timeout = self._timeout_for(travel)
        return MoveStatus.run(lambda: self._wait_idle(target_deg, timeout), target=float(value),
                              device=self.name, name="move")

    def home(self) -> MoveStatus:
        """Start the homing run (finds the home sensor and sets the reference position)."""
        self._require()
        self.command("home")
        timeout = self._timeout_for(360.0 if self.cyclic else self.limits[1] - self.limits[0])
        return MoveStatus.run(lambda: self._wait_idle(None, timeout), target="home",
                              device=self.name, name="home")

    def stop(self) -> None:
        """Decelerate to a stop now; a pending move's status then fails (interrupted).

        The command is written at once, without waiting for the port lock: a request in flight
        (a status poll waiting out a silent line) must not delay an emergency stop. Its reply
        is then read under the lock (a request that reads it first keeps it aside by message id).
        """
        self._require()
        mid = self._next_id()
        self.transport.write(encode_command("stop", device=self.address, axis=self.axis_number,
                                            message_id=mid, with_checksum=self.use_checksum))
        msg = self._await_reply("stop", mid, self.axis_number, self.timeout_s)
        if msg.rejected:
            raise rejection_error(msg, "stop", device=self.name)

    def _wait_idle(self, target_deg: float | None, timeout: float) -> float:
        deadline = time.monotonic() + timeout
        while True:
            msg = self._poll(lambda: self.request(""))
            if not msg.busy:
                break
            if time.monotonic() > deadline:
                self.command("stop")
                raise DeviceTimeout("move did not finish", device=self.name, timeout_s=timeout)
            time.sleep(self.poll_interval_s)
        error = flag_error(msg.warning, device=self.name)
        if isinstance(error, DeviceError):
            self.clear_warnings()  # latched fault: clear it so the next move can run
            raise error
        position = self.position
        if target_deg is not None:
            miss = abs((position - target_deg + 180.0) % 360.0 - 180.0) if self.cyclic \
                else abs(position - target_deg)
            if miss > 1.5 * self.microstep_deg:
                flag = msg.warning if msg.warning != "--" else "NI"
                raise DeviceError(flag, f"move ended at {position:.4f} deg, not at the target "
                                  f"{target_deg:.4f} deg (interrupted by stop or a new command)",
                                  device=self.name)
        elif error is not None:
            raise error  # homing finished without a reference
        return position

    # -- description ------------------------------------------------------------------------------
    def read(self) -> dict[str, dict[str, Any]]:
        self._require()
        msg = self.request("")
        flags = self.warnings()
        return {
            "angle": reading(self.position, "deg"),
            "busy": reading(msg.busy),
            "homed": reading(not {"WR", "WH"} & set(flags)),
            "warnings": reading(flags),
        }

    def describe(self) -> dict[str, Any]:
        info = self.info
        out: dict[str, Any] = {"driver": "zaber", "port": self.port, "units": "deg",
                               "address": f"{self.address}/{self.axis_number}"}
        if info:
            out.update({
                "model": f"Zaber rotary stage (device ID {info['device_id']})",
                "firmware": info["firmware"], "serial": info["serial"],
                "limits": self.limits, "cyclic": self.cyclic, "resolution": info["resolution"],
                "microstep_deg": self.microstep_deg, "max_speed_deg_s": self.speed_deg_s,
                "accel_deg_s2": self.accel_deg_s2, "reply_checksums": self._require_reply_checksum,
            })
        return out
