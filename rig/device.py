"""The device API every driver implements (see docs/measurements.md).

- Every device: ``connect()``, ``close()``, ``read() -> dict``, ``describe() -> dict``, and use as a
  context manager.
- Axes (turntable, polarizer, each positioner): ``move_to(value) -> MoveStatus`` returning at once,
  ``stop()``, ``home() -> MoveStatus``, ``position``, ``homed``, ``limits``, ``units``.
- Cameras: ``exposure_s`` / ``iso`` settings, ``capture() -> Frame``, ``bracket(exposures)``.

Units at this level are degrees and millimetres (and seconds for exposure).
"""
from __future__ import annotations

import abc
import math
import numbers
import time
from dataclasses import dataclass, field
from typing import Any

from .status import MoveStatus


def reading(value: Any, units: str = "", timestamp: float | None = None) -> dict[str, Any]:
    """One entry of ``Device.read()``: ``{"value": v, "units": u, "timestamp": t}`` (Unix seconds)."""
    return {"value": value, "units": units, "timestamp": time.time() if timestamp is None else timestamp}


class Device(abc.ABC):
    """Base of all drivers. ``name`` is the role in the rig (``turntable``, ``camera`` ...)."""

    def __init__(self, name: str) -> None:
        self.name = name

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the link and check the device answers (raises ``Disconnected`` / ``DeviceTimeout``)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the link. Safe to call twice."""

    @abc.abstractmethod
    def read(self) -> dict[str, dict[str, Any]]:
        """Current state, each entry made by :func:`reading` (value, units, timestamp)."""

    @abc.abstractmethod
    def describe(self) -> dict[str, Any]:
        """Static facts: driver, model, firmware, serial number, limits, units, port."""

    @property
    def connected(self) -> bool:
        return False

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}>"


class Axis(Device):
    """A single motorised axis (rotary in degrees or linear in millimetres)."""

    units: str = "deg"

    @property
    @abc.abstractmethod
    def position(self) -> float:
        """Read-back position in ``units`` (queried from the device)."""

    @property
    @abc.abstractmethod
    def homed(self) -> bool:
        """True once the axis has a valid reference."""

    @property
    @abc.abstractmethod
    def limits(self) -> tuple[float, float]:
        """Allowed travel ``(low, high)`` in ``units``."""

    @abc.abstractmethod
    def move_to(self, value: float) -> MoveStatus:
        """Start an absolute move and return at once; ``status.wait()`` blocks until it ends."""

    @abc.abstractmethod
    def home(self) -> MoveStatus:
        """Start the homing run and return at once."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop motion now (decelerating where the device allows)."""

    def move_by(self, delta: float) -> MoveStatus:
        """Relative move by ``delta`` in ``units`` (jogging)."""
        return self.move_to(self.position + delta)


@dataclass(frozen=True)
class Frame:
    """One image as the camera delivered it.

    Attributes
    ----------
    data : bytes
        The camera's own file, untouched (DNG, CR2, NEF ...).
    filename : str
        The camera's name for it (``IMG_0001.DNG``).
    exposure_s : float
        Exposure time the camera reports for this frame, seconds.
    iso : float or None
        ISO / exposure index the camera reports.
    fnumber : float or None
        Aperture the camera reports.
    timestamp : float
        Capture time, Unix seconds (host clock at the capture-complete event).
    metadata : dict
        Anything else the camera reported (object handle, format code, size ...).
    """

    data: bytes
    filename: str
    exposure_s: float
    iso: float | None = None
    fnumber: float | None = None
    timestamp: float = field(default_factory=time.time)
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def format(self) -> str:
        return self.filename.rsplit(".", 1)[-1].lower() if "." in self.filename else "bin"


class Camera(Device):
    """A tethered still camera."""

    @property
    @abc.abstractmethod
    def exposure_s(self) -> float:
        """Current exposure time, seconds (as the camera reports it)."""

    @abc.abstractmethod
    def set_exposure(self, seconds: float) -> float:
        """Set the exposure time; return the value the camera actually took (its nearest step)."""

    @property
    @abc.abstractmethod
    def iso(self) -> float | None:
        """Current ISO / exposure index, or None if the body does not report it."""

    @abc.abstractmethod
    def set_iso(self, iso: float) -> float:
        """Set the ISO; return the value the camera took."""

    @abc.abstractmethod
    def capture(self) -> Frame:
        """Take one picture with the current settings and return its file."""

    def bracket(self, exposures_s: list[float]) -> list[Frame]:
        """One frame per exposure time (seconds), in the given order; restores the old exposure.

        Raises
        ------
        ValueError
            Before anything is captured, if the list is empty or an entry is not a positive
            finite number of seconds (so a typo at the end does not waste the first exposures).
        """
        times = []
        for i, t in enumerate(exposures_s):
            if not (isinstance(t, numbers.Real) and math.isfinite(t) and t > 0):
                raise ValueError(f"exposures_s[{i}] = {t!r} is not a positive finite time in seconds")
            times.append(float(t))
        if not times:
            raise ValueError("exposures_s is empty: give at least one exposure time in seconds")
        original = self.exposure_s
        frames = []
        try:
            for t in times:
                self.set_exposure(t)
                frames.append(self.capture())
        finally:
            self.set_exposure(original)
        return frames


@dataclass(frozen=True)
class LightTarget:
    """Where the light should go, in the world (turntable) frame: origin on the turntable axis at
    the platter surface, +z up the axis, millimetres.

    Give either a direction (``azimuth_deg`` from +x towards +y, ``elevation_deg`` above the
    platter plane) with an optional ``distance_mm`` (default: the positioner's own radius), or
    a point ``xyz_mm``.
    """

    azimuth_deg: float | None = None
    elevation_deg: float | None = None
    distance_mm: float | None = None
    xyz_mm: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        has_dir = self.azimuth_deg is not None and self.elevation_deg is not None
        if has_dir == (self.xyz_mm is not None):
            raise ValueError("LightTarget needs either azimuth_deg and elevation_deg, or xyz_mm")
        # a NaN would otherwise slip through every limit comparison and reach the G-code
        for name in ("azimuth_deg", "elevation_deg", "distance_mm"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, numbers.Real) and math.isfinite(value)):
                raise ValueError(f"LightTarget.{name} must be a finite number, got {value!r}")
        if self.distance_mm is not None and self.distance_mm <= 0:
            raise ValueError(f"LightTarget.distance_mm must be > 0, got {self.distance_mm!r}")
        if self.xyz_mm is not None:
            try:
                ok = len(self.xyz_mm) == 3 and all(math.isfinite(float(v)) for v in self.xyz_mm)
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise ValueError(f"LightTarget.xyz_mm must be 3 finite numbers (mm), got {self.xyz_mm!r}")

    def __str__(self) -> str:
        if self.xyz_mm is not None:
            return "xyz=({:.1f}, {:.1f}, {:.1f}) mm".format(*self.xyz_mm)
        d = "" if self.distance_mm is None else f" r={self.distance_mm:g} mm"
        return f"az={self.azimuth_deg:g}° el={self.elevation_deg:g}°{d}"


class LightPositioner(Device):
    """Moves the point light around the object (a light stage arm or an XYZ gantry)."""

    @abc.abstractmethod
    def move_to(self, target: LightTarget) -> MoveStatus:
        """Start moving the light to ``target``; return at once. Raises ``LimitError`` at once if
        the kinematics cannot reach it."""

    @property
    @abc.abstractmethod
    def light_position_mm(self) -> tuple[float, float, float]:
        """Read-back light position in the world frame, millimetres (via the kinematics)."""

    @property
    @abc.abstractmethod
    def homed(self) -> bool:
        """True once the machine is homed and unlocked."""

    @abc.abstractmethod
    def home(self) -> MoveStatus:
        """Start the homing cycle; return at once."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop motion now (feed hold and flush)."""
