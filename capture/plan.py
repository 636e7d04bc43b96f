"""Capture plans: what to measure, validated, expanded into motion-minimising steps.

A plan is a TOML file (or :class:`Plan` built in Python)::

    name = "teapot"                 # optional: object, operator, notes
    repeats = 1                     # captures of each bracket at each pose

    [turntable]
    angles_deg = { start = 0, stop = 330, step = 30 }    # or a list [0, 45, 90]

    [light]                         # a grid of directions ...
    azimuth_deg = [0, 60, 120, 180, 240, 300]
    elevation_deg = { start = 15, stop = 75, step = 30 }
    # distance_mm = 600             # optional; default: the positioner's own radius
    # ... or explicit points in the world (turntable) frame:
    # xyz_mm = [[300, 0, 400], [0, 300, 400]]
    # held_out_deg = [[30, 40]]     # [azimuth, elevation] lights captured at every pose but
                                    # never fitted: they score the reconstruction

    [polarizer]
    angles_deg = [0, 90]            # parallel / crossed; or  count = 4  (0, 45, 90, 135)

    [exposure]
    base_s = 0.02
    stops = [-2, 0, 2]              # bracket: base * 2**stop
    iso = 100
    # auto = true                   # meter first (raw histogram); bracket = metered * 2**stop
    # highlight = 0.8               # where the 99.5th percentile of the raw values should land

    [[calibration]]                 # named calibration captures
    kind = "dark"                   # dark | checkerboard | handheld_board | spheres | gray_card
    frames = 5                      # | mirror_probe | passive | passive_sphere

    [[calibration]]
    kind = "handheld_board"         # the board held in front of the camera, a new pose per view
    views = 12                      # (intrinsics: tilted about both axes, covering the frame)

Any list of numbers may be written as ``{ start, stop, step }`` (``stop`` included when the grid
lands on it). With ``exposure.auto = true`` the runner meters the scene first and the bracket
becomes ``metered * 2**stop`` (see :class:`Exposure`). Units: degrees, millimetres, seconds.
Validation errors are :class:`PlanError` and name the field, e.g. ``light.elevation_deg[3] = 95 is outside the positioner's limit 0..85``.

Expansion orders the measurement grid so motion time is smallest: each loop level is one axis
(turntable, light elevation, light azimuth, polarizer), inner loops run serpentine (reversed on
every other pass, so consecutive steps move one axis by one grid step), and the nesting order is
the permutation with the least estimated motion time, using the devices' speeds from
``describe()`` (or defaults). Faster axes therefore end up inside.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable, Sequence

from rig.device import LightTarget
from rig.errors import LimitError
from rig.motion import move_time_s
from rig.tomlfile import read_toml

#: The scene targets: what stands in front of the camera for a step, and what the operator does
#: to set it up. One vocabulary: a calibration kind is named after its target, and the simulated
#: lab (``sims.world.SimWorld.set_scene``) stages a scene under the same name.
SCENE_TARGETS = {
    "object": "put the object on the turntable",
    "dark": "put the lens cap on",
    "checkerboard": "put the checkerboard target on the turntable",
    "handheld_board": "hold the calibration board in front of the camera",
    "spheres": "put the calibration spheres on the turntable",
    "gray_card": "put the gray card on the turntable",
    "mirror_probe": "put the mirror sphere on the turntable",
    "passive": "put the object on the turntable, lamp off, room lit",
    "passive_sphere": "put the sample sphere on its stand at the turntable's centre, lamp off, room lit",
}

CALIBRATION_KINDS = {
    # kind (= its scene target): (default frames, default light use)
    "dark": (5, "none"),
    "checkerboard": (1, "first"),
    # the board held (or on a tripod) in free poses for the intrinsics; lit by the room or a
    # light on the camera, so the positioner stays where it is
    "handheld_board": (1, "none"),
    "spheres": (1, "grid"),
    "gray_card": (1, "grid"),
    "mirror_probe": (1, "none"),
    # the object lit by the room alone (lamp off): passive reflectometry's input
    "passive": (1, "none"),
    # a homogeneous sphere of the sample material lit by the room alone: passive reflectometry
    # within its assumption (one material, a known curved shape)
    "passive_sphere": (1, "none"),
}

#: hand-held board views a plan takes when it names no count, and the fewest it accepts
HANDHELD_VIEWS_DEFAULT = 12
HANDHELD_VIEWS_MIN = 3
#: motion model defaults where a device's describe() gives none (speed unit/s, accel unit/s^2)
DEFAULT_SPEEDS = {
    "turntable": (20.0, 40.0),     # deg/s, deg/s^2 (Zaber rotary stage, conservative)
    "positioner": (15.0, 30.0),    # deg/s of each arm joint, or mm/s for a gantry
    "polarizer": (180.0, 720.0),   # deg/s (Elliptec ELL14)
}
DEFAULT_FRAME_BYTES = 25_000_000
USB_BYTES_PER_S = 35e6
#: per-frame overhead beyond the exposure time: shutter and readout, then the USB transfer, s
DEFAULT_FRAME_OVERHEAD_S = 0.2 + DEFAULT_FRAME_BYTES / USB_BYTES_PER_S


#: caps on a plan, counted before anything is expanded: values past them are surely typos (a
#: 10^9-step plan once ran until memory ran out); split a bigger measurement into sessions
MAX_VALUES = 100_000        # values in one list or range
MAX_STEPS = 200_000         # steps of a whole plan
MAX_FRAMES = 1_000_000      # frames of a whole plan
MAX_REPEATS = 1_000         # repeats, and frames of one calibration step
MAX_STOPS = 64              # exposures in a bracket
MAX_EXPOSURE_S = 3600.0     # one exposure (base_s x 2^stop, or a calibration's own), seconds
MIN_EXPOSURE_S = 1e-6       # below any shutter's shortest time


class PlanError(ValueError):
    """The plan is malformed or unreachable; the message names the field and the reason."""


# -- the plan dataclasses ---------------------------------------------------------------------
@dataclass(frozen=True)
class LightGrid:
    """Light positions, either a grid of directions or explicit points.

    Attributes
    ----------
    azimuth_deg, elevation_deg : tuple of float
        Directions in the world (turntable) frame: azimuth from +x towards +y, elevation above
        the platter plane, degrees. The grid is their Cartesian product.
    distance_mm : float or None
        Light distance from the origin, mm (None: the positioner's own radius).
    xyz_mm : tuple of (x, y, z) or None
        Explicit light points in the world frame, mm (instead of the grid), visited in order.
    held_out_deg : tuple of (azimuth, elevation)
        Extra light directions (degrees, at ``distance_mm``) captured at every turntable and
        polarizer pose like the grid, but marked ``held_out``: never given to a fitter, used to
        score renders of the recovered model.
    """

    azimuth_deg: tuple[float, ...] = ()
    elevation_deg: tuple[float, ...] = ()
    distance_mm: float | None = None
    xyz_mm: tuple[tuple[float, float, float], ...] | None = None
    held_out_deg: tuple[tuple[float, float], ...] = ()

    @property
    def count(self) -> int:
        if self.xyz_mm is not None:
            return len(self.xyz_mm)
        return len(self.azimuth_deg) * len(self.elevation_deg)

    def targets(self) -> list[LightTarget]:
        """Every light position as a step's ``light`` (grid order: elevation, azimuth)."""
        if self.xyz_mm is not None:
            return [LightTarget(xyz_mm=tuple(p)) for p in self.xyz_mm]
        return [LightTarget(az, el, self.distance_mm) for el in self.elevation_deg for az in self.azimuth_deg]

    def held_out_targets(self) -> list[LightTarget]:
        """The held-out light positions as steps' ``light``."""
        return [LightTarget(az, el, self.distance_mm) for az, el in self.held_out_deg]


def light_to_dict(light: LightTarget | None) -> dict[str, Any] | None:
    """A step's light as the store and the journal keep it: ``{azimuth_deg, elevation_deg[,
    distance_mm]}`` or ``{xyz_mm: [x, y, z]}`` (None: the step leaves the light alone)."""
    if light is None:
        return None
    if light.xyz_mm is not None:
        return {"xyz_mm": list(light.xyz_mm)}
    d: dict[str, Any] = {"azimuth_deg": light.azimuth_deg, "elevation_deg": light.elevation_deg}
    if light.distance_mm is not None:
        d["distance_mm"] = light.distance_mm
    return d


def light_from_dict(d: dict[str, Any] | None) -> LightTarget | None:
    """The inverse of :func:`light_to_dict` (``ValueError`` naming what is wrong)."""
    if d is None:
        return None
    if not isinstance(d, dict) or set(d) - {"azimuth_deg", "elevation_deg", "distance_mm", "xyz_mm"}:
        raise ValueError(f"a step's light must be {{azimuth_deg, elevation_deg[, distance_mm]}} or "
                         f"{{xyz_mm}}, got {d!r}")
    xyz = d.get("xyz_mm")
    return LightTarget(d.get("azimuth_deg"), d.get("elevation_deg"), d.get("distance_mm"),
                       None if xyz is None else tuple(xyz))


@dataclass(frozen=True)
class Exposure:
    """Exposure bracket: ``base_s * 2**stop`` for each stop, seconds; ``iso`` optional.

    With ``auto=True`` the runner meters the scene first (:mod:`capture.metering`: the raw
    histogram of shots starting at ``base_s``) so that the highlights reach ``highlight`` of the
    raw range, and the bracket becomes ``metered * 2**stop``; the metering is stored with the
    session and reused on resume.
    """

    base_s: float = 0.01
    stops: tuple[float, ...] = (0.0,)
    iso: float | None = None
    auto: bool = False
    highlight: float = 0.8

    @property
    def exposures_s(self) -> tuple[float, ...]:
        return tuple(self.base_s * 2.0 ** s for s in self.stops)


@dataclass(frozen=True)
class Calibration:
    """A named calibration capture.

    Attributes
    ----------
    kind : str
        One of ``dark``, ``checkerboard``, ``handheld_board``, ``spheres``, ``gray_card``,
        ``mirror_probe``, ``passive``, ``passive_sphere``.
    frames : int or None
        Captures per pose (None: the kind's default; dark frames default to 5).
    exposure_s : float, tuple of float or None
        Single exposure, or the calibration's own bracket (a mirror probe: the room's range
        outruns one raw), seconds (None: the measurement bracket; dark frames match every
        exposure of the bracket).
    turntable_angles_deg : tuple of float or None
        Turntable angles (checkerboard: the target imaged at several angles, for the axis);
        None: the first measurement angle (8 evenly spaced angles for ``checkerboard``).
    lights : str or None
        ``grid`` (every light position), ``first`` or ``none`` (None: the kind's default).
    when : str
        ``before`` or ``after`` the measurement.
    views : int or None
        ``handheld_board`` only: board poses (one step each; None: :data:`HANDHELD_VIEWS_DEFAULT`).
    """

    kind: str
    frames: int | None = None
    exposure_s: float | tuple[float, ...] | None = None
    turntable_angles_deg: tuple[float, ...] | None = None
    lights: str | None = None
    when: str = "before"
    views: int | None = None

    @property
    def exposures_s(self) -> tuple[float, ...] | None:
        """The calibration's own exposures, seconds (None: the measurement bracket)."""
        if self.exposure_s is None:
            return None
        return tuple(self.exposure_s) if isinstance(self.exposure_s, tuple) else (self.exposure_s,)


@dataclass(frozen=True)
class Plan:
    """A whole capture plan. Angles in degrees, distances in mm, times in seconds."""

    turntable_deg: tuple[float, ...] = ()
    light: LightGrid | None = None
    polarizer_deg: tuple[float, ...] = ()
    exposure: Exposure = field(default_factory=Exposure)
    repeats: int = 1
    calibration: tuple[Calibration, ...] = ()
    name: str = ""
    object: str = ""
    operator: str = ""
    notes: str = ""

    def __post_init__(self) -> None:
        # coerce Python-built plans to the canonical tuple form, then validate
        object.__setattr__(self, "turntable_deg", tuple(float(v) for v in self.turntable_deg))
        object.__setattr__(self, "polarizer_deg", tuple(float(v) for v in self.polarizer_deg))
        object.__setattr__(self, "calibration", tuple(self.calibration))
        _validate(self)

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_toml(cls, path: str | Path) -> "Plan":
        """Read and validate a plan file (errors name the file and the field)."""
        path = Path(path)
        data = read_toml(path, error=PlanError, what="plan file")
        try:
            return cls.from_dict(data)
        except PlanError as exc:
            raise PlanError(f"{path}: {exc}") from None

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Plan":
        """Build from a dict shaped like the TOML file (also accepts :meth:`to_dict` output)."""
        return _parse(data)

    def to_dict(self) -> dict[str, Any]:
        """Canonical form: every range expanded to a list, every number a float (except counts),
        defaults filled in. ``Plan.from_dict(p.to_dict()) == p``."""
        d: dict[str, Any] = {"name": self.name, "object": self.object, "operator": self.operator,
                             "notes": self.notes, "repeats": self.repeats,
                             "exposure": {"base_s": self.exposure.base_s, "stops": list(self.exposure.stops),
                                          "iso": self.exposure.iso}}
        if self.exposure.auto:
            d["exposure"].update(auto=True, highlight=self.exposure.highlight)
        if self.turntable_deg:
            d["turntable"] = {"angles_deg": list(self.turntable_deg)}
        if self.polarizer_deg:
            d["polarizer"] = {"angles_deg": list(self.polarizer_deg)}
        if self.light is not None:
            if self.light.xyz_mm is not None:
                d["light"] = {"xyz_mm": [list(p) for p in self.light.xyz_mm]}
            else:
                d["light"] = {"azimuth_deg": list(self.light.azimuth_deg),
                              "elevation_deg": list(self.light.elevation_deg),
                              "distance_mm": self.light.distance_mm}
                if self.light.held_out_deg:
                    d["light"]["held_out_deg"] = [list(p) for p in self.light.held_out_deg]
        d["calibration"] = [
            {"kind": c.kind, "frames": c.frames,
             "exposure_s": list(c.exposure_s) if isinstance(c.exposure_s, tuple) else c.exposure_s,
             "turntable_angles_deg": None if c.turntable_angles_deg is None else list(c.turntable_angles_deg),
             "lights": c.lights, "when": c.when, "views": c.views} for c in self.calibration]
        return _drop_none(d)

    @property
    def hash(self) -> str:
        """SHA-256 of the canonical JSON of :meth:`to_dict` (what ``resume`` compares)."""
        return plan_hash(self.to_dict())

    # -- validation against a rig -------------------------------------------------------------
    def check_rig(self, rig: Any) -> None:
        """Check the plan against a rig: needed devices fitted, values inside their limits.

        Limits come from each device's ``limits`` / ``describe()``. Raises :class:`PlanError`
        naming the field, value and limit.
        """
        desc = _describe(rig)
        _need(self.turntable_deg, rig, "turntable", "turntable.angles_deg")
        _need(self.polarizer_deg, rig, "polarizer", "polarizer.angles_deg")
        _need(self.light is not None and self.light.count > 0, rig, "positioner", "light")
        if getattr(rig, "camera", None) is None:
            raise PlanError("the rig has no camera; a plan needs one to capture anything")
        for role, label, values in (("turntable", "turntable.angles_deg", self.turntable_deg),
                                    ("polarizer", "polarizer.angles_deg", self.polarizer_deg)):
            device = getattr(rig, role, None)
            if device is not None:
                _check_limits(label, values, _axis_limits(device), f"the {role}'s limit", "")
        for i, c in enumerate(self.calibration):
            if c.turntable_angles_deg and rig.turntable is not None:
                _check_limits(f"calibration[{i}].turntable_angles_deg", c.turntable_angles_deg,
                              _axis_limits(rig.turntable), "the turntable's limit", "")
        if self.light is not None and rig.positioner is not None:
            _check_reach(self.light, desc.get("positioner", {}))
        cd = desc.get("camera", {})
        lim = limit_from_describe(cd, "exposure")
        if lim is not None:
            for i, (stop, t) in enumerate(zip(self.exposure.stops, self.exposure.exposures_s)):
                if not lim[0] * (1 - 1e-9) <= t <= lim[1] * (1 + 1e-9):
                    raise PlanError(f"exposure.stops[{i}] = {stop:g} gives {t:g} s, outside the "
                                    f"camera's range {lim[0]:g}..{lim[1]:g} s")
            for i, c in enumerate(self.calibration):
                if c.exposure_s is not None:
                    _check_limits(f"calibration[{i}].exposure_s", list(c.exposures_s), lim,
                                  "the camera's range", " s", indexed=False)
        if self.exposure.iso is not None:
            _check_limits("exposure.iso", [self.exposure.iso], limit_from_describe(cd, "iso"),
                          "the camera's range", "", indexed=False)

    # -- expansion ----------------------------------------------------------------------------
    def steps(self, rig: Any = None) -> list["Step"]:
        """Expand into ordered steps: calibrations marked ``before``, the measurement grid in
        motion-minimising order, then calibrations marked ``after``."""
        model = MotionModel.from_rig(rig)
        before = [s for c in self.calibration if c.when == "before" for s in self._calibration_steps(c)]
        after = [s for c in self.calibration if c.when == "after" for s in self._calibration_steps(c)]
        return [replace(s, index=i) for i, s in enumerate([*before, *self._measure_steps(model), *after])]

    def _measure_steps(self, model: "MotionModel") -> list["Step"]:
        axes: list[tuple[str, list[Any]]] = []
        if self.turntable_deg:
            axes.append(("turntable", list(self.turntable_deg)))
        if self.light is not None:
            if self.light.xyz_mm is not None:
                axes.append(("light_xyz", [tuple(p) for p in self.light.xyz_mm]))
            else:
                axes.append(("light_el", list(self.light.elevation_deg)))
                axes.append(("light_az", list(self.light.azimuth_deg)))
        if self.polarizer_deg:
            axes.append(("polarizer", list(self.polarizer_deg)))
        if not axes:
            return []
        order = _best_nesting(axes, model)
        names = [axes[i][0] for i in order]
        steps = []
        for combo in _serpentine([axes[i][1] for i in order]):
            steps.append(self._measure_step(dict(zip(names, combo))))
        if self.light is not None and self.light.held_out_deg:
            # held-out lights: the same turntable and polarizer poses, after the grid
            levels = [list(self.turntable_deg) or [None], list(self.light.held_out_deg),
                      list(self.polarizer_deg) or [None]]
            for a, (az, el), pol in _serpentine(levels):
                steps.append(replace(self._measure_step({"turntable": a, "light_az": az, "light_el": el,
                                                         "polarizer": pol}), held_out=True))
        return steps

    def _measure_step(self, v: dict[str, Any]) -> "Step":
        return Step(index=0, kind="measure", target="object", turntable_deg=v.get("turntable"),
                    light=self._light_of(v), polarizer_deg=v.get("polarizer"),
                    exposures_s=self.exposure.exposures_s, repeats=self.repeats,
                    iso=self.exposure.iso, auto_exposure=self.exposure.auto)

    def _light_of(self, v: dict[str, Any]) -> LightTarget | None:
        if "light_xyz" in v:
            return LightTarget(xyz_mm=tuple(v["light_xyz"]))
        if "light_az" in v:
            return LightTarget(v["light_az"], v["light_el"], self.light.distance_mm)
        return None

    def _calibration_steps(self, c: Calibration) -> list["Step"]:
        default_frames, default_lights = CALIBRATION_KINDS[c.kind]
        frames = c.frames or default_frames
        lights = c.lights or default_lights
        if c.exposure_s is not None:
            exposures = c.exposures_s
        else:
            exposures = tuple(sorted(set(self.exposure.exposures_s)))
        pol = None if c.kind == "dark" or not self.polarizer_deg else self.polarizer_deg[0]
        if c.kind == "handheld_board":  # one step per pose; the turntable and the light stay put
            views = c.views or HANDHELD_VIEWS_DEFAULT
            return [Step(index=0, kind=c.kind, target=c.kind, turntable_deg=None, light=None,
                         polarizer_deg=pol, exposures_s=exposures, repeats=frames, iso=self.exposure.iso,
                         auto_exposure=self.exposure.auto and c.exposure_s is None, view=k, views=views)
                    for k in range(views)]
        if c.turntable_angles_deg is not None:
            angles: list[float | None] = list(c.turntable_angles_deg)
        elif c.kind == "checkerboard" and self.turntable_deg:
            angles = [self.turntable_deg[0] + k * 45.0 for k in range(8)]
        else:
            angles = [self.turntable_deg[0] if self.turntable_deg else None]
        # held-out lights are calibrated like the grid's (a ``grid`` calibration covers them)
        all_lights = [*self.light.targets(), *self.light.held_out_targets()] if self.light is not None else []
        light_list: list[LightTarget | None] = {"grid": all_lights, "first": all_lights[:1]}.get(lights, [])
        light_list = light_list or [None]
        # dark frames: lens cap on, nothing needs to move
        out = []
        for a, lt in _serpentine([angles, light_list]):
            out.append(Step(index=0, kind=c.kind, target=c.kind,
                            turntable_deg=None if c.kind == "dark" else a,
                            light=None if c.kind == "dark" else lt, polarizer_deg=pol,
                            exposures_s=exposures, repeats=frames, iso=self.exposure.iso,
                            auto_exposure=self.exposure.auto and c.exposure_s is None))
        return out

    def estimate(self, rig: Any = None, steps: Sequence["Step"] | None = None) -> "Estimate":
        """Steps, frames, bytes and duration of the plan on ``rig`` (or default speeds)."""
        model = MotionModel.from_rig(rig)
        steps = self.steps(rig) if steps is None else steps
        return model.estimate(steps)


@dataclass(frozen=True)
class Step:
    """One pose of the rig and the frames captured there.

    Attributes
    ----------
    index : int
        Position in execution order (0-based).
    kind : str
        ``measure`` or a calibration kind (``dark``, ``checkerboard`` ...).
    target : str
        What must be in front of the camera: a key of :data:`SCENE_TARGETS`.
    turntable_deg, polarizer_deg : float or None
        Axis targets, degrees (None: leave where it is).
    light : rig.LightTarget or None
        Where the light goes, world (turntable) frame (stored as :func:`light_to_dict`); None:
        leave the light where it is.
    exposures_s : tuple of float
        The bracket, seconds, captured in this order (with ``auto_exposure``: nominal values,
        scaled at run time by metered / ``base_s``).
    repeats : int
        Captures of the whole bracket.
    iso : float or None
    auto_exposure : bool
        The bracket follows the session's metered exposure.
    held_out : bool
        A measurement at a held-out light (:attr:`LightGrid.held_out_deg`): scores, never fits.
    view, views : int or None
        ``handheld_board`` steps: which board pose (0-based) of how many (see
        :func:`sims.handheld.handheld_view`); None for other steps.
    """

    index: int
    kind: str
    target: str
    turntable_deg: float | None
    light: LightTarget | None
    polarizer_deg: float | None
    exposures_s: tuple[float, ...]
    repeats: int = 1
    iso: float | None = None
    auto_exposure: bool = False
    held_out: bool = False
    view: int | None = None
    views: int | None = None

    @property
    def frames(self) -> int:
        return len(self.exposures_s) * self.repeats

    def to_dict(self) -> dict[str, Any]:
        return {"index": self.index, "kind": self.kind, "target": self.target,
                "turntable_deg": self.turntable_deg, "light": light_to_dict(self.light),
                "polarizer_deg": self.polarizer_deg, "exposures_s": list(self.exposures_s),
                "repeats": self.repeats, "iso": self.iso, "frames": self.frames,
                "auto_exposure": self.auto_exposure, **({"held_out": True} if self.held_out else {}),
                **({"view": self.view, "views": self.views} if self.view is not None else {})}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Step":
        return cls(index=d["index"], kind=d["kind"], target=d["target"],
                   turntable_deg=d["turntable_deg"], light=light_from_dict(d["light"]),
                   polarizer_deg=d["polarizer_deg"], exposures_s=tuple(d["exposures_s"]),
                   repeats=d["repeats"], iso=d.get("iso"), auto_exposure=d.get("auto_exposure", False),
                   held_out=d.get("held_out", False), view=d.get("view"), views=d.get("views"))


def step_prompt(step: Step) -> str:
    """What the operator must set up for ``step``: its scene target's instruction, and for a
    hand-held board view which view it is and how to hold the board."""
    text = SCENE_TARGETS.get(step.target, f"set up {step.target}")
    if step.view is not None and step.views is not None:
        from sims.handheld import handheld_view   # here, not at the top: numpy would load with every plan and store
        text = f"{text}: {handheld_view(step.view, step.views).prompt}"
    return text


@dataclass(frozen=True)
class Estimate:
    """What a plan will take. Times in seconds, sizes in bytes.

    ``frame_bytes`` is the size assumed per frame and ``frame_bytes_source`` where it came from:
    ``camera`` (its describe()), ``measured`` (frames already stored) or ``default`` (the camera
    cannot tell: :data:`DEFAULT_FRAME_BYTES` is assumed until the first frame is captured).
    """

    steps: int
    frames: int
    bytes: int
    motion_s: float
    exposure_s: float
    overhead_s: float
    frame_bytes: int = DEFAULT_FRAME_BYTES
    frame_bytes_source: str = "default"

    @property
    def seconds(self) -> float:
        return self.motion_s + self.exposure_s + self.overhead_s

    @property
    def frame_bytes_assumed(self) -> bool:
        """True when the bytes are a guess (the camera does not report its image size)."""
        return self.frame_bytes_source == "default"


def plan_hash(plan_dict: dict[str, Any]) -> str:
    """SHA-256 hex of a canonical plan dict (sorted keys, compact JSON)."""
    return hashlib.sha256(json.dumps(plan_dict, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


# -- motion model -----------------------------------------------------------------------------
@dataclass(frozen=True)
class MotionModel:
    """Trapezoidal move times per device (speed unit/s, acceleration unit/s^2), the expected
    frame size (bytes), where that size came from (see :class:`Estimate`) and the per-frame
    overhead (s)."""

    speeds: dict[str, tuple[float, float]] = field(default_factory=lambda: dict(DEFAULT_SPEEDS))
    frame_bytes: int = DEFAULT_FRAME_BYTES
    frame_overhead_s: float = DEFAULT_FRAME_OVERHEAD_S
    frame_bytes_source: str = "default"

    @classmethod
    def from_rig(cls, rig: Any) -> "MotionModel":
        if rig is None:
            return cls()
        desc = _describe(rig)
        speeds = dict(DEFAULT_SPEEDS)
        for role in speeds:
            d = desc.get(role, {})
            v = _first_number(d, ("max_speed_deg_s", "speed_deg_s", "max_speed_mm_s", "speed_mm_s"))
            a = _first_number(d, ("accel_deg_s2", "accel_mm_s2"))
            speeds[role] = (v or speeds[role][0], a or speeds[role][1])
        model = cls(speeds=speeds)
        fb = frame_bytes_from_describe(desc.get("camera", {}))
        if fb is None:   # the simulated lab's camera states its resolution in the rig's [rig] table
            table = (getattr(rig, "config", None) or {}).get("rig", {})
            fb = frame_bytes_from_describe({"image_size": table.get("camera_resolution")}) \
                if isinstance(table, dict) else None
        return model if fb is None else model.with_frame_bytes(fb, "camera")

    def with_frame_bytes(self, frame_bytes: float, source: str = "measured") -> "MotionModel":
        """This model with another frame size (bytes; e.g. measured from a stored frame)."""
        return replace(self, frame_bytes=int(round(frame_bytes)), frame_bytes_source=source,
                       frame_overhead_s=0.2 + frame_bytes / USB_BYTES_PER_S)

    def move_s(self, role: str, distance: float) -> float:
        """Time of one trapezoidal move of ``distance`` (device units), seconds."""
        return move_time_s(distance, *self.speeds[role])

    def step_move_s(self, prev: Step | None, step: Step) -> float:
        """Time to go from ``prev`` to ``step``: axes move together, so the slowest counts."""
        if prev is None:
            return 0.0
        t = [0.0]
        if step.turntable_deg is not None and prev.turntable_deg is not None:
            t.append(self.move_s("turntable", step.turntable_deg - prev.turntable_deg))
        if step.polarizer_deg is not None and prev.polarizer_deg is not None:
            t.append(self.move_s("polarizer", step.polarizer_deg - prev.polarizer_deg))
        if step.light is not None and prev.light is not None:
            t.append(self._light_move_s(prev.light, step.light))
        return max(t)

    def _light_move_s(self, a: LightTarget, b: LightTarget) -> float:
        if a.xyz_mm is not None and b.xyz_mm is not None:
            return self.move_s("positioner", math.dist(a.xyz_mm, b.xyz_mm))
        if a.xyz_mm is None and b.xyz_mm is None:
            return max(self.move_s("positioner", b.azimuth_deg - a.azimuth_deg),
                       self.move_s("positioner", b.elevation_deg - a.elevation_deg))
        return self.move_s("positioner", 90.0)  # mixed forms: assume a long move

    def estimate(self, steps: Sequence[Step]) -> Estimate:
        motion = sum(self.step_move_s(p, s) for p, s in zip([None, *steps[:-1]], steps))
        frames = sum(s.frames for s in steps)
        exposure = sum(sum(s.exposures_s) * s.repeats for s in steps)
        return Estimate(steps=len(steps), frames=frames, bytes=frames * self.frame_bytes,
                        motion_s=motion, exposure_s=exposure,
                        overhead_s=frames * self.frame_overhead_s, frame_bytes=self.frame_bytes,
                        frame_bytes_source=self.frame_bytes_source)


def frame_bytes_from_describe(cam: dict[str, Any]) -> int | None:
    """Bytes of one raw frame from a camera's describe(), or None if it does not say.

    Understood: ``frame_bytes``; ``width`` and ``height`` (pixels) with optional ``bit_depth``;
    ``image_size`` as PTP's ImageSize property (0x5003) reports it, ``"6000x4000"``, or
    ``[6000, 4000]``. A raw file holds one sample per pixel (the Bayer mosaic), stored in 16 bits
    up to 16-bit depth, plus a header (taken as 64 kB).
    """
    fb = _first_number(cam, ("frame_bytes",))
    if fb is not None:
        return int(fb)
    size = cam.get("image_size")
    if isinstance(size, str) and size.lower().count("x") == 1:
        try:
            size = [int(v) for v in size.lower().split("x")]
        except ValueError:
            size = None
    if (isinstance(size, (list, tuple)) and len(size) == 2
            and all(_is_num(v) and v > 0 for v in size)):
        w, h = size
    elif _first_number(cam, ("width",)) and _first_number(cam, ("height",)):
        w, h = cam["width"], cam["height"]
    else:
        return None
    depth = _first_number(cam, ("bit_depth",)) or 16
    return int(w * h * math.ceil(depth / 16) * 2 + 65536)


def _axis_role(name: str) -> str:
    return "positioner" if name.startswith("light") else name


def _one_step_s(name: str, values: list[Any], model: MotionModel) -> float:
    """Typical time of one move between neighbouring values of an axis."""
    if len(values) < 2:
        return 0.0
    if name == "light_xyz":
        d = [math.dist(p, q) for p, q in zip(values, values[1:])]
    else:
        d = [abs(q - p) for p, q in zip(values, values[1:])]
    return sum(model.move_s(_axis_role(name), x) for x in d) / len(d)


def _best_nesting(axes: list[tuple[str, list[Any]]], model: MotionModel) -> tuple[int, ...]:
    """Loop order (outermost first) with the least estimated motion time.

    With serpentine loops exactly one axis moves between consecutive steps; the axis at level k
    moves ``prod(n_j, j < k) * (n_k - 1)`` times, each costing its one-step time. Ties go to the
    order with faster axes inside.
    """
    t = [_one_step_s(n, v, model) for n, v in axes]
    n = [len(v) for _, v in axes]

    def cost(order: tuple[int, ...]) -> tuple[float, tuple[float, ...]]:
        total, outer = 0.0, 1
        for i in order:
            total += outer * (n[i] - 1) * t[i]
            outer *= n[i]
        return round(total, 9), tuple(-t[i] for i in order)

    return min(itertools.permutations(range(len(axes))), key=cost)


def _serpentine(levels: list[list[Any]]) -> Iterable[tuple[Any, ...]]:
    """Cartesian product, outermost level first, each inner block reversed on every other pass."""
    if not levels:
        yield ()
        return
    inner = list(_serpentine(levels[1:]))
    for k, v in enumerate(levels[0]):
        for rest in (reversed(inner) if k % 2 else inner):
            yield (v, *rest)


# -- parsing and validation -------------------------------------------------------------------
_TOP = {"name", "object", "operator", "notes", "repeats", "turntable", "light", "polarizer",
        "exposure", "calibration"}


def _parse(data: Any) -> Plan:
    if not isinstance(data, dict):
        raise PlanError(f"a plan must be a table, got {type(data).__name__}")
    _no_unknown(data, _TOP, "plan")
    tt = _table(data, "turntable", {"angles_deg"})
    lt = _table(data, "light", {"azimuth_deg", "elevation_deg", "distance_mm", "xyz_mm", "held_out_deg"})
    po = _table(data, "polarizer", {"angles_deg", "count"})
    ex = _table(data, "exposure", {"base_s", "stops", "iso", "auto", "highlight"})
    light = None
    if lt is not None:
        if "xyz_mm" in lt:
            if {"azimuth_deg", "elevation_deg", "distance_mm", "held_out_deg"} & lt.keys():
                raise PlanError("light: give either xyz_mm or azimuth_deg/elevation_deg (and held_out_deg), "
                                "not both")
            pts = lt["xyz_mm"]
            if not isinstance(pts, list):
                raise PlanError(f"light.xyz_mm must be a list of [x, y, z] points in mm, got {_tname(pts)}")
            if len(pts) > MAX_VALUES:  # before converting them all
                raise PlanError(f"light.xyz_mm has {len(pts)} points; more than {MAX_VALUES} is "
                                "surely a mistake")
            for i, p in enumerate(pts):
                if not (isinstance(p, list) and len(p) == 3 and all(_is_num(x) for x in p)):
                    raise PlanError(f"light.xyz_mm[{i}] must be [x, y, z] (three numbers, mm), got {p!r}")
            light = LightGrid(xyz_mm=tuple(tuple(float(x) for x in p) for p in pts))
        else:
            for key in ("azimuth_deg", "elevation_deg"):
                if key not in lt:
                    raise PlanError(f"light.{key} is missing (or give light.xyz_mm instead)")
            dist = lt.get("distance_mm")
            if dist is not None and not _is_num(dist):
                raise PlanError(f"light.distance_mm must be a number (mm), got {_tname(dist)}")
            held = lt.get("held_out_deg", [])
            if not isinstance(held, list):
                raise PlanError(f"light.held_out_deg must be a list of [azimuth, elevation] pairs (degrees), "
                                f"got {_tname(held)}")
            if len(held) > MAX_VALUES:  # before converting them all
                raise PlanError(f"light.held_out_deg has {len(held)} lights; more than {MAX_VALUES} is "
                                "surely a mistake")
            for i, p in enumerate(held):
                if not (isinstance(p, list) and len(p) == 2 and all(_is_num(x) for x in p)):
                    raise PlanError(f"light.held_out_deg[{i}] must be [azimuth, elevation] (degrees), got {p!r}")
            light = LightGrid(azimuth_deg=_numbers(lt["azimuth_deg"], "light.azimuth_deg"),
                              elevation_deg=_numbers(lt["elevation_deg"], "light.elevation_deg"),
                              distance_mm=None if dist is None else float(dist),
                              held_out_deg=tuple((float(a), float(e)) for a, e in held))
    pol: tuple[float, ...] = ()
    if po is not None:
        if ("angles_deg" in po) == ("count" in po):
            raise PlanError("polarizer: give exactly one of angles_deg or count")
        if "count" in po:
            n = po["count"]
            if not _is_int(n) or n < 1:
                raise PlanError(f"polarizer.count must be a whole number >= 1, got {n!r}")
            pol = tuple(180.0 * k / n for k in range(n))  # polarization repeats every 180 deg
        else:
            pol = _numbers(po["angles_deg"], "polarizer.angles_deg")
    exposure = Exposure()
    if ex is not None:
        base = ex.get("base_s", exposure.base_s)
        if not _is_num(base):
            raise PlanError(f"exposure.base_s must be a number (seconds), got {_tname(base)}")
        iso = ex.get("iso")
        if iso is not None and not _is_num(iso):
            raise PlanError(f"exposure.iso must be a number, got {_tname(iso)}")
        auto = ex.get("auto", False)
        if not isinstance(auto, bool):
            raise PlanError(f"exposure.auto must be true or false, got {_tname(auto)}")
        highlight = ex.get("highlight", 0.8)
        if not _is_num(highlight):
            raise PlanError(f"exposure.highlight must be a number (fraction of the raw range), "
                            f"got {_tname(highlight)}")
        if "highlight" in ex and not auto:
            raise PlanError("exposure.highlight is only used with exposure.auto = true")
        stops = _numbers(ex["stops"], "exposure.stops") if "stops" in ex else (0.0,)
        exposure = Exposure(base_s=float(base), stops=stops, iso=None if iso is None else float(iso),
                            auto=auto, highlight=float(highlight))
    cals = data.get("calibration", [])
    if not isinstance(cals, list):
        raise PlanError(f"calibration must be an array of tables ([[calibration]]), got {_tname(cals)}")
    calibration = tuple(_parse_calibration(c, i) for i, c in enumerate(cals))
    meta = {}
    for key in ("name", "object", "operator", "notes"):
        v = data.get(key, "")
        if not isinstance(v, str):
            raise PlanError(f"{key} must be a string, got {_tname(v)}")
        meta[key] = v
    repeats = data.get("repeats", 1)
    if not _is_int(repeats):
        raise PlanError(f"repeats must be a whole number, got {_tname(repeats)}")
    turntable = _numbers(tt["angles_deg"], "turntable.angles_deg") if tt and "angles_deg" in tt else ()
    return Plan(turntable_deg=turntable,
                light=light, polarizer_deg=pol, exposure=exposure, repeats=repeats,
                calibration=calibration, **meta)


def _parse_calibration(c: Any, i: int) -> Calibration:
    where = f"calibration[{i}]"
    if not isinstance(c, dict):
        raise PlanError(f"{where} must be a table, got {_tname(c)}")
    _no_unknown(c, {"kind", "frames", "exposure_s", "turntable_angles_deg", "lights", "when", "views"}, where)
    if "kind" not in c:
        raise PlanError(f"{where}.kind is missing; one of {', '.join(CALIBRATION_KINDS)}")
    for key in ("kind", "lights", "when"):
        if key in c and not isinstance(c[key], str):
            raise PlanError(f"{where}.{key} must be a string, got {_tname(c[key])}")
    frames = c.get("frames")
    if frames is not None and not _is_int(frames):
        raise PlanError(f"{where}.frames must be a whole number, got {_tname(frames)}")
    exp = c.get("exposure_s")
    if isinstance(exp, list) and len(exp) > MAX_STOPS:
        raise PlanError(f"{where}.exposure_s has {len(exp)} exposures; more than {MAX_STOPS} is "
                        "surely a mistake")
    if isinstance(exp, list) and exp and all(_is_num(e) for e in exp):
        exp = tuple(float(e) for e in exp)
    elif exp is not None and not _is_num(exp):
        raise PlanError(f"{where}.exposure_s must be a number or a list of numbers (seconds), got {_tname(exp)}")
    views = c.get("views")
    if views is not None and not _is_int(views):
        raise PlanError(f"{where}.views must be a whole number of board poses, got {_tname(views)}")
    angles = c.get("turntable_angles_deg")
    return Calibration(kind=c["kind"], frames=frames, exposure_s=exp if exp is None or isinstance(exp, tuple) else float(exp),
                       turntable_angles_deg=(None if angles is None else
                                             _numbers(angles, f"{where}.turntable_angles_deg")),
                       lights=c.get("lights"), when=c.get("when", "before"), views=views)


def _validate(p: Plan) -> None:
    """Rig-independent checks (also run on Python-built plans)."""
    if not _is_int(p.repeats) or p.repeats < 1:
        raise PlanError(f"repeats = {p.repeats!r} must be a whole number >= 1")
    if p.repeats > MAX_REPEATS:
        raise PlanError(f"repeats = {p.repeats} is more than {MAX_REPEATS}: surely a mistake")
    e = p.exposure
    if len(e.stops) > MAX_STOPS:
        raise PlanError(f"exposure.stops has {len(e.stops)} stops; more than {MAX_STOPS} is "
                        "surely a mistake")
    if p.light is not None and p.light.xyz_mm is not None and len(p.light.xyz_mm) > MAX_VALUES:
        raise PlanError(f"light.xyz_mm has {len(p.light.xyz_mm)} points; more than {MAX_VALUES} "
                        "is surely a mistake")  # a plan built in Python
    for i, c in enumerate(p.calibration):
        if c.frames is not None and c.frames > MAX_REPEATS:
            raise PlanError(f"calibration[{i}].frames = {c.frames} is more than {MAX_REPEATS}: "
                            "surely a mistake")
    if not (_is_num(e.base_s) and MIN_EXPOSURE_S <= e.base_s <= MAX_EXPOSURE_S):
        raise PlanError(f"exposure.base_s = {_fmt(e.base_s)} must be a positive number of seconds "
                        f"in {MIN_EXPOSURE_S:g}..{MAX_EXPOSURE_S:g}")
    if not e.stops:
        raise PlanError("exposure.stops is empty; give at least one stop (0 = base exposure)")
    _finite(e.stops, "exposure.stops")
    for i, stop in enumerate(e.stops):  # in log2, so a stop of 2000 cannot overflow
        if not math.log2(MIN_EXPOSURE_S) <= math.log2(e.base_s) + stop <= math.log2(MAX_EXPOSURE_S):
            raise PlanError(f"exposure.stops[{i}] = {_fmt(stop)} gives base_s x 2^stop outside "
                            f"{MIN_EXPOSURE_S:g}..{MAX_EXPOSURE_S:g} s")
    if len(set(e.stops)) != len(e.stops):
        raise PlanError(f"exposure.stops {list(e.stops)} has duplicates")
    if e.iso is not None and not (e.iso > 0 and math.isfinite(e.iso)):
        raise PlanError(f"exposure.iso = {_fmt(e.iso)} must be positive")
    if not 0.05 <= e.highlight <= 0.9:
        raise PlanError(f"exposure.highlight = {_fmt(e.highlight)} must lie in 0.05..0.9 "
                        "(fraction of the raw range; above 0.9 the highlights risk clipping)")
    _finite(p.turntable_deg, "turntable.angles_deg")
    _finite(p.polarizer_deg, "polarizer.angles_deg")
    _no_duplicates(p.turntable_deg, "turntable.angles_deg")
    _no_duplicates(p.polarizer_deg, "polarizer.angles_deg")
    if p.light is not None:
        lt = p.light
        if lt.xyz_mm is not None:
            if not lt.xyz_mm:
                raise PlanError("light.xyz_mm is empty; give at least one [x, y, z] point")
            for i, pt in enumerate(lt.xyz_mm):
                _finite(pt, f"light.xyz_mm[{i}]")
            _no_duplicates([tuple(pt) for pt in lt.xyz_mm], "light.xyz_mm")
        else:
            for key, lo, hi in (("azimuth_deg", -360.0, 360.0), ("elevation_deg", -90.0, 90.0)):
                values = getattr(lt, key)
                if not values:
                    raise PlanError(f"light.{key} is empty; the light grid needs at least one value")
                _finite(values, f"light.{key}")
                _no_duplicates(values, f"light.{key}")
                _check_limits(f"light.{key}", values, (lo, hi), "the valid range", "")
            for i, (az, el) in enumerate(lt.held_out_deg):
                _finite((az, el), f"light.held_out_deg[{i}]")
                if not (-360 <= az <= 360 and -90 <= el <= 90):
                    raise PlanError(f"light.held_out_deg[{i}] = [{az:g}, {el:g}] is outside the valid range "
                                    "(azimuth -360..360, elevation -90..90)")
                if any(az == a and el == e for e in lt.elevation_deg for a in lt.azimuth_deg):
                    raise PlanError(f"light.held_out_deg[{i}] = [{az:g}, {el:g}] is also on the light grid; "
                                    "a held-out light must be one the fit never sees")
            if lt.distance_mm is not None and not (lt.distance_mm > 0 and math.isfinite(lt.distance_mm)):
                raise PlanError(f"light.distance_mm = {_fmt(lt.distance_mm)} must be a positive finite "
                                "number (mm)")
    for i, c in enumerate(p.calibration):
        where = f"calibration[{i}]"
        if c.kind not in CALIBRATION_KINDS:
            raise PlanError(f"{where}.kind = {c.kind!r} is unknown; one of {', '.join(CALIBRATION_KINDS)}")
        if c.frames is not None and c.frames < 1:
            raise PlanError(f"{where}.frames = {c.frames} must be >= 1")
        for k, t in enumerate(c.exposures_s or ()):
            if not MIN_EXPOSURE_S <= t <= MAX_EXPOSURE_S:  # also false for NaN
                at = f"{where}.exposure_s" + (f"[{k}]" if isinstance(c.exposure_s, tuple) else "")
                raise PlanError(f"{at} = {_fmt(t)} must be a number of seconds in "
                                f"{MIN_EXPOSURE_S:g}..{MAX_EXPOSURE_S:g}")
        if c.lights is not None and c.lights not in ("grid", "first", "none"):
            raise PlanError(f"{where}.lights = {c.lights!r} must be 'grid', 'first' or 'none'")
        if c.when not in ("before", "after"):
            raise PlanError(f"{where}.when = {c.when!r} must be 'before' or 'after'")
        if c.turntable_angles_deg is not None:
            _finite(c.turntable_angles_deg, f"{where}.turntable_angles_deg")
        if c.kind == "handheld_board":
            if c.views is not None and not (_is_int(c.views) and HANDHELD_VIEWS_MIN <= c.views <= MAX_REPEATS):
                raise PlanError(f"{where}.views = {c.views!r} must be a whole number in "
                                f"{HANDHELD_VIEWS_MIN}..{MAX_REPEATS} (board poses; the intrinsics need "
                                f"at least {HANDHELD_VIEWS_MIN})")
            for key in ("turntable_angles_deg", "lights"):
                if getattr(c, key) is not None:
                    raise PlanError(f"{where}.{key} does not apply to kind = 'handheld_board' (the board "
                                    "is held in front of the camera; the turntable and the light stay put)")
        elif c.views is not None:
            raise PlanError(f"{where}.views is only for kind = 'handheld_board' (board poses); "
                            f"kind = {c.kind!r} takes turntable_angles_deg / lights")
    measuring = p.turntable_deg or p.polarizer_deg or p.light is not None
    if not measuring and not p.calibration:
        raise PlanError("the plan captures nothing: give turntable, light or polarizer values, "
                        "or a [[calibration]] capture")
    steps, frames = _count(p)
    if steps > MAX_STEPS or frames > MAX_FRAMES:
        raise PlanError(f"the plan has {steps:,} steps and {frames:,} frames; the caps are "
                        f"{MAX_STEPS:,} steps and {MAX_FRAMES:,} frames per session (split the "
                        "measurement into several sessions, or check the ranges for a typo)")


def _count(p: Plan) -> tuple[int, int]:
    """Steps and frames of ``p`` by arithmetic (what :meth:`Plan.steps` would expand), so a plan
    far too big is refused before anything is expanded."""
    measure = [len(p.turntable_deg), len(p.polarizer_deg), p.light.count if p.light else 0]
    steps = math.prod(n for n in measure if n) if any(measure) else 0
    held = len(p.light.held_out_deg) if p.light is not None else 0
    steps += max(len(p.turntable_deg), 1) * held * max(len(p.polarizer_deg), 1)
    frames = steps * len(p.exposure.stops) * p.repeats
    for c in p.calibration:
        default_frames, default_lights = CALIBRATION_KINDS.get(c.kind, (1, "none"))
        angles = ((c.views or HANDHELD_VIEWS_DEFAULT) if c.kind == "handheld_board" else
                  len(c.turntable_angles_deg) if c.turntable_angles_deg is not None else
                  8 if c.kind == "checkerboard" and p.turntable_deg else 1)
        lights = (c.lights or default_lights) == "grid" and p.light is not None and p.light.count + held or 1
        steps += angles * lights
        frames += angles * lights * (len(c.exposures_s) if c.exposure_s is not None else len(p.exposure.stops)) \
            * (c.frames or default_frames)
    return steps, frames


def _no_duplicates(values: Sequence[Any], where: str) -> None:
    # a repeated grid value captures the same pose twice under two step numbers: `repeats` is
    # the way to do that
    seen: dict[Any, int] = {}
    for i, v in enumerate(values):
        if v in seen:
            raise PlanError(f"{where}[{i}] = {_fmt(v)} repeats {where}[{seen[v]}]; use repeats = N "
                            "to capture a pose more than once")
        seen[v] = i


def _no_unknown(d: dict, allowed: set[str], where: str) -> None:
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise PlanError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} "
                        f"{', '.join(map(repr, unknown))}; allowed: {', '.join(sorted(allowed))}")


def _table(data: dict, key: str, allowed: set[str]) -> dict | None:
    t = data.get(key)
    if t is None:
        return None
    if not isinstance(t, dict):
        raise PlanError(f"{key} must be a table ([{key}]), got {_tname(t)}")
    _no_unknown(t, allowed, key)
    return t


def _fmt(x: Any) -> str:
    return f"{x:g}" if _is_num(x) else repr(x)


def _is_num(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _tname(x: Any) -> str:
    return {str: "a string", bool: "a boolean", dict: "a table", list: "a list"}.get(
        type(x), type(x).__name__) + f" ({x!r})"


def _numbers(v: Any, where: str) -> tuple[float, ...]:
    """A list of numbers, or a ``{start, stop, step}`` range (stop included when on the grid)."""
    if isinstance(v, dict):
        _no_unknown(v, {"start", "stop", "step"}, where)
        for k in ("start", "stop", "step"):
            if k not in v:
                raise PlanError(f"{where}.{k} is missing (a range needs start, stop and step)")
            if not _is_num(v[k]):
                raise PlanError(f"{where}.{k} must be a number, got {_tname(v[k])}")
        start, stop, step = (float(v[k]) for k in ("start", "stop", "step"))
        for k, x in (("start", start), ("stop", stop), ("step", step)):
            if not math.isfinite(x):
                raise PlanError(f"{where}.{k} = {x} is not a finite number")
        if step == 0 or (stop - start) * step < 0:
            raise PlanError(f"{where}: step {step:g} never goes from {start:g} to {stop:g}")
        n = math.floor((stop - start) / step + 1e-9) + 1
        if n > MAX_VALUES:
            raise PlanError(f"{where}: the range has {n} values; more than {MAX_VALUES} is surely "
                            "a mistake")
        return tuple(round(start + k * step, 9) for k in range(n))
    if not isinstance(v, list):
        raise PlanError(f"{where} must be a list of numbers or {{start, stop, step}}, got {_tname(v)}")
    if not v:
        raise PlanError(f"{where} is empty; give at least one value")
    if len(v) > MAX_VALUES:
        raise PlanError(f"{where} has {len(v)} values; more than {MAX_VALUES} is surely a mistake")
    for i, x in enumerate(v):
        if not _is_num(x):
            raise PlanError(f"{where}[{i}] must be a number, got {_tname(x)}")
    return tuple(float(x) for x in v)


def _finite(values: Iterable[float], where: str) -> None:
    for i, x in enumerate(values):
        if not math.isfinite(x):
            raise PlanError(f"{where}[{i}] = {x} is not a finite number")


def _check_limits(where: str, values: Iterable[float], limits: tuple[float, float] | None,
                  what: str, unit: str, *, indexed: bool = True) -> None:
    """Raise naming ``where[i]`` (or ``where`` with ``{i}`` filled in) for the first value
    outside ``limits``."""
    if limits is None:
        return
    lo, hi = limits
    for i, x in enumerate(values):
        if not lo - 1e-9 <= x <= hi + 1e-9:
            label = where.format(i=i) if "{i}" in where else (f"{where}[{i}]" if indexed else where)
            raise PlanError(f"{label} = {x:g}{unit} is outside {what} {lo:g}..{hi:g}{unit}")


def _describe(rig: Any) -> dict[str, dict[str, Any]]:
    return rig.describe() if rig is not None else {}


def _need(used: Any, rig: Any, role: str, field_name: str) -> None:
    if used and getattr(rig, role, None) is None:
        raise PlanError(f"{field_name} is given but the rig has no {role}")


def _axis_limits(device: Any) -> tuple[float, float] | None:
    try:
        lo, hi = device.limits
    except (AttributeError, TypeError, ValueError):
        return None
    return float(lo), float(hi)


def _check_reach(light: LightGrid, desc: dict[str, Any]) -> None:
    """Check every light position against the positioner's kinematics (from its describe())."""
    config = desc.get("kinematics")
    if not isinstance(config, dict):
        return  # the driver does not tell its reach: the move itself will say
    from rig.kinematics import kinematics_from_config   # here, not at the top: numpy would load with every plan and store
    kin = kinematics_from_config(config)
    if light.xyz_mm is not None:
        for i, p in enumerate(light.xyz_mm):
            try:
                kin.inverse(LightTarget(xyz_mm=p))
            except LimitError as exc:
                raise PlanError(f"light.xyz_mm[{i}] = [{p[0]:g}, {p[1]:g}, {p[2]:g}] is out of the "
                                f"positioner's reach: {exc.message}") from None
        return
    for j, el in enumerate(light.elevation_deg):
        for i, az in enumerate(light.azimuth_deg):
            try:
                kin.inverse(LightTarget(azimuth_deg=az, elevation_deg=el, distance_mm=light.distance_mm))
            except LimitError as exc:
                lo, hi = exc.limits
                if "elevation" in exc.message:
                    field_, value = f"light.elevation_deg[{j}]", el
                elif "azimuth" in exc.message:
                    field_, value = f"light.azimuth_deg[{i}]", az
                else:
                    raise PlanError(f"light (azimuth {az:g}, elevation {el:g}) is out of the "
                                    f"positioner's reach: {exc.message}") from None
                raise PlanError(f"{field_} = {value:g} is outside the positioner's limit "
                                f"{lo:g}..{hi:g}") from None
    for i, (az, el) in enumerate(light.held_out_deg):
        try:
            kin.inverse(LightTarget(azimuth_deg=az, elevation_deg=el, distance_mm=light.distance_mm))
        except LimitError as exc:
            raise PlanError(f"light.held_out_deg[{i}] = [{az:g}, {el:g}] is out of the positioner's "
                            f"reach: {exc.message}") from None


def limit_from_describe(desc: dict[str, Any], name: str) -> tuple[float, float] | None:
    """Find ``name``'s (low, high) in a describe() dict: ``<name>_limits[_deg|_mm|_s]``,
    ``<name>_range[...]``, ``limits: {<name>: [lo, hi]}``, or the extremes of a list of allowed
    values ``<name>_values[_s]`` (a camera's exposure steps)."""
    candidates = [desc.get(f"{name}{mid}{suffix}") for mid in ("_limits", "_range")
                  for suffix in ("", "_deg", "_mm", "_s")]
    lims = desc.get("limits")
    if isinstance(lims, dict):
        candidates += [lims.get(name), lims.get(f"{name}_deg"), lims.get(f"{name}_mm"), lims.get(f"{name}_s")]
    for c in candidates:
        if isinstance(c, (list, tuple)) and len(c) == 2 and all(_is_num(x) for x in c):
            return float(c[0]), float(c[1])
    for key in (f"{name}_values", f"{name}_values_s"):
        values = desc.get(key)
        if isinstance(values, (list, tuple)) and values and all(_is_num(x) for x in values):
            return float(min(values)), float(max(values))
    return None


def _first_number(d: dict[str, Any], keys: Sequence[str]) -> float | None:
    for k in keys:
        if _is_num(d.get(k)) and d[k] > 0:
            return float(d[k])
    return None


def _drop_none(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    if isinstance(d, list):
        return [_drop_none(v) for v in d]
    return d


def plan_diff(old: dict[str, Any], new: dict[str, Any], prefix: str = "") -> list[str]:
    """Fields that differ between two canonical plan dicts, as ``path: old -> new`` lines."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        path = f"{prefix}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            out += plan_diff(a, b, path + ".")
        elif a != b:
            out.append(f"{path}: {_short(a)} -> {_short(b)}")
    return out


def _short(v: Any) -> str:
    text = json.dumps(v)
    return text if len(text) <= 60 else text[:57] + "..."
