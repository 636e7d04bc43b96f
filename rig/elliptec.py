"""Thorlabs Elliptec ELL14 rotation mount (the polarizer), over the Elliptec ASCII protocol.

Wire format (ELLx protocol manual, issue 5): 9600 baud, 8N1, no flow control. A request is
``<addr><cmd>[data]`` with **no terminator**: one address character ``0``-``F``, a two-letter
lower-case command, then fixed-length upper-case hex data. Replies are ``<addr><CMD>[data]\\r\\n``
with an upper-case mnemonic::

    > 0in                 < 0IN0E1140012320211501016800023000\\r\\n   (device information)
    > 0gs                 < 0GS00\\r\\n                              (status, 2 hex digits)
    > 0gp                 < 0PO00008C00\\r\\n                        (position, pulses)
    > 0ma00008C00         < 0PO00008C00\\r\\n  when the move ends    (move absolute)
    > 0mrFFFFC400         < 0PO...\\r\\n                             (move relative)
    > 0ho0                < 0PO00000000\\r\\n                        (home; 0 = CW, 1 = CCW)
    > 0st                 < 0GS00\\r\\n                              (stop)

Positions are signed 32-bit two's complement encoder pulses as 8 hex digits. The ``IN`` reply
carries motor type (2 hex), serial number (8 chars), year (4), firmware (2 hex), hardware
(2 hex: bit 7 thread imperial, bits 0-6 release), travel (4 hex, degrees for a rotary mount) and
pulses per measurement unit (8 hex; per revolution for the ELL14). The driver reads the pulse
count from the device rather than assuming 143360.

A move that fails answers ``GS`` with a status code instead of ``PO``; :data:`STATUS` maps each
documented code to its meaning and a typed error.
"""
from __future__ import annotations

import math
import re
import threading
import time
from dataclasses import dataclass
from typing import Any

from .device import Axis, reading
from .errors import (DeviceBusy, DeviceError, DeviceTimeout, LimitError, NotHomed,
                     ProtocolError, RigError)
from .status import MoveStatus
from .transport import SerialDriver, SerialTransport

BAUDRATE = 9600
TERMINATOR = b"\r\n"

#: status code -> (meaning, error class); 0 is success. Codes are sent as 2 hex digits.
STATUS: dict[int, tuple[str, type[RigError] | None]] = {
    0: ("OK, no error", None),
    1: ("communication time out", DeviceTimeout),
    2: ("mechanical time out", DeviceError),
    3: ("command error or not supported", DeviceError),
    4: ("value out of range", DeviceError),
    5: ("module isolated", DeviceError),
    6: ("module out of isolation", DeviceError),
    7: ("initialising error", DeviceError),
    8: ("thermal error", DeviceError),
    9: ("busy", DeviceBusy),
    10: ("sensor error", DeviceError),
    11: ("motor error", DeviceError),
    12: ("out of range", DeviceError),
    13: ("over current error", DeviceError),
}
BUSY = 9

#: request data length (hex characters) per command, used to frame requests (no terminator)
REQUEST_DATA_LEN: dict[str, int] = {"in": 0, "gs": 0, "gp": 0, "st": 0, "ma": 8, "mr": 8, "ho": 1}

_REPLY = re.compile(rb"^([0-9A-F])([A-Z][A-Z0-9])([0-9A-Za-z]*)\r\n$")


# -- pure codec -------------------------------------------------------------------------------
def _check_address(address: str) -> str:
    if not (isinstance(address, str) and len(address) == 1 and address in "0123456789ABCDEF"):
        raise ValueError(f"address must be one hex character '0'..'F', got {address!r}")
    return address


def encode_request(address: str, command: str, data: str = "") -> bytes:
    """Encode one request: ``<addr><cmd><data>`` as ASCII, no terminator.

    Raises
    ------
    ValueError
        If the address, command or data length is not what the protocol defines.
    """
    _check_address(address)
    if command not in REQUEST_DATA_LEN:
        raise ValueError(f"command must be one of {sorted(REQUEST_DATA_LEN)}, got {command!r}")
    if len(data) != REQUEST_DATA_LEN[command]:
        raise ValueError(f"command {command!r} takes {REQUEST_DATA_LEN[command]} data characters, "
                         f"got {data!r}")
    return f"{address}{command}{data}".encode("ascii")


def encode_pulses(pulses: int) -> str:
    """Signed 32-bit pulse count as 8 upper-case hex digits (two's complement)."""
    if not -(2**31) <= pulses < 2**31:
        raise ValueError(f"pulses must fit a signed 32-bit integer, got {pulses}")
    return f"{pulses & 0xFFFFFFFF:08X}"


def decode_pulses(text: str) -> int:
    """Inverse of :func:`encode_pulses`."""
    value = int(text, 16)
    return value - (1 << 32) if value & 0x80000000 else value


def encode_move_absolute(address: str, pulses: int) -> bytes:
    """``ma`` request to ``pulses`` (encoder counts from home)."""
    return encode_request(address, "ma", encode_pulses(pulses))


def encode_move_relative(address: str, pulses: int) -> bytes:
    """``mr`` request by ``pulses`` (signed)."""
    return encode_request(address, "mr", encode_pulses(pulses))


def encode_home(address: str, clockwise: bool = True) -> bytes:
    """``ho`` request; the direction byte is ``0`` clockwise, ``1`` counter-clockwise."""
    return encode_request(address, "ho", "0" if clockwise else "1")


@dataclass(frozen=True)
class Reply:
    """One parsed reply: ``address`` (hex char), ``code`` (``PO``, ``GS``, ``IN`` ...), ``data``."""

    address: str
    code: str
    data: str
    raw: bytes


def parse_reply(raw: bytes, *, device: str = "") -> Reply:
    """Split a reply line into address, mnemonic and data.

    Raises
    ------
    ProtocolError
        If the bytes are not ``<hex addr><2 upper-case chars><data>\\r\\n``.
    """
    m = _REPLY.match(raw)
    if m is None:
        raise ProtocolError("malformed Elliptec reply", device=device, raw=raw)
    addr, code, data = (g.decode("ascii") for g in m.groups())
    return Reply(addr, code, data, raw)


def parse_position(reply: Reply, *, device: str = "") -> int:
    """Pulses from a ``PO`` (position) reply."""
    if reply.code != "PO" or len(reply.data) != 8:
        raise ProtocolError("expected a PO reply with 8 hex digits", device=device, raw=reply.raw)
    try:
        return decode_pulses(reply.data)
    except ValueError:
        raise ProtocolError("PO reply data is not hex", device=device, raw=reply.raw) from None


def parse_status(reply: Reply, *, device: str = "") -> int:
    """Status code (int) from a ``GS`` reply."""
    if reply.code != "GS" or len(reply.data) != 2:
        raise ProtocolError("expected a GS reply with 2 hex digits", device=device, raw=reply.raw)
    try:
        return int(reply.data, 16)
    except ValueError:
        raise ProtocolError("GS reply data is not hex", device=device, raw=reply.raw) from None


def status_error(code: int, *, device: str = "", context: str = "") -> RigError | None:
    """The typed error for a non-zero status ``code`` (None for 0), its meaning in the message."""
    if code == 0:
        return None
    meaning, cls = STATUS.get(code, (f"undocumented status {code}", DeviceError))
    where = f" ({context})" if context else ""
    if cls is DeviceError or cls is None:
        return DeviceError(code, meaning + where, device=device)
    return cls(f"status {code}: {meaning}{where}", device=device)


@dataclass(frozen=True)
class DeviceInfo:
    """Decoded ``IN`` reply.

    Attributes
    ----------
    motor_type : int
        Elliptec model number (14 for the ELL14).
    serial_number, year, firmware : str
        As the device reports them (firmware as its 2 hex digits, e.g. ``"15"``).
    hardware_release : int
        Bits 0-6 of the hardware byte.
    imperial_thread : bool
        Bit 7 of the hardware byte.
    travel : int
        Travel in the device's measurement unit (degrees for a rotation mount).
    pulses_per_unit : int
        Encoder pulses per revolution (rotary) or per mm (linear).
    """

    motor_type: int
    serial_number: str
    year: str
    firmware: str
    hardware_release: int
    imperial_thread: bool
    travel: int
    pulses_per_unit: int


def parse_info(reply: Reply, *, device: str = "") -> DeviceInfo:
    """Decode an ``IN`` reply (30 data characters)."""
    d = reply.data
    if reply.code != "IN" or len(d) != 30:
        raise ProtocolError("expected an IN reply with 30 data characters", device=device,
                            raw=reply.raw)
    try:
        hw = int(d[16:18], 16)
        info = DeviceInfo(motor_type=int(d[0:2], 16), serial_number=d[2:10], year=d[10:14],
                          firmware=d[14:16], hardware_release=hw & 0x7F,
                          imperial_thread=bool(hw & 0x80), travel=int(d[18:22], 16),
                          pulses_per_unit=int(d[22:30], 16))
    except ValueError:
        raise ProtocolError("IN reply has non-hex fields", device=device, raw=reply.raw) from None
    if info.pulses_per_unit <= 0 or info.travel <= 0:
        raise ProtocolError("IN reply reports zero travel or zero pulses per unit", device=device,
                            raw=reply.raw)
    return info


def encode_info(info: DeviceInfo, address: str = "0") -> bytes:
    """The ``IN`` reply line for ``info`` (used by the simulator and protocol tests)."""
    hw = (info.hardware_release & 0x7F) | (0x80 if info.imperial_thread else 0)
    return (f"{_check_address(address)}IN{info.motor_type:02X}{info.serial_number:>8.8}"
            f"{info.year:>4.4}{info.firmware:>2.2}{hw:02X}{info.travel:04X}"
            f"{info.pulses_per_unit:08X}").encode("ascii") + TERMINATOR


# -- driver -----------------------------------------------------------------------------------
class ElliptecRotator(SerialDriver, Axis):
    """ELL14 rotation mount as an :class:`~rig.device.Axis` in degrees.

    The mount rotates without end; targets in ``limits`` (-360..360 degrees) are wrapped into
    [0, 360) before they are sent, and ``position`` reads back in [0, 360). The pulses per
    revolution come from the device's ``IN`` reply at :meth:`connect`.

    Parameters
    ----------
    name : str
        Role in the rig (``"polarizer"``).
    port : str
        Serial port path (``/dev/ttyUSB1`` or a simulator's pty).
    address : str
        Bus address, one hex character (factory default ``"0"``).
    timeout_s : float
        Reply timeout for non-motion requests, seconds.
    move_timeout_s : float
        Time a move or homing run may take before ``DeviceTimeout``, seconds (the ELL14 turns
        360 degrees in about 1.5 s).
    busy_retry_s : float
        How long to keep retrying a request the device answers with ``GS09`` (busy), seconds.
    require_home : bool
        Refuse moves (``NotHomed``) until :meth:`home` has run on this connection.
    transport : SerialTransport, optional
        A ready transport (tests pass a scripted fake); by default one on ``port`` at 9600 baud.
    """

    units = "deg"

    def __init__(self, name: str, port: str, *, address: str = "0", timeout_s: float = 0.5,
                 move_timeout_s: float = 6.0, busy_retry_s: float = 3.0, require_home: bool = True,
                 transport: Any = None) -> None:
        super().__init__(name)
        self.port = port
        self.address = _check_address(address)
        for arg, value in (("timeout_s", timeout_s), ("move_timeout_s", move_timeout_s),
                           ("busy_retry_s", busy_retry_s)):
            if not value > 0:
                raise ValueError(f"{arg} must be > 0 seconds, got {value!r}")
        self.move_timeout_s = move_timeout_s
        self.busy_retry_s = busy_retry_s
        self.require_home = require_home
        self.transport = transport or SerialTransport(port, BAUDRATE, timeout_s=timeout_s,
                                                      device=name)
        self.info: DeviceInfo | None = None
        self._homed = False
        self._stop_sent = threading.Event()
        self._late_reply_possible = False
        self._motion: MoveStatus | None = None

    @classmethod
    def from_config(cls, name: str, section: dict[str, Any], **context: Any) -> "ElliptecRotator":
        """Build from a rig-file section: ``port`` plus optional ``address``, ``timeout_s``,
        ``move_timeout_s``, ``busy_retry_s``, ``require_home``."""
        from .rig import driver_options
        allowed = {"address", "timeout_s", "move_timeout_s", "busy_retry_s", "require_home"}
        return cls(name, section["port"], **driver_options(name, section, "elliptec", allowed))

    # -- link ---------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the port and read the device information (``in``)."""
        if not self.transport.is_open:
            self.transport.open()
        self.transport.reset_input()
        self._homed = False
        info = parse_info(self._query("in", "IN"), device=self.name)
        if info.motor_type != 14:
            self.close()
            raise DeviceError(info.motor_type, f"expected an ELL14 rotation mount (type 14), the "
                              f"device at address {self.address} is type {info.motor_type}",
                              device=self.name)
        self.info = info
        self._check_ok(self._exchange("gs"), "status at connect")
        self._connected = True

    def _require_info(self) -> DeviceInfo:
        self._require()
        return self.info

    # -- exchanges ----------------------------------------------------------------------------
    def _read_reply(self, timeout_s: float | None = None) -> Reply:
        reply = parse_reply(self.transport.read_until(TERMINATOR, timeout_s), device=self.name)
        if reply.address != self.address:
            raise ProtocolError(f"reply from address {reply.address}, expected {self.address}",
                                device=self.name, raw=reply.raw)
        return reply

    def _exchange(self, command: str, data: str = "", timeout_s: float | None = None) -> Reply:
        """One request/reply, retrying while the device answers busy (``GS09``) with back-off."""
        request = encode_request(self.address, command, data)
        deadline = time.monotonic() + self.busy_retry_s
        delay = 0.01
        while True:
            with self.transport.lock:
                if self._late_reply_possible:
                    # an earlier request timed out: its reply may still arrive; drop it
                    self.transport.reset_input()
                    self._late_reply_possible = False
                self.transport.write(request)
                try:
                    reply = self._read_reply(timeout_s)
                except ProtocolError:
                    self.transport.reset_input()  # drop the rest of a garbled line
                    raise
                except DeviceTimeout:
                    self._late_reply_possible = True
                    raise
            busy = reply.code == "GS" and parse_status(reply, device=self.name) == BUSY
            if not busy or command == "gs":
                return reply
            if time.monotonic() + delay > deadline:
                raise DeviceBusy(f"'{command}' still refused as busy after {self.busy_retry_s:g} s",
                                 device=self.name)
            time.sleep(delay)
            delay = min(delay * 2, 0.2)

    def _query(self, command: str, expected: str) -> Reply:
        """Exchange ``command`` and return its ``expected`` reply; a ``GS`` error status in its
        place raises that status's typed error."""
        reply = self._exchange(command)
        if reply.code == "GS" and expected != "GS":
            self._check_ok(reply, f"'{command}'")
        return reply

    def _check_ok(self, reply: Reply, context: str) -> None:
        error = status_error(parse_status(reply, device=self.name), device=self.name, context=context)
        if error is not None:
            raise error

    def _pulses_to_deg(self, pulses: int) -> float:
        ppr = self._require_info().pulses_per_unit
        return (pulses % ppr) * 360.0 / ppr

    def _motion_reply(self, reply: Reply, context: str) -> float:
        """A move ends with ``PO`` (done) or ``GS`` (failed); return degrees or raise."""
        if reply.code == "GS":
            self._check_ok(reply, context)
            raise ProtocolError(f"{context}: device answered GS00 instead of a position",
                                device=self.name, raw=reply.raw)
        return self._pulses_to_deg(parse_position(reply, device=self.name))

    def _run_motion(self, command: str, data: str, context: str) -> float:
        self._stop_sent.clear()
        reply = self._exchange(command, data, timeout_s=self.move_timeout_s)
        if self._stop_sent.is_set():
            # stop() wrote 'st' while we waited: its GS reply follows the move's PO
            with self.transport.lock:
                try:
                    self._read_reply()
                except (DeviceTimeout, ProtocolError):
                    pass
        return self._motion_reply(reply, context)

    # -- Axis API -----------------------------------------------------------------------------
    @property
    def limits(self) -> tuple[float, float]:
        travel = float(self.info.travel) if self.info else 360.0
        return (-travel, travel)

    @property
    def homed(self) -> bool:
        return self._homed

    @property
    def position(self) -> float:
        """Read-back angle in degrees, [0, 360). Waits for a running move to finish (the port
        is busy with it until its ``PO`` reply)."""
        self._require()
        return self._pulses_to_deg(parse_position(self._query("gp", "PO"), device=self.name))

    def move_to(self, value: float) -> MoveStatus:
        """Rotate to ``value`` degrees (wrapped into [0, 360)); returns at once.

        Raises
        ------
        LimitError
            At once, if ``value`` is outside ``limits`` or not finite.
        NotHomed
            At once, if ``require_home`` and the mount has not been homed on this connection.
        """
        info = self._require_info()
        value = float(value)
        lo, hi = self.limits
        if not lo <= value <= hi:  # also rejects NaN
            raise LimitError(value, (lo, hi), "deg", device=self.name)
        if self.require_home and not self._homed:
            raise NotHomed(f"cannot move to {value:g} deg before homing", device=self.name)
        pulses = round((value % 360.0) * info.pulses_per_unit / 360.0) % info.pulses_per_unit
        self._motion = MoveStatus.run(
            lambda: self._run_motion("ma", encode_pulses(pulses), f"move to {value:g} deg"),
            target=value, device=self.name)
        return self._motion

    def move_by(self, delta: float) -> MoveStatus:
        """Relative rotation by ``delta`` degrees with the device's ``mr`` command."""
        info = self._require_info()
        delta = float(delta)
        if not math.isfinite(delta):
            raise ValueError(f"{self.name}: delta must be a finite number of degrees, got {delta}")
        if self.require_home and not self._homed:
            raise NotHomed(f"cannot move by {delta:g} deg before homing", device=self.name)
        reach = (2**31 - 1) * 360.0 / info.pulses_per_unit  # what a signed 32-bit pulse count holds
        if abs(delta) > reach:
            raise LimitError(delta, (-reach, reach), "deg", device=self.name, what="relative move")
        data = encode_pulses(round(delta * info.pulses_per_unit / 360.0))
        self._motion = MoveStatus.run(
            lambda: self._run_motion("mr", data, f"move by {delta:g} deg"),
            target=f"+{delta:g}", device=self.name)
        return self._motion

    def home(self, clockwise: bool = True) -> MoveStatus:
        """Start the homing run (``ho``); ``homed`` becomes True when it ends at 0 degrees."""
        self._require()

        def _home() -> float:
            angle = self._run_motion("ho", "0" if clockwise else "1", "homing")
            self._homed = True
            return angle

        self._motion = MoveStatus.run(_home, target="home", device=self.name, name="home")
        return self._motion

    def stop(self) -> None:
        """Stop motion now (``st``). A running move's status then ends at the stop position."""
        self._require()
        motion = self._motion
        if motion is not None and not motion.done:
            # the move thread holds the port waiting for PO; write past it and let it eat the GS
            self._stop_sent.set()
            self.transport.write(encode_request(self.address, "st"))
            return
        self._check_ok(self._exchange("st"), "stop")

    def status_code(self) -> int:
        """The device's ``gs`` status code (0 = OK, 9 = busy, see :data:`STATUS`)."""
        self._require()
        return parse_status(self._exchange("gs"), device=self.name)

    def read(self) -> dict[str, dict[str, Any]]:
        code = self.status_code()
        return {"position": reading(self.position, "deg"),
                "homed": reading(self._homed),
                "status": reading(STATUS.get(code, (f"status {code}", None))[0])}

    def describe(self) -> dict[str, Any]:
        info = self.info
        out: dict[str, Any] = {"driver": "elliptec", "port": self.port, "address": self.address,
                               "units": "deg", "limits": self.limits}
        if info is not None:
            out.update(model=f"ELL{info.motor_type}", serial_number=info.serial_number,
                       year=info.year, firmware=info.firmware,
                       hardware_release=info.hardware_release, travel=info.travel,
                       pulses_per_revolution=info.pulses_per_unit)
        return out
