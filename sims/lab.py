"""The simulated lab: all four device simulators, started together, and their physical state.

``SimLab`` starts the turntable (:class:`~sims.zaber_sim.ZaberSim`), the light positioner
(:class:`~sims.grbl_sim.GrblSim`), the polarizer (``ElliptecSim``) and the camera
(``PtpCameraSim``, a pyusb backend), and hands out what a driver needs to reach them: a rig
config (driver + port per role, as ``rig.Rig.from_config`` reads it) and the camera's
``usb_backend``. :meth:`SimLab.state` is the physical state the simulated camera renders from.

Usage::

    with SimLab(fast=True) as lab:
        rig = Rig.from_config(lab.rig_config(), usb_backend=lab.usb_backend)

(``capture.rigs.open_rig("sim")`` does this and connects; sims may not import rig.)
"""
from __future__ import annotations

import importlib
from typing import Any, Callable, Mapping

from .grbl_sim import GrblSim, light_position_mm
from .zaber_sim import ZaberSim

ROLES = ("turntable", "positioner", "polarizer", "camera")

#: default kinematics tables (the rig-file form); the same table configures sim and driver
KINEMATICS: dict[str, dict[str, Any]] = {
    "arm": {"type": "arm", "radius_mm": 500.0, "centre_mm": [0.0, 0.0, 0.0],
            "azimuth_limits_deg": [-180.0, 180.0], "elevation_limits_deg": [0.0, 85.0]},
    "gantry": {"type": "gantry", "origin_mm": [500.0, 500.0, 900.0], "yaw_deg": 0.0,
               "travel_mm": {"X": [-999.0, -1.0], "Y": [-999.0, -1.0], "Z": [-999.0, -1.0]},
               "centre_mm": [0.0, 0.0, 0.0], "default_distance_mm": 500.0},
}

#: where each kinematics' axes sit in the simulated GRBL's machine space (the rig file's
#: ``machine_offset`` / ``machine_sign``), which is [-$13x, 0]: the arm's azimuth homes towards +
#: and stops at MPos -$27 = -1, azimuth 180 deg, so -180..180 deg is MPos -361..-1 in $130 = 370;
#: its elevation homes towards - ($23 = 2) and stops at -$131 + $27 = -94, elevation 0, so
#: 0..85 deg is MPos -94..-9 in $131 = 95; the gantry's travel is already in machine coordinates
MACHINE_MAPS: dict[str, dict[str, dict[str, float]]] = {
    "arm": {"machine_offset": {"X": -181.0, "Y": -94.0}},
    "gantry": {},
}
#: where the arm stands at power-up (machine units): azimuth 0, elevation 0, the light on +x
#: (GRBL reports MPos 0 there until homed); the gantry powers up where homing leaves it
ARM_POWER_UP = (-181.0, -94.0, -1.0)
#: after homing (at azimuth 180 deg, behind the object) the arm parks its light at azimuth 0,
#: elevation 0, beside the camera: calibration steps that do not place the light are lit as before
PARK: dict[str, dict[str, dict[str, float]]] = {"arm": {"park": {"azimuth_deg": 0.0, "elevation_deg": 0.0}}}


#: the ``[rig] name`` of the simulated lab's config: a session's rig snapshot says by it that the
#: session was recorded on the simulated lab (whose targets the simulator knows)
LAB_NAME = "simulated lab"

class SimLab:
    """All simulators of the lab.

    Parameters
    ----------
    fast : bool
        Moves, homing and exposures complete at once (tests). ``False`` models motion time.
    frame_source : callable, optional
        ``frame_source(state) -> bytes`` (DNG) for the camera; ``state`` includes
        :meth:`state`. Default: the camera simulator's stand-in gradient
        (:func:`sims.ptp_sim.placeholder_frame`); the rendered lab, its scenes and targets, is
        what ``capture.rigs.open_rig("sim")`` hands in (``capture.pipeline.demo_lab.DemoLab``).
    kinematics : str or mapping
        ``"arm"``, ``"gantry"`` (the defaults in :data:`KINEMATICS`) or a full table.
    roles : iterable of str, optional
        Which devices to simulate (default: all four).
    options : mapping of role -> dict, optional
        Extra keyword arguments per simulator, e.g. ``{"turntable": {"speed_deg_s": 30}}``.
    machine_map : mapping, optional
        The positioner's ``machine_offset`` / ``machine_sign`` tables (default: the kinematics'
        entry in :data:`MACHINE_MAPS`).
    """

    def __init__(self, fast: bool = True, frame_source: Callable[[dict], bytes] | None = None,
                 kinematics: str | Mapping[str, Any] = "arm", *, roles: Any = None,
                 options: Mapping[str, Mapping[str, Any]] | None = None,
                 machine_map: Mapping[str, Mapping[str, float]] | None = None) -> None:
        self.fast = fast
        self.frame_source = frame_source
        if isinstance(kinematics, str):
            if kinematics not in KINEMATICS:
                raise ValueError(f"kinematics {kinematics!r} is unknown; use one of {', '.join(KINEMATICS)} "
                                 "or a table")
            kinematics = KINEMATICS[kinematics]
        self.kinematics = dict(kinematics)
        self.machine_map = {k: dict(v) for k, v in (
            machine_map if machine_map is not None else MACHINE_MAPS.get(self.kinematics.get("type"), {})).items()}
        self.roles = tuple(ROLES if roles is None else roles)
        unknown = set(self.roles) - set(ROLES)
        if unknown:
            raise ValueError(f"unknown role(s) {sorted(unknown)}; a SimLab simulates {', '.join(ROLES)}")
        self.options = {role: dict(opts) for role, opts in (options or {}).items()}
        if set(self.options) - set(ROLES):
            raise ValueError(f"options for unknown role(s) {sorted(set(self.options) - set(ROLES))}")
        self.sims: dict[str, Any] = {}
        self.started = False

    # -- lifecycle --------------------------------------------------------------------------------
    def start(self) -> "SimLab":
        """Create and start the simulators (serial ones get their ptys). Returns self."""
        if self.started:
            return self
        try:
            for role in self.roles:
                sim = self._make(role, self.options.get(role, {}))
                if hasattr(sim, "start"):
                    sim.start()
                self.sims[role] = sim
        except BaseException:
            self.stop()
            raise
        self.started = True
        return self

    def _make(self, role: str, opts: dict[str, Any]) -> Any:
        if role == "turntable":
            return ZaberSim(role, fast=self.fast, **opts)
        if role == "positioner":
            if self.kinematics.get("type") == "arm" and self.machine_map == MACHINE_MAPS["arm"]:
                opts = {"power_up_position": ARM_POWER_UP, **opts}
            return GrblSim(role, fast=self.fast, kinematics=self.kinematics, machine_map=self.machine_map,
                           **opts)
        if role == "polarizer":
            # imported lazily: the polarizer and camera simulators are separate modules
            elliptec = importlib.import_module("sims.elliptec_sim")
            return elliptec.ElliptecSim(role, fast=self.fast, **opts)
        ptp = importlib.import_module("sims.ptp_sim")
        kwargs = {"extra_state": self.state, "fast": self.fast, "frame_source": self.frame_source, **opts}
        return ptp.PtpCameraSim(**kwargs)

    def stop(self) -> None:
        """Stop every simulator (safe to call twice)."""
        for sim in self.sims.values():
            if hasattr(sim, "stop"):
                sim.stop()
        self.sims.clear()
        self.started = False

    def __enter__(self) -> "SimLab":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- what drivers need ------------------------------------------------------------------------
    @property
    def usb_backend(self) -> Any:
        """The camera simulator (a ``usb.backend.IBackend``), or None without a camera."""
        return self.sims.get("camera")

    def rig_config(self) -> dict[str, Any]:
        """Driver and port per role, in the form ``rig.Rig.from_config`` reads."""
        if not self.started:
            raise RuntimeError("SimLab.rig_config(): start() the lab first")
        cfg: dict[str, Any] = {"rig": {"name": LAB_NAME, "fast": self.fast}}
        for role, sim in self.sims.items():
            if role == "turntable":
                cfg[role] = {"driver": "zaber", "port": sim.port}
            elif role == "positioner":
                cfg[role] = {"driver": "grbl", "port": sim.port, "kinematics": dict(self.kinematics),
                             **self.machine_map, **PARK.get(self.kinematics.get("type"), {})}
            elif role == "polarizer":
                cfg[role] = {"driver": "elliptec", "port": sim.port}
            else:
                cfg[role] = {"driver": "ptp", "port": f"usb:{sim.vendor_id:04x}:{sim.product_id:04x}"}
        return cfg

    # -- physical state ---------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """What the scene looks like now: ``turntable_angle_deg`` (platter angle, deg),
        ``light_position_mm`` (world frame, mm), ``polarizer_angle_deg`` (deg) -- for the roles
        that are simulated."""
        out: dict[str, Any] = {}
        if "turntable" in self.sims:
            out["turntable_angle_deg"] = self.sims["turntable"].angle_deg
        if "positioner" in self.sims:
            out["light_position_mm"] = self.sims["positioner"].light_position_mm
        if "polarizer" in self.sims:
            out["polarizer_angle_deg"] = self.sims["polarizer"].angle_deg
        return out

    def __repr__(self) -> str:
        state = "running" if self.started else "stopped"
        return f"<SimLab {state} {', '.join(self.roles)} fast={self.fast}>"


__all__ = ["SimLab", "ROLES", "KINEMATICS", "MACHINE_MAPS", "light_position_mm"]
