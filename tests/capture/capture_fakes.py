"""Small in-process fake devices implementing rig.device's ABCs, for runner and store tests.

Faults are armed like the simulators' (``dev.inject("timeout", 2)``) and consumed one call at a
time: ``timeout`` (DeviceTimeout), ``busy`` (DeviceBusy), ``garble`` (ProtocolError) and
``disconnect`` (Disconnected; the device stays down until ``connect()``).
"""
from __future__ import annotations

import hashlib
import math
import threading
import time
from collections import Counter

from rig import (Axis, Camera, DeviceBusy, DeviceTimeout, Disconnected, Frame, LightPositioner,
                 LimitError, MoveStatus, ProtocolError, Rig, reading)


class _Faulty:
    def _init_faults(self) -> None:
        self.faults: Counter[str] = Counter()
        self._connected = False
        self.connects = 0
        self.stops = 0
        self._flock = threading.Lock()

    def inject(self, fault: str, count: int = 1) -> None:
        self.faults[fault] += count

    def _fault(self) -> None:
        with self._flock:
            if not self._connected:
                raise Disconnected("not connected", device=self.name)
            for kind in ("timeout", "busy", "garble", "disconnect"):
                if self.faults[kind] > 0:
                    self.faults[kind] -= 1
                    break
            else:
                return
        if kind == "timeout":
            raise DeviceTimeout("no reply", device=self.name, timeout_s=0.01)
        if kind == "busy":
            raise DeviceBusy("busy", device=self.name)
        if kind == "garble":
            raise ProtocolError("garbled reply", device=self.name, raw=b"\x00@#")
        self._connected = False
        raise Disconnected("link lost", device=self.name)

    def connect(self) -> None:
        self._connected = True
        self.connects += 1

    def close(self) -> None:
        self._connected = False

    @property
    def connected(self) -> bool:
        return self._connected


class FakeAxis(_Faulty, Axis):
    def __init__(self, name: str, limits=(-360.0, 360.0), move_s: float = 0.0) -> None:
        super().__init__(name)
        self._init_faults()
        self._limits = limits
        self._pos = 0.0
        self.move_s = move_s
        self.moves: list[float] = []
        # set to a threading.Barrier shared by axes to prove their moves overlap in time
        self.rendezvous: threading.Barrier | None = None

    def read(self):
        return {"position": reading(self._pos, self.units)}

    def describe(self):
        return {"driver": "fake", "units": "deg", "limits": list(self._limits),
                "max_speed_deg_s": 30.0, "accel_deg_s2": 60.0}

    @property
    def position(self) -> float:
        self._fault()
        return self._pos

    @property
    def homed(self) -> bool:
        return True

    @property
    def limits(self):
        return self._limits

    def move_to(self, value: float) -> MoveStatus:
        self._fault()
        lo, hi = self._limits
        if not lo <= value <= hi:
            raise LimitError(value, self._limits, "deg", device=self.name)
        self.moves.append(value)

        def go():
            if self.rendezvous is not None:
                self.rendezvous.wait()  # BrokenBarrierError unless the other axis moves too
            time.sleep(self.move_s)
            self._pos = float(value)
        if self.move_s:
            return MoveStatus.run(go, target=value, device=self.name)
        go()
        return MoveStatus.completed(target=value, device=self.name)

    def home(self) -> MoveStatus:
        return self.move_to(0.0)

    def stop(self) -> None:
        self.stops += 1


class FakePositioner(_Faulty, LightPositioner):
    """An arm of radius 500 mm; elevation limit 0..85 deg (like the GRBL arm's default)."""

    radius_mm = 500.0

    def __init__(self, name: str = "positioner") -> None:
        super().__init__(name)
        self._init_faults()
        self._xyz = (self.radius_mm, 0.0, 0.0)
        self.moves: list = []

    def read(self):
        return {"light_mm": reading(list(self._xyz), "mm")}

    def describe(self):
        return {"driver": "fake", "units": "mm",
                "kinematics": {"type": "arm", "radius_mm": self.radius_mm,
                               "azimuth_limits_deg": [-180.0, 180.0],
                               "elevation_limits_deg": [0.0, 85.0]}}

    def move_to(self, target) -> MoveStatus:
        self._fault()
        if target.xyz_mm is not None:
            self._xyz = tuple(float(v) for v in target.xyz_mm)
        else:
            az, el = math.radians(target.azimuth_deg), math.radians(target.elevation_deg)
            r = self.radius_mm
            self._xyz = (r * math.cos(el) * math.cos(az), r * math.cos(el) * math.sin(az), r * math.sin(el))
        self.moves.append(target)
        return MoveStatus.completed(target=target, device=self.name)

    @property
    def light_position_mm(self):
        self._fault()
        return self._xyz

    @property
    def homed(self) -> bool:
        return True

    def home(self) -> MoveStatus:
        return MoveStatus.completed(device=self.name)

    def stop(self) -> None:
        self.stops += 1


class FakeCamera(_Faulty, Camera):
    """Returns ``frame_bytes`` bytes per capture: unique per shot, or, with ``constant=True``,
    a function of the exposure only (so identical captures dedupe)."""

    def __init__(self, name: str = "camera", frame_bytes: int = 4096, constant: bool = False,
                 capture_s: float = 0.0) -> None:
        super().__init__(name)
        self._init_faults()
        self.frame_bytes = frame_bytes
        self.constant = constant
        self.capture_s = capture_s
        self._exposure = 0.01
        self._iso = 100.0
        self.shots = 0

    def read(self):
        return {"exposure_s": reading(self._exposure, "s")}

    def describe(self):
        return {"driver": "fake", "frame_bytes": self.frame_bytes, "exposure_range_s": [1e-4, 30.0]}

    @property
    def exposure_s(self) -> float:
        return self._exposure

    def set_exposure(self, seconds: float) -> float:
        self._fault()
        self._exposure = float(seconds)
        return self._exposure

    @property
    def iso(self):
        return self._iso

    def set_iso(self, iso: float) -> float:
        self._fault()
        self._iso = float(iso)
        return self._iso

    def capture(self) -> Frame:
        self._fault()
        time.sleep(self.capture_s)
        self.shots += 1
        seed = f"{self._exposure}" if self.constant else f"{self._exposure}-{self.shots}-{time.time_ns()}"
        block = hashlib.sha256(seed.encode()).digest()
        data = (block * (self.frame_bytes // 32 + 1))[: self.frame_bytes]
        return Frame(data=data, filename=f"IMG_{self.shots:04d}.DNG", exposure_s=self._exposure,
                     iso=self._iso, metadata={"handle": self.shots})


def make_rig(*, frame_bytes: int = 4096, constant: bool = False, move_s: float = 0.0,
             capture_s: float = 0.0, connect: bool = True) -> Rig:
    rig = Rig(turntable=FakeAxis("turntable", move_s=move_s), positioner=FakePositioner(),
              polarizer=FakeAxis("polarizer", limits=(0.0, 360.0)),
              camera=FakeCamera(frame_bytes=frame_bytes, constant=constant, capture_s=capture_s),
              config={"rig": {"name": "fake"}})
    if connect:
        rig.connect()
    return rig


SMALL_PLAN = {
    "name": "small",
    "turntable": {"angles_deg": [0, 90, 180]},
    "light": {"azimuth_deg": [0, 90], "elevation_deg": [30]},
    "polarizer": {"angles_deg": [0, 90]},
    "exposure": {"base_s": 0.01, "stops": [-1, 1]},
}


def tolerant_sim_config(turntable_timeout_s: float = 5.0) -> dict:
    """A rig config serving every role from the simulated lab (``port = "sim"``) with reply
    timeouts well above the drivers' defaults (0.5-1 s): on a loaded or swapping machine a
    simulator thread can stall that long, and the tests must not read that as a device fault."""
    return {"turntable": {"driver": "zaber", "port": "sim", "timeout_s": turntable_timeout_s},
            "positioner": {"driver": "grbl", "port": "sim", "timeout_s": 5.0},
            "polarizer": {"driver": "elliptec", "port": "sim", "timeout_s": 5.0},
            "camera": {"driver": "ptp", "port": "sim"}}
