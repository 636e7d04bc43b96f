"""``--rig sim|FILE`` -> a built (and usually connected) ``rig.Rig``, with its SimLab if any.

Every command that needs hardware calls :func:`open_rig`::

    with open_rig("sim") as opened:            # the whole simulated lab (DemoLab's scenes)
        opened.rig.turntable.move_to(30).wait()
    with open_rig("sim", resolution=(640, 480)) as opened:  # its camera at 640 x 480
    with open_rig("lab.toml") as opened:       # real devices; any role with port = "sim"
        ...                                    # gets a simulator of its own

A rig file may mix real and simulated devices: sections whose ``port = "sim"`` are served by a
:class:`sims.lab.SimLab` started for just those roles (a simulated positioner takes the file's
``kinematics`` table).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from rig import Axis, Rig, load_config, wait_all
from rig.rig import ROLES, ConfigError
from sims.lab import KINEMATICS, LAB_NAME, SimLab

from .pipeline.demo_lab import FAST_RESOLUTION, FULL_RESOLUTION, DemoLab


#: the driver that speaks each simulated device's protocol (what ``port = "sim"`` serves)
SIM_DRIVERS = {"turntable": "zaber", "positioner": "grbl", "polarizer": "elliptec", "camera": "ptp"}


#: ``[rig] camera_scene`` in the config of ``open_rig("sim")`` when its camera renders the
#: built-in lab (:class:`capture.pipeline.demo_lab.DemoLab`): a session's rig snapshots say by it
#: whose targets, mesh and ground truth its frames show
BUILT_IN_SCENE = "demo lab"


@dataclass
class OpenedRig:
    """A rig built by :func:`open_rig` and the simulators behind it (None for real hardware).

    ``prepare_target(target, step)`` stages a scene target (``object``, ``checkerboard`` ...)
    in front of a simulated camera — the runner's ``prepare_target`` hook. None where nothing
    can: a real camera (the operator sets the scene up) or a lab given a plain ``frame_source``
    without a ``prepare_target`` of its own."""

    rig: Rig
    lab: SimLab | None = None
    prepare_target: Callable[[str, Any], None] | None = None

    def close(self) -> None:
        """Close every device, then stop the simulators."""
        try:
            self.rig.close()
        finally:
            if self.lab is not None:
                self.lab.stop()

    def __enter__(self) -> "OpenedRig":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_rig(spec: str | Path | dict[str, Any], *, fast: bool = True, connect: bool = True,
             home: bool = False, timeout_s: float = 120.0, **lab_options: Any) -> OpenedRig:
    """Build the rig named by ``spec`` and (by default) connect it.

    Parameters
    ----------
    spec : str, Path or dict
        ``"sim"`` for the whole simulated lab, a rig TOML file, or a config dict.
    fast : bool
        For simulated devices: complete motion at once (``False`` models motion time).
    connect : bool
        Connect every device (on failure all are closed, the simulators stopped, and the error
        re-raised).
    home : bool
        After connecting, home every axis and the positioner at the same time.
    timeout_s : float
        Time allowed for homing, seconds.
    lab_options
        Passed to :class:`SimLab` (``frame_source``, ``kinematics``, ``options``), but for
        ``prepare_target``: the scene changer that goes with a given ``frame_source``, and
        ``resolution``: (width, height) of the built-in lab's camera. Without a ``frame_source``
        a simulated camera renders :class:`capture.pipeline.demo_lab.DemoLab` (the lab
        ``gonio demo`` captures), at ``resolution`` (default 320 x 240 when ``fast``, else
        640 x 480: ``demo_lab.FAST_RESOLUTION`` / ``FULL_RESOLUTION``), and the result carries
        its ``prepare_target``; for ``"sim"`` the config's ``[rig]`` table then says so
        (``camera_scene`` = :data:`BUILT_IN_SCENE`, ``camera_resolution``).

    Raises
    ------
    rig.ConfigError
        For a malformed rig file; ``RigError`` subclasses for device faults.
    ValueError
        ``resolution`` beside a ``frame_source``, or not two even pixel counts >= 16.
    """
    lab = None
    prepare_target = lab_options.pop("prepare_target", None)
    where = "rig config" if isinstance(spec, dict) or spec == "sim" else str(spec)  # for messages
    if isinstance(spec, str) and spec == "sim":
        prepare_target, scene = _sim_scene(fast, lab_options, prepare_target)
        lab = SimLab(fast=fast, **lab_options).start()
        cfg = lab.rig_config()
        if scene is not None:
            cfg["rig"].update(camera_scene=BUILT_IN_SCENE,
                              camera_resolution=[scene.camera.width, scene.camera.height])
    else:
        cfg = load_config(spec)
        sim_roles = [role for role, section in cfg.items() if role in ROLES and section.get("port") == "sim"]
        for role in sim_roles:
            if cfg[role]["driver"] != SIM_DRIVERS[role]:
                raise ConfigError(f"{where}: [{role}] driver = {cfg[role]['driver']!r} with port = "
                                  f"'sim': the simulated {role} speaks the {SIM_DRIVERS[role]!r} "
                                  f"protocol; write driver = {SIM_DRIVERS[role]!r}, or a real port")
        if sim_roles:
            if "positioner" in sim_roles and "kinematics" in cfg["positioner"]:
                lab_options.setdefault("kinematics", _kinematics_table(cfg["positioner"]["kinematics"]))
            if "positioner" in sim_roles:
                given = {k: cfg["positioner"][k] for k in ("machine_offset", "machine_sign")
                         if k in cfg["positioner"]}
                if given:
                    lab_options.setdefault("machine_map", given)
            if "camera" in sim_roles:
                prepare_target, _ = _sim_scene(fast, lab_options, prepare_target)
            elif "resolution" in lab_options:
                raise ValueError(f"resolution: {where} simulates no camera")
            lab = SimLab(fast=fast, roles=sim_roles, **lab_options).start()
            served = lab.rig_config()
            # the lab's keys (the simulated GRBL's machine map) fill in what the section leaves out
            cfg = {role: ({**served[role], **section, "port": served[role]["port"]} if role in sim_roles
                          else section)
                   for role, section in cfg.items()}
    try:
        context = {"usb_backend": lab.usb_backend} if lab is not None and lab.usb_backend is not None else {}
        rig = Rig.from_config(cfg, where=where, **context)
        if connect:
            rig.connect()
            if home:
                home_all(rig, timeout_s=timeout_s)
    except BaseException:
        if lab is not None:
            lab.stop()
        raise
    return OpenedRig(rig, lab, prepare_target)


def _sim_scene(fast: bool, lab_options: dict[str, Any], prepare_target):
    """(scene changer, built-in lab or None) of the simulated camera: the given changer beside a
    given ``frame_source``, else a new :class:`DemoLab` (which goes into ``lab_options`` as the
    frame source) and its own."""
    resolution = lab_options.pop("resolution", None)
    camera_options = (lab_options.get("options") or {}).get("camera", {})
    if lab_options.get("frame_source") is not None or camera_options.get("frame_source") is not None:
        if resolution is not None:
            raise ValueError("resolution: sets the built-in lab's camera; a given frame_source renders "
                             "at its own")
        return prepare_target, None
    if resolution is None:
        resolution = FAST_RESOLUTION if fast else FULL_RESOLUTION
    if not isinstance(resolution, (tuple, list)) or len(resolution) != 2:
        raise ValueError(f"resolution: (width, height) in pixels, got {resolution!r}")
    try:
        scene = DemoLab(*resolution)
    except ValueError as exc:
        raise ValueError(f"resolution: {exc}") from None
    lab_options["frame_source"] = scene
    return scene.prepare_target, scene


def recorded_in_built_in_lab(snapshots: list[dict[str, Any]]) -> bool:
    """Whether every rig snapshot of a session (:meth:`capture.store.Store.rig_snapshots`) says
    it was recorded on ``--rig sim`` with the camera rendering the built-in lab (see
    :func:`open_rig`), whose targets, mesh and ground truth are then known."""
    tables = [s["config"].get("rig", {}) for s in snapshots]
    return bool(tables) and all(isinstance(t, dict) and t.get("name") == LAB_NAME   # [rig] of an old store
                                and t.get("camera_scene") == BUILT_IN_SCENE for t in tables)


def _kinematics_table(value: Any) -> Any:
    return KINEMATICS[value] if isinstance(value, str) and value in KINEMATICS else value


def home_all(rig: Rig, *, timeout_s: float = 120.0, roles: list[str] | None = None) -> dict[str, Any]:
    """Home the axes and the positioner of ``rig`` concurrently; return each one's result."""
    devices = {role: d for role, d in rig.devices.items()
               if (roles is None or role in roles) and hasattr(d, "home")}
    statuses = {role: d.home() for role, d in devices.items()}
    results = wait_all(list(statuses.values()), timeout=timeout_s)
    return dict(zip(statuses, results))


def position_text(device: Any) -> str:
    """The device's current position with units, for tables (``123.456 deg``, ``(x, y, z) mm``)."""
    if isinstance(device, Axis):
        return f"{device.position:.3f} {device.units}"
    if hasattr(device, "light_position_mm"):
        x, y, z = device.light_position_mm
        return f"({x:.1f}, {y:.1f}, {z:.1f}) mm"
    if hasattr(device, "exposure_s"):
        return f"exposure {device.exposure_s:g} s"
    return ""


def to_toml(cfg: dict[str, Any]) -> str:
    """Write a rig config as TOML (tables per role; nested values as inline tables / arrays)."""
    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + " }"
        raise TypeError(f"cannot write {type(v).__name__} to TOML")

    blocks = []
    for role, section in cfg.items():
        lines = [f"[{role}]"] + [f"{k} = {value(v)}" for k, v in section.items()]
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks) + "\n"
