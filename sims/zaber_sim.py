"""Zaber ASCII firmware simulator: a continuous rotary stage (the turntable) on a pty.

Speaks the frames described in ``rig/zaber.py`` byte for byte (commands ``/1 1 07 move abs
1000:CC``, replies ``@01 1 07 OK BUSY -- 0:CC``), models motion with a trapezoidal profile
(``maxspeed`` / ``accel`` in Zaber data units), and keeps the firmware's reference state: after
power-up the axis reports ``WR`` (no reference position) and rejects absolute moves with
``RJ IDLE WR BADCOMMAND`` until ``home`` has run.

``stop`` decelerates at ``accel`` from the current speed (flag ``NI``, command interrupted).

Checksums: a command's checksum is verified when present; replies, info lines and alerts carry
one only while the device setting ``comm.checksum`` is 1 (factory default 0; the setting is kept
over a power cycle, as the firmware keeps it in non-volatile memory).

Simplifications, stated: one device with one axis; a command whose checksum is wrong is dropped
without a reply (the manual's exact answer to it was not verified).

With ``set comm.alert 1`` the device pushes an alert ``!01 1 IDLE <flag>`` when a move ends.

Identification: Zaber's own library (``zaber-motion``) asks every device, before it drives it,
for ``deviceid``, ``system.serial``, ``version``, ``version.build``, ``device.hw.modified``,
``comm.command.packets.max``, ``comm.word.size.max``, ``get.settings.max``,
``system.axiscount`` and, per axis, ``resolution`` and ``peripheralid``. The simulator answers them
as an integrated X-series stage on firmware 7.38 (build 15708): ``comm.packet.size.max`` 80,
``comm.command.packets.max`` 5, ``comm.word.size.max`` 50, ``get.settings.max`` 12,
``device.hw.modified`` 0, ``system.axiscount`` 1, ``system.access`` 1; ``peripheralid`` is
rejected (an integrated stage has no peripheral). ``tools echo <words>`` answers the words (``0``
when there are none).

With ``get.settings.max`` above 1 a ``get`` may name several settings; zaber-motion sends them at
device scope with the axis number first (``/1 0 get 1 maxspeed pos``) and splits the reply's data
on ``;`` (it trims spaces around it), so the simulator answers ``629146 ; 0``.

Device faults for :meth:`inject` (besides the base ``no_reply``, ``garble``, ``disconnect``):

- ``busy``    the next motion or ``set`` command is rejected ``RJ BUSY -- STATUSBUSY``;
- ``stall``   the next move stops half way and latches fault ``FS`` (stalled and stopped);
- ``encoder`` the next move stops half way and latches fault ``FQ`` (encoder error);
- ``limit``   the next move trips a limit sensor half way: warning ``WL`` and the reference
  position is lost (``WR``) until the axis is homed again.
"""
from __future__ import annotations

import math
import re
import time

from .serial_sim import SerialSim

SPEED_UNITS = 1.6384            # data units per microstep/s (firmware 7)
ACCEL_UNITS = 1.6384 / 10000.0  # data units per microstep/s^2

_FLAG_ORDER = ("F", "W", "N")  # most urgent first

# protocol limits an X-series device on firmware 7.38 reports (zaber-motion reads them to size
# its commands): bytes in one packet, packets in one command (line continuation), characters in
# one word, settings in one ``get``
PACKET_SIZE_MAX = 80
COMMAND_PACKETS_MAX = 5
WORD_SIZE_MAX = 50
GET_SETTINGS_MAX = 12


def trapezoid_duration(distance: float, vmax: float, amax: float) -> float:
    """Duration (s) of a rest-to-rest trapezoidal move over ``distance`` (any length unit)."""
    distance = abs(distance)
    if distance == 0.0:
        return 0.0
    if distance <= vmax * vmax / amax:
        return 2.0 * math.sqrt(distance / amax)
    return vmax / amax + distance / vmax


def trapezoid_distance(distance: float, vmax: float, amax: float, t: float) -> float:
    """Distance covered after ``t`` seconds of a rest-to-rest trapezoidal move.

    Parameters
    ----------
    distance : float
        Total (unsigned) distance of the move.
    vmax, amax : float
        Speed and acceleration limits in the same length unit per s and per s^2.
    t : float
        Time since the start of the move, seconds (clipped to the move's duration).
    """
    distance = abs(distance)
    total = trapezoid_duration(distance, vmax, amax)
    if t >= total:
        return distance
    if t <= 0.0:
        return 0.0
    t_acc = min(vmax / amax, total / 2.0)
    v_peak = amax * t_acc
    if t < t_acc:
        return 0.5 * amax * t * t
    if t > total - t_acc:
        rest = total - t
        return distance - 0.5 * amax * rest * rest
    return 0.5 * amax * t_acc * t_acc + v_peak * (t - t_acc)


def trapezoid_speed(distance: float, vmax: float, amax: float, t: float) -> float:
    """Speed (length unit per s) ``t`` seconds into a rest-to-rest trapezoidal move."""
    total = trapezoid_duration(distance, vmax, amax)
    if t <= 0.0 or t >= total:
        return 0.0
    return amax * min(t, vmax / amax, total - t)


def _checksum(body: str) -> str:
    return f"{(-sum(body.encode('ascii'))) & 0xFF:02X}"


_COMMAND = re.compile(r"/(?:(\d+)(?: (\d+))?(?: (\d+))?)? ?(.*)")


class ZaberSim(SerialSim):
    """A Zaber X-series continuous rotary stage (firmware 7) behind a pseudo-terminal.

    Parameters
    ----------
    name : str
        Role (port symlink name).
    fast : bool
        Moves complete at once.
    device : int
        Daisy-chain address.
    device_id, firmware, firmware_build, serial : int, str, int, int
        Identity reported by ``get deviceid`` / ``get version`` / ``get version.build`` /
        ``get system.serial``.
    cycle_microsteps : int
        Microsteps per revolution (``limit.cycle.dist``); 1,536,000 is 0.000234375 deg/microstep.
    speed_deg_s, accel_deg_s2 : float
        Initial ``maxspeed`` and ``accel``, in degrees per second (squared).
    homed : bool
        Start with a reference position (skips the ``WR`` state after power-up).
    power_up_angle_deg : float
        Physical angle of the platter at power-up; the position counter starts at 0 there, so
        the reported angle is wrong until the stage is homed (the home sensor is at 0 deg).
    reply_checksums : bool
        Initial ``comm.checksum`` (False, the factory default: replies carry no checksum).
    """

    FAULTS = SerialSim.FAULTS | {"busy", "stall", "encoder", "limit"}

    def __init__(self, name: str = "turntable", *, fast: bool = False, device: int = 1,
                 device_id: int = 50419, firmware: str = "7.38", firmware_build: int = 15708,
                 serial: int = 123456,
                 cycle_microsteps: int = 1_536_000, resolution: int = 64,
                 speed_deg_s: float = 90.0, accel_deg_s2: float = 360.0, homed: bool = False,
                 power_up_angle_deg: float = 0.0, reply_checksums: bool = False) -> None:
        super().__init__(name, fast=fast)
        if cycle_microsteps <= 0:
            raise ValueError(f"cycle_microsteps must be > 0, got {cycle_microsteps}")
        self.device = device
        self.device_id = device_id
        self.firmware = firmware
        self.firmware_build = firmware_build
        self.serial = serial
        self.cycle = cycle_microsteps
        self.resolution = resolution
        steps_per_deg = cycle_microsteps / 360.0
        self.settings = {
            "maxspeed": round(speed_deg_s * steps_per_deg * SPEED_UNITS),
            "accel": round(accel_deg_s2 * steps_per_deg * ACCEL_UNITS),
        }
        self.reply_checksums = reply_checksums  # comm.checksum (non-volatile)
        self._start_homed = homed
        self._power_up_angle = power_up_angle_deg
        self.on_power_up()

    # -- firmware state ---------------------------------------------------------------------------
    def on_power_up(self) -> None:
        with self._lock:
            self._pos = 0.0                 # position counter, microsteps (unwrapped while moving)
            self._offset = 0.0 if self._start_homed else self._power_up_angle * self.cycle / 360.0
            # t0, p0, delta, flags applied at the end, braking start speed (None: rest to rest)
            self._motion: tuple[float, float, float, list[str], float | None] | None = None
            self.flags: set[str] = set() if self._start_homed else {"WR"}
            self.alerts_on = False  # comm.alert: push "!01 1 IDLE --" when a move ends
            self._outbox = bytearray()

    def on_disconnect(self) -> None:
        with self._lock:
            self._settle(time.monotonic())
            self._motion = None  # power lost: the motor stops where it is

    @property
    def speed(self) -> float:
        """Speed limit, microsteps/s."""
        return self.settings["maxspeed"] / SPEED_UNITS

    @property
    def accel(self) -> float:
        """Acceleration, microsteps/s^2."""
        return self.settings["accel"] / ACCEL_UNITS

    def _settle(self, now: float) -> None:
        """Advance the motion model to ``now``; finish the move when its time is up."""
        if self._motion is None:
            return
        t0, p0, delta, flags, v0 = self._motion
        duration = trapezoid_duration(delta, self.speed, self.accel) if v0 is None else v0 / self.accel
        if self.fast or now - t0 >= duration:
            self._pos = p0 + delta
            self._motion = None
            if "home" in flags:  # reached the home sensor: it defines counter 0
                self._pos = self._offset = 0.0
                self.flags -= {"WR", "WL"}
            else:
                self.flags |= set(flags)
                if "WL" in flags:
                    self.flags.add("WR")
            if self.alerts_on:
                self._outbox += self._frame("!", f"{self.device:02d} 1 IDLE {self._flag()}")
        elif v0 is None:
            self._pos = p0 + math.copysign(trapezoid_distance(delta, self.speed, self.accel, now - t0), delta)
        else:  # braking after a stop
            t = now - t0
            self._pos = p0 + math.copysign(v0 * t - 0.5 * self.accel * t * t, delta)

    def _speed(self, now: float) -> float:
        """Current speed, microsteps/s (0 when idle)."""
        if self._motion is None or self.fast:
            return 0.0
        t0, _, delta, _, v0 = self._motion
        if v0 is None:
            return trapezoid_speed(delta, self.speed, self.accel, now - t0)
        return max(0.0, v0 - self.accel * (now - t0))

    def _start(self, delta: float, flags: list[str]) -> None:
        """Begin a move by ``delta`` microsteps; ``flags`` are applied when it ends."""
        if set(flags) & {"FS", "FQ", "WL"}:
            delta = delta / 2.0  # the fault stops it half way
        self._motion = (time.monotonic(), self._pos, delta, flags, None)

    @property
    def busy(self) -> bool:
        with self._lock:
            self._settle(time.monotonic())
            return self._motion is not None

    @property
    def angle_deg(self) -> float:
        """Physical platter angle, degrees in [0, 360) (what the camera sees)."""
        with self._lock:
            self._settle(time.monotonic())
            return ((self._pos + self._offset) * 360.0 / self.cycle) % 360.0

    def _counter(self) -> int:
        return int(round(self._pos)) % self.cycle

    def _flag(self) -> str:
        for prefix in _FLAG_ORDER:
            found = sorted(f for f in self.flags if f.startswith(prefix))
            if found:
                return found[0]
        return "--"

    def tick(self) -> bytes | None:
        with self._lock:
            self._settle(time.monotonic())
            out, self._outbox = bytes(self._outbox), bytearray()
        return out or None

    # -- protocol ---------------------------------------------------------------------------------
    def handle(self, request: bytes) -> bytes | None:
        text = request.decode("ascii", "replace").strip("\r")
        if not text.startswith("/"):
            return None  # line noise; firmware ignores lines that are not commands
        with_ck = len(text) >= 4 and text[-3] == ":"
        if with_ck:
            if _checksum(text[1:-3]) != text[-2:].upper():
                return None
            text = text[:-3]
        m = _COMMAND.fullmatch(text)
        if m is None:
            return None
        dev, axis, mid, command = m.groups()
        dev_n = int(dev) if dev else 0
        axis_n = int(axis) if axis else 0
        if dev_n not in (0, self.device):
            return None
        with self._lock:
            self._settle(time.monotonic())
            flag, data = self._execute(axis_n, " ".join(command.split()))
            status = "BUSY" if self._motion is not None else "IDLE"
            body = f"{self.device:02d} {axis_n}"
            if mid is not None:
                body += f" {int(mid):02d}"
            body += f" {flag} {status} {self._flag()} {data}"
            return self._frame("@", body)

    def _frame(self, kind: str, body: str) -> bytes:
        """One outgoing line, checksummed while ``comm.checksum`` is 1."""
        if self.reply_checksums:
            body += ":" + _checksum(body)
        return (kind + body + "\r\n").encode("ascii")

    def _execute(self, axis: int, command: str) -> tuple[str, str]:
        """Run one command; return (``OK``/``RJ``, data)."""
        if axis not in (0, 1):
            return "RJ", "BADAXIS"
        words = command.split(" ") if command else []
        if not words:
            return "OK", "0"
        verb = words[0]
        if verb in ("move", "home", "set") and self.take_fault("busy"):
            return "RJ", "STATUSBUSY"
        if verb == "get" and len(words) == 2:
            return self._get(axis, words[1])
        if verb == "get" and len(words) > 2:
            return self._get_many(axis, words[1:])
        if verb == "tools" and words[1:2] == ["echo"]:  # a link test: the words come back
            return "OK", " ".join(words[2:]) or "0"
        if verb == "set" and len(words) == 3:
            return self._set(axis, words[1], words[2])
        if verb == "move" and len(words) == 3 and words[1] in ("abs", "rel"):
            return self._move(words[1], words[2])
        if verb == "home" and len(words) == 1:
            here = self._pos % self.cycle
            # the home sensor sits at counter 0 of the physical platter: turn back to it
            travel = -((here + self._offset) % self.cycle)
            self._start(travel, ["home"])
            return "OK", "0"
        if verb == "stop" and len(words) == 1:
            if self._motion is not None:
                now = time.monotonic()
                v = self._speed(now)
                direction = self._motion[2]
                # decelerate at `accel` from the current speed; the move's own flags are dropped
                self._motion = (now, self._pos, math.copysign(v * v / (2 * self.accel), direction), [], v) \
                    if v > 0 else None
                self.flags.add("NI")
            return "OK", "0"
        if verb == "warnings":
            listed = " ".join(sorted(self.flags))
            if words[1:] == ["clear"]:
                self.flags &= {"WR"}  # the missing reference clears only by homing
            elif words[1:]:
                return "RJ", "BADCOMMAND"
            return "OK", f"{len(listed.split()):02d} {listed}".rstrip()
        if verb == "system" and words[1:] == ["reset"]:
            self.on_power_up()
            return "OK", "0"
        return "RJ", "BADCOMMAND"

    def _get_many(self, axis: int, words: list[str]) -> tuple[str, str]:
        """``get`` of several settings; at device scope an axis number scopes the settings after
        it. Values are listed in the order asked, separated by `` ; ``."""
        values: list[str] = []
        scope = axis
        for word in words:
            if word.isdigit():
                if axis != 0:
                    return "RJ", "BADCOMMAND"
                scope = int(word)
                if scope not in (0, 1):
                    return "RJ", "BADAXIS"
                continue
            flag, data = self._get(scope, word)
            if flag == "RJ":
                return flag, data
            values.append(data)
        if not values or len(values) > GET_SETTINGS_MAX:
            return "RJ", "BADCOMMAND"
        return "OK", " ; ".join(values)

    def _get(self, axis: int, setting: str) -> tuple[str, str]:
        device_settings = {"deviceid": self.device_id, "version": self.firmware,
                           "version.build": self.firmware_build, "system.serial": self.serial,
                           "comm.checksum": int(self.reply_checksums), "system.axiscount": 1,
                           "device.hw.modified": 0, "system.access": 1,
                           "comm.packet.size.max": PACKET_SIZE_MAX,
                           "comm.command.packets.max": COMMAND_PACKETS_MAX,
                           "comm.word.size.max": WORD_SIZE_MAX,
                           "get.settings.max": GET_SETTINGS_MAX}
        if setting in device_settings:
            if axis != 0:
                return "RJ", "DEVICEONLY"
            return "OK", str(device_settings[setting])
        values = {"pos": self._counter(), "resolution": self.resolution, "comm.alert": int(self.alerts_on),
                  "limit.cycle.dist": self.cycle, "limit.min": 0, "limit.max": self.cycle - 1,
                  **self.settings}
        if setting not in values:
            return "RJ", "BADCOMMAND"
        return "OK", str(values[setting])

    def _set(self, axis: int, setting: str, value: str) -> tuple[str, str]:
        if setting == "comm.checksum":
            if axis != 0:
                return "RJ", "DEVICEONLY"
            if value not in ("0", "1"):
                return "RJ", "BADDATA"
            self.reply_checksums = value == "1"
            return "OK", "0"
        if setting == "comm.alert":
            if value not in ("0", "1"):
                return "RJ", "BADDATA"
            self.alerts_on = value == "1"
            return "OK", "0"
        if setting not in self.settings:
            return "RJ", "BADCOMMAND"
        try:
            number = int(value)
        except ValueError:
            return "RJ", "BADDATA"
        if number <= 0:
            return "RJ", "BADDATA"
        self.settings[setting] = number
        return "OK", "0"

    def _move(self, mode: str, value: str) -> tuple[str, str]:
        try:
            number = int(value)
        except ValueError:
            return "RJ", "BADDATA"
        if mode == "abs":
            if "WR" in self.flags:
                return "RJ", "BADCOMMAND"
            if not 0 <= number < self.cycle:
                return "RJ", "BADDATA"
            # a cyclic axis takes the shorter way round
            delta = (number - self._pos + self.cycle / 2) % self.cycle - self.cycle / 2
        else:
            delta = float(number)
        self.flags.discard("NI")
        faults = [flag for fault, flag in (("stall", "FS"), ("encoder", "FQ"), ("limit", "WL"))
                  if self.take_fault(fault)]
        self._start(delta, faults[:1])
        return "OK", "0"
