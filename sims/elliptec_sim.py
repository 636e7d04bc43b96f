"""Firmware simulator of a Thorlabs ELL14 rotation mount, byte-exact on a pseudo-terminal.

Requests carry no terminator, so :meth:`ElliptecSim.split` frames them by command length, as the
module's firmware does; a request left incomplete for ``comm_timeout_s`` is dropped with
``GS01`` (communication time out). Requests for another bus address get no answer.

Moves and homing take ``|delta| / speed_deg_s`` seconds (at once with ``fast=True``); the ``PO``
reply is sent when the motion ends, and requests other than ``gs``/``st`` during motion are
answered ``GS09`` (busy). The encoder position wraps modulo one revolution.

Faults (:meth:`inject`), besides the base ``no_reply``, ``garble``, ``disconnect``:

- ``busy``                the next request is answered ``GS09``;
- ``mechanical_timeout``  the next move or homing run stops short and answers ``GS02``;
- ``out_of_range``        the next move is refused with ``GS0C``.
"""
from __future__ import annotations

import time

from .serial_sim import SerialSim

# the simulator speaks bytes; the codec is restated here rather than imported from rig
_DATA_LEN = {"in": 0, "gs": 0, "gp": 0, "st": 0, "ma": 8, "mr": 8, "ho": 1}
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
    """

    FAULTS = SerialSim.FAULTS | {"busy", "mechanical_timeout", "out_of_range"}

    terminator = None

    def __init__(self, name: str = "polarizer", *, fast: bool = False, address: str = "0",
                 pulses_per_rev: int = 143360, serial_number: str = "11400123", year: str = "2023",
                 firmware: str = "17", speed_deg_s: float = 240.0, comm_timeout_s: float = 0.5,
                 start_angle_deg: float = 37.0) -> None:
        super().__init__(name, fast=fast)
        self.address = address
        self.pulses_per_rev = pulses_per_rev
        self.serial_number = serial_number
        self.year = year
        self.firmware = firmware
        self.speed_deg_s = speed_deg_s
        self.comm_timeout_s = comm_timeout_s
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
    def split(self, buf: bytearray) -> list[bytes]:
        out = []
        while len(buf) >= 3:
            cmd = buf[1:3].decode("ascii", "replace")
            need = 3 + _DATA_LEN.get(cmd, 0)  # unknown command: framed as 3 bytes, GS03
            if len(buf) < need:
                break
            out.append(bytes(buf[:need]))
            del buf[:need]
        if buf:
            if self._partial_since is None:
                self._partial_since = time.monotonic()
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
            try:
                if cmd == "ma":
                    target = _signed32(data)
                    delta = (target % self.pulses_per_rev) - self._pos
                elif cmd == "mr":
                    delta = _signed32(data)
                else:  # ho
                    if data not in "01":
                        return self._status(4)
                    delta = -self._pos if data == "0" else self.pulses_per_rev - self._pos
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
            if (self._partial_since is not None and self._partial_buf
                    and time.monotonic() - self._partial_since > self.comm_timeout_s):
                del self._partial_buf[:]
                self._partial_since = None
                return (reply or b"") + self._status(1)
            return reply
