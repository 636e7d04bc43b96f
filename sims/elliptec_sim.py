"""Firmware simulator of a Thorlabs ELL14 rotation mount, byte-exact on a pseudo-terminal.

Requests carry no terminator, so :meth:`ElliptecSim.split` frames them by command length, as the
module's firmware does. CR and LF bytes are ignored wherever they fall (clients such as
``thorlabs-elliptec`` end every request with ``\\r\\n``). A request left incomplete for
``comm_timeout_s`` is dropped with ``GS01`` (communication time out). An unknown command takes the
upper-case hex characters after it as its data (up to the next request's address), so that a
data-carrying command the simulator does not model (``0xy00002000``) is answered ``GS03`` once
and does not swallow the requests after it; when its data runs to the end of what has arrived,
it is framed after ``unknown_gap_s`` of silence. Requests for another bus address get no answer.

Moves and homing take ``|delta| / speed_deg_s`` seconds (at once with ``fast=True``); the ``PO``
reply is sent when the motion ends, and requests other than ``gs``/``st`` during motion are
answered ``GS09`` (busy). The encoder position wraps modulo one revolution.

Besides ``in``/``gs``/``gp``/``ma``/``mr``/``ho``/``st`` the firmware answers what the vendor
clients send: ``gj``/``sj`` (jog step, ``GJ`` + 8 hex pulses), ``fw``/``bw`` (one jog step, ``PO``
at the end), ``go``/``so`` (home offset, ``HO`` + 8 hex pulses; homing ends at the offset),
``i1``/``i2`` (motor info ``I1``: loop and motor state, current, ramps, forward and backward
periods), ``us`` (save user data). Set commands answer ``GS00``. Stated simplifications: the
factory jog step (0x2000 pulses) and the motor-info values are plausible ELL14 figures, not read
off a device; a jog step of 0 (continuous jog on the real mount) jogs nothing.

Faults (:meth:`inject`), besides the base ``no_reply``, ``garble``, ``disconnect``:

- ``busy``                the next request is answered ``GS09``;
- ``mechanical_timeout``  the next move or homing run stops short and answers ``GS02``;
- ``out_of_range``        the next move is refused with ``GS0C``.
"""
from __future__ import annotations

import time

from .serial_sim import SerialSim

# the simulator speaks bytes; the codec is restated here rather than imported from rig
_DATA_LEN = {"in": 0, "gs": 0, "gp": 0, "st": 0, "ma": 8, "mr": 8, "ho": 1, "gj": 0, "sj": 8,
             "fw": 0, "bw": 0, "go": 0, "so": 8, "i1": 0, "i2": 0, "us": 0}
_HEX = frozenset(b"0123456789ABCDEF")
# I1/I2 data: loop on, motor off, current 0 (1866 per A), ramp up and down FFFF (none), forward
# and backward periods 0x008F / 0x0092 (14.74 MHz / period: ~103 / ~101 kHz)
_MOTOR_INFO = "1" "0" "0000" "FFFF" "FFFF" "008F" "0092"
_MOTION_FAULTS = ("mechanical_timeout", "out_of_range")


def _hex32(pulses: int) -> str:
    return f"{pulses & 0xFFFFFFFF:08X}"


def _signed32(text: str) -> int:
    v = int(text, 16)
    return v - (1 << 32) if v & 0x80000000 else v


class ElliptecSim(SerialSim):
    """ELL14 firmware.

    Parameters
    ----------
    name : str
        Device role (symlink name of the pty).
    fast : bool
        Complete moves at once.
    address : str
        Bus address (one hex character).
    pulses_per_rev : int
        Encoder pulses per revolution reported in ``IN`` (ELL14: 143360).
    serial_number, year, firmware : str
        Reported in ``IN``.
    speed_deg_s : float
        Rotation speed when not ``fast``, degrees per second.
    comm_timeout_s : float
        Time after which an incomplete request is dropped with ``GS01``.
    unknown_gap_s : float
        Silence after which an unknown command whose data reached the end of the input is framed.
    """

    FAULTS = SerialSim.FAULTS | {"busy", "mechanical_timeout", "out_of_range"}

    terminator = None

    def __init__(self, name: str = "polarizer", *, fast: bool = False, address: str = "0",
                 pulses_per_rev: int = 143360, serial_number: str = "11400123", year: str = "2023",
                 firmware: str = "17", speed_deg_s: float = 240.0, comm_timeout_s: float = 0.5,
                 unknown_gap_s: float = 0.02, start_angle_deg: float = 37.0) -> None:
        super().__init__(name, fast=fast)
        self.address = address
        self.pulses_per_rev = pulses_per_rev
        self.serial_number = serial_number
        self.year = year
        self.firmware = firmware
        self.speed_deg_s = speed_deg_s
        self.comm_timeout_s = comm_timeout_s
        self.unknown_gap_s = unknown_gap_s
        self.jog_pulses = 0x2000        # sj / gj (kept in user data on the real mount)
        self.home_offset_pulses = 0     # so / go
        self._last_rx = 0.0
        self._partial_since: float | None = None
        self._partial_buf: bytearray | None = None
        self._pos = round(start_angle_deg / 360.0 * pulses_per_rev) % pulses_per_rev
        self.on_power_up()

    # -- state --------------------------------------------------------------------------------
    def on_power_up(self) -> None:
        """The mount stays where it physically is; motion and the homed flag are lost."""
        self._motion: tuple[float, float, int, int, str | None] | None = None  # t0, t1, p0, p1, fault
        self.homed = False

    def on_disconnect(self) -> None:
        with self._lock:
            if self._motion is not None:
                self._pos = self._current_pulses() % self.pulses_per_rev
                self._motion = None

    def _current_pulses(self) -> int:
        """Unwrapped position along the current motion (pulses)."""
        if self._motion is None:
            return self._pos
        t0, t1, p0, p1, _ = self._motion
        frac = 1.0 if t1 <= t0 else min(1.0, (time.monotonic() - t0) / (t1 - t0))
        return round(p0 + frac * (p1 - p0))

    @property
    def angle_deg(self) -> float:
        """True mount angle now, degrees in [0, 360) (for the scene renderer)."""
        with self._lock:
            return (self._current_pulses() % self.pulses_per_rev) * 360.0 / self.pulses_per_rev

    @property
    def moving(self) -> bool:
        return self._motion is not None

    # -- framing ------------------------------------------------------------------------------
    def split(self, buf: bytearray, *, flush: bool = False) -> list[bytes]:
        """Cut complete requests off ``buf``; ``flush`` frames a trailing unknown command now."""
        buf[:] = buf.translate(None, b"\r\n")  # the controller ignores CR and LF
        now = time.monotonic()
        if not flush:
            self._last_rx = now
        out = []
        while len(buf) >= 3:
            cmd = buf[1:3].decode("ascii", "replace")
            if cmd in _DATA_LEN:
                need = 3 + _DATA_LEN[cmd]
                if len(buf) < need:
                    break
            else:  # unknown: its data is the run of upper-case hex before the next request
                end = 3
                while end < len(buf) and buf[end] in _HEX:
                    end += 1
                if end < len(buf):
                    need = end - 1  # buf[end - 1] is the next request's address
                elif flush:
                    need = end
                else:
                    break  # more data may follow: framed by tick() after a silence
            out.append(bytes(buf[:need]))
            del buf[:need]
        if buf:
            if self._partial_since is None:
                self._partial_since = now
            self._partial_buf = buf
        else:
            self._partial_since = self._partial_buf = None
        return out

    def _line(self, code: str, data: str = "") -> bytes:
        return f"{self.address}{code}{data}\r\n".encode("ascii")

    def _status(self, code: int) -> bytes:
        return self._line("GS", f"{code:02X}")

    def _position(self) -> bytes:
        return self._line("PO", _hex32(self._pos))

    # -- firmware -----------------------------------------------------------------------------
    def handle(self, request: bytes) -> bytes | None:
        text = request.decode("ascii", "replace")
        addr, cmd, data = text[0], text[1:3], text[3:]
        if addr != self.address:
            return None  # another module on the bus
        with self._lock:
            if self.take_fault("busy"):
                return self._status(9)
            if cmd not in _DATA_LEN:
                return self._status(3)
            if self._motion is not None and cmd not in ("gs", "st"):
                return self._status(9)
            if cmd == "in":
                hw = 0x01
                return self._line("IN", f"0E{self.serial_number:>8.8}{self.year:>4.4}"
                                        f"{self.firmware:>2.2}{hw:02X}{360:04X}"
                                        f"{self.pulses_per_rev:08X}")
            if cmd == "gs":
                return self._status(9 if self._motion is not None else 0)
            if cmd == "gp":
                return self._position()
            if cmd == "st":
                if self._motion is not None:
                    self._pos = self._current_pulses() % self.pulses_per_rev
                    self._motion = None
                    self.send(self._position())  # the interrupted move's reply comes first
                return self._status(0)
            if cmd in ("gj", "go"):
                return self._line("GJ" if cmd == "gj" else "HO",
                                  _hex32(self.jog_pulses if cmd == "gj" else self.home_offset_pulses))
            if cmd in ("i1", "i2"):
                return self._line(cmd.upper(), _MOTOR_INFO)
            if cmd == "us":
                return self._status(0)
            if cmd in ("sj", "so"):
                try:
                    value = _signed32(data)
                except ValueError:
                    return self._status(4)
                if cmd == "sj":
                    self.jog_pulses = value
                else:
                    self.home_offset_pulses = value % self.pulses_per_rev
                return self._status(0)
            try:
                if cmd == "ma":
                    target = _signed32(data)
                    delta = (target % self.pulses_per_rev) - self._pos
                elif cmd == "mr":
                    delta = _signed32(data)
                elif cmd in ("fw", "bw"):
                    delta = self.jog_pulses if cmd == "fw" else -self.jog_pulses
                else:  # ho: to the home offset, backward (0) or forward (1)
                    if data not in ("0", "1"):
                        return self._status(4)
                    rel = (self._pos - self.home_offset_pulses) % self.pulses_per_rev
                    delta = -rel if data == "0" else self.pulses_per_rev - rel
            except ValueError:
                return self._status(3)
            fault = next((f for f in _MOTION_FAULTS if self.take_fault(f)), None)
            if fault == "out_of_range":
                return self._status(12)
            return self._start_motion(delta, fault, homing=cmd == "ho")

    def _start_motion(self, delta: int, fault: str | None, *, homing: bool) -> bytes | None:
        if fault == "mechanical_timeout":
            delta //= 3  # it stalls a third of the way
        deg = abs(delta) * 360.0 / self.pulses_per_rev
        t0 = time.monotonic()
        t1 = t0 if self.fast else t0 + deg / self.speed_deg_s
        self._motion = (t0, t1, self._pos, self._pos + delta, fault or ("home" if homing else None))
        return self._finish_motion()

    def _finish_motion(self) -> bytes | None:
        """Complete the motion if its time is up; return its reply (None while still moving)."""
        if self._motion is None:
            return None
        t0, t1, p0, p1, tag = self._motion
        if time.monotonic() < t1:
            return None
        self._pos = p1 % self.pulses_per_rev
        self._motion = None
        if tag == "mechanical_timeout":
            return self._status(2)
        if tag == "home":
            self.homed = True
        return self._position()

    def tick(self) -> bytes | None:
        with self._lock:
            reply = self._finish_motion()
            buf = self._partial_buf
            if buf and len(buf) >= 3 and buf[1:3].decode("ascii", "replace") not in _DATA_LEN \
                    and time.monotonic() - self._last_rx > self.unknown_gap_s:
                for request in self.split(buf, flush=True):
                    self._dispatch(request)
            if (self._partial_since is not None and self._partial_buf
                    and time.monotonic() - self._partial_since > self.comm_timeout_s):
                del self._partial_buf[:]
                self._partial_since = None
                return (reply or b"") + self._status(1)
            return reply
