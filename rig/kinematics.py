"""Light-positioner kinematics: world-frame light targets <-> machine axis coordinates.

World frame (DESIGN.md): origin on the turntable axis at the platter surface, +z up the axis,
millimetres. A :class:`~rig.device.LightTarget` gives a direction (``azimuth_deg`` from +x
towards +y, ``elevation_deg`` above the platter plane, optional ``distance_mm``) or a point
``xyz_mm``. Machine coordinates are what the GRBL controller moves (``MPos``), keyed by axis
letter.

- :class:`ArmKinematics` -- a two-axis light arm: machine X is the azimuth in degrees, machine
  Y the elevation in degrees (GRBL's steps-per-unit are set so one unit is one degree). The
  light sits at a fixed ``radius_mm`` from the arm's pivot ``centre_mm``; directions are taken
  about that pivot.
- :class:`GantryKinematics` -- an XYZ gantry in millimetres; the machine frame is placed in the
  world frame by ``origin_mm`` (world position of machine zero) and a rotation. Directions are
  taken about ``centre_mm`` at ``distance_mm`` (default ``default_distance_mm``).

``kinematics_from_config`` builds either from a rig-file value (``"arm"``, ``"gantry"`` or an
inline table with ``type = ...``). :class:`MachineMap` places the kinematics' axis coordinates
in the controller's machine space (GRBL homes to ``MPos`` = -pull-off and keeps its machine space
in [-max travel, 0]: ``machine = offset + sign * axis``). The forward maps are mirrored, for the scene renderer, in
``sims/grbl_sim.py`` (sims may not import rig); a test keeps the two in agreement.
"""
from __future__ import annotations

import abc
import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from .device import LightTarget
from .errors import LimitError


def _vec3(value: Any, what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be 3 finite numbers (x, y, z), got {value!r}")
    return arr


def _range(value: Any, what: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a pair (low, high), got {value!r}") from None
    if not lo < hi:
        raise ValueError(f"{what} must have low < high, got ({lo}, {hi})")
    return lo, hi


class Kinematics(abc.ABC):
    """Maps light targets in the world frame to machine coordinates and back."""

    kind: str = ""
    #: machine axis letters this kinematics drives, in order
    axes: tuple[str, ...] = ()

    def __init__(self, device: str = "positioner") -> None:
        self.device = device

    @abc.abstractmethod
    def inverse(self, target: LightTarget) -> dict[str, float]:
        """Machine coordinates (by axis letter) that put the light on ``target``.

        Raises
        ------
        LimitError
            If the target is out of reach; the message names the axis (or quantity) and limit.
        """

    @abc.abstractmethod
    def forward(self, machine: Mapping[str, float]) -> tuple[float, float, float]:
        """Light position in the world frame, millimetres, for machine coordinates ``machine``."""

    @abc.abstractmethod
    def to_config(self) -> dict[str, Any]:
        """The rig-file table that rebuilds this kinematics (``type`` plus parameters)."""

    def limits(self) -> dict[str, tuple[float, float]]:
        """Travel of each machine axis, in machine units."""
        return {}


class ArmKinematics(Kinematics):
    """Two-axis light arm: X = azimuth (deg), Y = elevation (deg), light at ``radius_mm``.

    Parameters
    ----------
    radius_mm : float
        Distance from the pivot to the light, millimetres.
    centre_mm : (3,) float
        Pivot position in the world frame, millimetres (normally the object centre).
    azimuth_limits_deg, elevation_limits_deg : (float, float)
        Allowed travel of the two axes, degrees. An azimuth outside its range is brought in by
        whole turns when possible (e.g. 350 -> -10 for limits (-180, 180)).
    radius_tolerance_mm : float
        How far a requested distance / point may lie off the arm's sphere.
    """

    kind = "arm"
    axes = ("X", "Y")

    def __init__(self, radius_mm: float = 500.0, centre_mm: Any = (0.0, 0.0, 0.0), *,
                 azimuth_limits_deg: Any = (-180.0, 180.0), elevation_limits_deg: Any = (0.0, 85.0),
                 radius_tolerance_mm: float = 1.0, device: str = "positioner") -> None:
        super().__init__(device)
        if not radius_mm > 0:
            raise ValueError(f"radius_mm must be > 0, got {radius_mm}")
        self.radius_mm = float(radius_mm)
        self.centre_mm = _vec3(centre_mm, "centre_mm")
        self.azimuth_limits_deg = _range(azimuth_limits_deg, "azimuth_limits_deg")
        self.elevation_limits_deg = _range(elevation_limits_deg, "elevation_limits_deg")
        if not (-90.0 <= self.elevation_limits_deg[0] and self.elevation_limits_deg[1] <= 90.0):
            raise ValueError(f"elevation_limits_deg must lie in [-90, 90], got {self.elevation_limits_deg}")
        self.radius_tolerance_mm = float(radius_tolerance_mm)

    def inverse(self, target: LightTarget) -> dict[str, float]:
        if target.xyz_mm is not None:
            d = _vec3(target.xyz_mm, "xyz_mm") - self.centre_mm
            r = float(np.linalg.norm(d))
            if abs(r - self.radius_mm) > self.radius_tolerance_mm:
                raise LimitError(r, (self.radius_mm, self.radius_mm), "mm", device=self.device,
                                 what="distance of the point from the arm pivot")
            az = math.degrees(math.atan2(d[1], d[0]))
            el = math.degrees(math.asin(max(-1.0, min(1.0, d[2] / r))))
        else:
            if target.distance_mm is not None and \
                    abs(target.distance_mm - self.radius_mm) > self.radius_tolerance_mm:
                raise LimitError(target.distance_mm, (self.radius_mm, self.radius_mm), "mm",
                                 device=self.device, what="distance (the arm radius is fixed)")
            az, el = float(target.azimuth_deg), float(target.elevation_deg)
        lo, hi = self.azimuth_limits_deg
        if not lo <= az <= hi:
            wrapped = lo + (az - lo) % 360.0  # the equivalent azimuth at or above the low limit
            if wrapped > hi:  # no whole-turn equivalent of az lies within the travel
                raise LimitError(az, (lo, hi), "deg", device=self.device, what="azimuth (machine axis X)")
            az = wrapped
        elo, ehi = self.elevation_limits_deg
        if not elo <= el <= ehi:
            raise LimitError(el, (elo, ehi), "deg", device=self.device, what="elevation (machine axis Y)")
        return {"X": az, "Y": el}

    def forward(self, machine: Mapping[str, float]) -> tuple[float, float, float]:
        az, el = math.radians(machine["X"]), math.radians(machine["Y"])
        p = self.centre_mm + self.radius_mm * np.array(
            [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        return (float(p[0]), float(p[1]), float(p[2]))

    def limits(self) -> dict[str, tuple[float, float]]:
        return {"X": self.azimuth_limits_deg, "Y": self.elevation_limits_deg}

    def to_config(self) -> dict[str, Any]:
        return {"type": "arm", "radius_mm": self.radius_mm, "centre_mm": self.centre_mm.tolist(),
                "azimuth_limits_deg": list(self.azimuth_limits_deg),
                "elevation_limits_deg": list(self.elevation_limits_deg),
                "radius_tolerance_mm": self.radius_tolerance_mm}


class GantryKinematics(Kinematics):
    """XYZ gantry, millimetres: ``world = origin_mm + R @ machine``.

    Parameters
    ----------
    origin_mm : (3,) float
        World position of machine zero (``MPos`` 0, 0, 0), millimetres.
    rotation : (3, 3) float, optional
        Columns are the machine X, Y, Z axes expressed in the world frame (orthonormal).
        Default: a rotation by ``yaw_deg`` about world +z.
    yaw_deg : float
        Used when ``rotation`` is not given.
    travel_mm : mapping of axis letter -> (low, high)
        Machine travel per axis, millimetres (GRBL homes to the top: typically (-travel, 0)).
    centre_mm : (3,) float
        Point about which direction targets are taken, world frame, millimetres.
    default_distance_mm : float
        Distance used for direction targets that give none.
    """

    kind = "gantry"
    axes = ("X", "Y", "Z")

    def __init__(self, origin_mm: Any = (0.0, 0.0, 0.0), *, rotation: Any = None, yaw_deg: float = 0.0,
                 travel_mm: Mapping[str, Any] | None = None, centre_mm: Any = (0.0, 0.0, 0.0),
                 default_distance_mm: float = 500.0, device: str = "positioner") -> None:
        super().__init__(device)
        self.origin_mm = _vec3(origin_mm, "origin_mm")
        if rotation is None:
            c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
            rotation = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        rot = np.asarray(rotation, dtype=float)
        if rot.shape != (3, 3) or not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6):
            raise ValueError(f"rotation must be an orthonormal 3x3 matrix, got {rotation!r}")
        self.rotation = rot
        travel = travel_mm or {"X": (-1000.0, 0.0), "Y": (-1000.0, 0.0), "Z": (-1000.0, 0.0)}
        unknown = set(travel) - set(self.axes)
        if unknown or len(travel) != 3:
            raise ValueError(f"travel_mm needs exactly the axes X, Y, Z, got {sorted(travel)}")
        self.travel_mm = {axis: _range(travel[axis], f"travel_mm[{axis}]") for axis in self.axes}
        self.centre_mm = _vec3(centre_mm, "centre_mm")
        if not default_distance_mm > 0:
            raise ValueError(f"default_distance_mm must be > 0, got {default_distance_mm}")
        self.default_distance_mm = float(default_distance_mm)

    def inverse(self, target: LightTarget) -> dict[str, float]:
        if target.xyz_mm is not None:
            p = _vec3(target.xyz_mm, "xyz_mm")
        else:
            az, el = math.radians(target.azimuth_deg), math.radians(target.elevation_deg)
            dist = self.default_distance_mm if target.distance_mm is None else float(target.distance_mm)
            if dist <= 0:
                raise LimitError(dist, (0.0, math.inf), "mm", device=self.device, what="distance")
            p = self.centre_mm + dist * np.array(
                [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        m = self.rotation.T @ (p - self.origin_mm)
        out = {}
        for axis, value in zip(self.axes, m):
            lo, hi = self.travel_mm[axis]
            if not lo - 1e-9 <= value <= hi + 1e-9:
                raise LimitError(float(value), (lo, hi), "mm", device=self.device,
                                 what=f"machine axis {axis}")
            out[axis] = float(value)
        return out

    def forward(self, machine: Mapping[str, float]) -> tuple[float, float, float]:
        m = np.array([machine["X"], machine["Y"], machine["Z"]], dtype=float)
        p = self.origin_mm + self.rotation @ m
        return (float(p[0]), float(p[1]), float(p[2]))

    def limits(self) -> dict[str, tuple[float, float]]:
        return dict(self.travel_mm)

    def to_config(self) -> dict[str, Any]:
        return {"type": "gantry", "origin_mm": self.origin_mm.tolist(), "rotation": self.rotation.tolist(),
                "travel_mm": {k: list(v) for k, v in self.travel_mm.items()},
                "centre_mm": self.centre_mm.tolist(), "default_distance_mm": self.default_distance_mm}


@dataclass(frozen=True)
class MachineMap:
    """Per-axis affine map from kinematic axis coordinates to controller machine coordinates:
    ``machine = offset + sign * axis`` (machine units; e.g. arm degrees to GRBL ``MPos``).

    ``offset[a]`` is the machine coordinate where axis ``a`` reads 0 (the arm's azimuth 0, say);
    ``sign[a]`` is +1 or -1 (-1 where the controller counts the other way). Axes not named map
    unchanged.
    """

    offset: dict[str, float]
    sign: dict[str, int]

    @classmethod
    def from_config(cls, offset: Mapping[str, Any] | None, sign: Mapping[str, Any] | None, *,
                    axes: tuple[str, ...] = ("X", "Y", "Z")) -> "MachineMap":
        """From the rig-file tables ``machine_offset = {X = -185.0}``, ``machine_sign = {X = -1}``."""
        out_offset, out_sign = {}, {}
        for key, table in (("machine_offset", offset), ("machine_sign", sign)):
            if table is None:
                continue
            if not isinstance(table, Mapping):
                raise ValueError(f"{key} must be a table of axis letter -> number, got {table!r}")
            for axis, value in table.items():
                if axis not in axes:
                    raise ValueError(f"{key} names axis {axis!r}; the machine axes are {', '.join(axes)}")
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                    raise ValueError(f"{key} {axis} = {value!r} must be a finite number")
                if key == "machine_sign":
                    if value not in (1, -1):
                        raise ValueError(f"machine_sign {axis} = {value!r} must be 1 or -1")
                    out_sign[axis] = int(value)
                else:
                    out_offset[axis] = float(value)
        return cls(out_offset, out_sign)

    def to_machine(self, axes: Mapping[str, float]) -> dict[str, float]:
        """Machine coordinates of kinematic axis coordinates ``axes`` (by axis letter)."""
        return {a: self.offset.get(a, 0.0) + self.sign.get(a, 1) * v for a, v in axes.items()}

    def to_axes(self, machine: Mapping[str, float]) -> dict[str, float]:
        """Kinematic axis coordinates of machine coordinates ``machine`` (inverse of to_machine)."""
        return {a: (v - self.offset.get(a, 0.0)) * self.sign.get(a, 1) for a, v in machine.items()}

    def machine_range(self, axis: str, low: float, high: float) -> tuple[float, float]:
        """The machine interval an axis interval [low, high] maps onto."""
        a, b = self.to_machine({axis: low})[axis], self.to_machine({axis: high})[axis]
        return (min(a, b), max(a, b))

    def to_config(self) -> dict[str, dict[str, float]]:
        """The rig-file keys that rebuild this map (empty where the map is the identity)."""
        out: dict[str, dict[str, float]] = {}
        if self.offset:
            out["machine_offset"] = dict(self.offset)
        if self.sign:
            out["machine_sign"] = dict(self.sign)
        return out


KINEMATICS: dict[str, type[Kinematics]] = {"arm": ArmKinematics, "gantry": GantryKinematics}


def kinematics_from_config(value: str | Mapping[str, Any] | Kinematics, *,
                           device: str = "positioner") -> Kinematics:
    """Build kinematics from a rig-file value: ``"arm"``, ``"gantry"``, or a table
    ``{type = "arm", radius_mm = 600, ...}`` whose other keys are the class's parameters."""
    if isinstance(value, Kinematics):
        return value
    params: dict[str, Any] = {"type": value} if isinstance(value, str) else dict(value)
    kind = params.pop("type", None)
    if kind not in KINEMATICS:
        raise ValueError(f"kinematics type {kind!r} is unknown; use one of {', '.join(KINEMATICS)}")
    try:
        return KINEMATICS[kind](**params, device=device)
    except TypeError as exc:
        raise ValueError(f"kinematics {kind!r}: {exc}") from None
