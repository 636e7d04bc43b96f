"""The rig: the set of devices of one measurement setup, built from a TOML config.

A rig file names each role's driver and port::

    [turntable]
    driver = "zaber"          # Zaber ASCII rotary stage
    port = "/dev/ttyUSB0"

    [positioner]
    driver = "grbl"           # GRBL 1.1 light-stage positioner
    port = "/dev/ttyACM0"
    kinematics = "arm"        # or "gantry"

    [polarizer]
    driver = "elliptec"       # Thorlabs ELL14 rotation mount
    port = "/dev/ttyUSB1"

    [camera]
    driver = "ptp"            # PTP/USB still camera
    port = "usb:04a9:32b4"

Any role may be left out. ``port = "sim"`` asks the application (``capture``) to start a
simulator for that device; ``rig`` itself never imports the simulators.
"""
from __future__ import annotations

import importlib
import inspect
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .device import Axis, Camera, Device, LightPositioner
from .errors import RigError
from .tomlfile import read_toml

#: driver name -> "module:Class"; each class has ``from_config(name, section, **context)``
DRIVERS: dict[str, str] = {
    "zaber": "rig.zaber:ZaberRotaryStage",
    "grbl": "rig.grbl:GrblPositioner",
    "elliptec": "rig.elliptec:ElliptecRotator",
    "ptp": "rig.ptp_camera:PtpCamera",
    "gphoto2": "rig.gphoto2_camera:Gphoto2Camera",  # optional: pip install 'gonio[gphoto2]'
}

ROLES: dict[str, type] = {"turntable": Axis, "positioner": LightPositioner,
                          "polarizer": Axis, "camera": Camera}


class ConfigError(RigError, ValueError):
    """The rig config is malformed; the message names the file, section and key."""


def load_config(source: str | Path | dict[str, Any]) -> dict[str, Any]:
    """Read a rig TOML file (or pass a dict through), checking roles and drivers."""
    where = "rig config"
    if isinstance(source, dict):
        cfg = source
    else:
        where = str(source)
        cfg = read_toml(source, error=ConfigError, what="rig file")
    for role, section in cfg.items():
        if role == "rig":  # free metadata: name, notes
            if not isinstance(section, dict):
                raise ConfigError(f"{where}: rig = {section!r} must be a table ([rig] with name = ..., "
                                  "notes = ...)")
            continue
        if role not in ROLES:
            raise ConfigError(f"{where}: unknown section [{role}]; expected one of "
                              f"{', '.join(ROLES)} (or [rig] for metadata)")
        if not isinstance(section, dict):
            raise ConfigError(f"{where}: [{role}] must be a table")
        driver = section.get("driver")
        if not isinstance(driver, str) or driver not in DRIVERS:
            raise ConfigError(f"{where}: [{role}] driver = {driver!r} is unknown; "
                              f"known drivers: {', '.join(sorted(DRIVERS))}")
        port = section.get("port")
        if not port:
            raise ConfigError(f"{where}: [{role}] needs a port (e.g. '/dev/ttyUSB0', "
                              f"'usb:VID:PID' or 'sim')")
        if not isinstance(port, str) or not port.isprintable():
            raise ConfigError(f"{where}: [{role}] port = {port!r} must be a text such as "
                              "\"/dev/ttyUSB0\", \"usb:VID:PID\" or \"sim\" (in quotes)")
    ports: dict[str, str] = {}
    for role, section in cfg.items():  # one device cannot serve two roles
        if role != "rig" and section["port"] not in ("sim", "auto"):
            # a device path by any spelling (/dev/./ttyUSB0, a /dev/serial/by-id link) is one device
            device = os.path.realpath(section["port"]) if section["port"].startswith("/") else section["port"]
            if device in ports:
                other = ports[device]
                raise ConfigError(f"{where}: [{role}] port = {section['port']!r} is the same device "
                                  f"as the [{other}] port = {cfg[other]['port']!r}; each device "
                                  "needs its own")
            ports[device] = role
    if "kinematics" in cfg.get("positioner", {}):
        _check_kinematics(cfg["positioner"]["kinematics"], where)
    return cfg


def _check_kinematics(value: Any, where: str) -> None:
    """``[positioner] kinematics``: a known name or a table the kinematics classes accept, checked
    here so that neither a simulator nor a later command meets it first."""
    from .kinematics import kinematics_from_config
    if not isinstance(value, (str, dict)):
        raise ConfigError(f"{where}: [positioner] kinematics = {value!r} must be \"arm\", \"gantry\" "
                          "or a table ([positioner.kinematics] type = ...)")
    numbers = [v for v in (value.values() if isinstance(value, dict) else ())
               for v in (v if isinstance(v, list) else [v])]
    if any(isinstance(v, float) and not math.isfinite(v) for v in numbers):
        raise ConfigError(f"{where}: [positioner] kinematics: every number must be finite")
    try:
        kinematics_from_config(value)
    except ValueError as exc:
        raise ConfigError(f"{where}: [positioner] {exc}") from None


def driver_options(name: str, section: dict[str, Any], driver: str,
                   allowed: set[str] | frozenset[str]) -> dict[str, Any]:
    """A section's driver options (every key but ``driver`` and ``port``), checked against the
    driver's ``allowed`` keys. Drivers call this from their ``from_config``;
    :meth:`Rig.from_config` adds the file name to any error."""
    unknown = set(section) - set(allowed) - {"driver", "port"}
    if unknown:
        raise ConfigError(f"[{name}] unknown key(s) for the {driver} driver: "
                          f"{', '.join(sorted(unknown))}; allowed: {', '.join(sorted(allowed))}")
    options = {k: v for k, v in section.items() if k not in ("driver", "port")}
    params = inspect.signature(driver_class(driver).__init__).parameters
    for key, value in options.items():
        want = _KINDS.get(str(params[key].annotation).replace(" | None", "")) if key in params else None
        if want is not None and not (isinstance(value, want[0]) and not isinstance(value, want[1])):
            raise ConfigError(f"[{name}] {key} = {value!r} must be {want[2]}")
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):
                raise ConfigError(f"[{name}] {key} = {value!r} must be a finite number")
            if key.endswith(_POSITIVE) and not value > 0:
                raise ConfigError(f"[{name}] {key} = {value!r} must be greater than 0")
            if key.endswith("_s") and value > MAX_DURATION_S:
                raise ConfigError(f"[{name}] {key} = {value!r} s is more than {MAX_DURATION_S:g} s "
                                  "(a day): surely a mistake")
            if key.endswith("_retries") and value < 0:
                raise ConfigError(f"[{name}] {key} = {value!r} must be 0 or more")
    return options


#: longest duration option (timeouts, poll intervals), s: past it a deadline overflows the clock
MAX_DURATION_S = 86_400.0

#: option names (by ending) whose value must be > 0: rates, durations, steps, sizes
_POSITIVE = ("baudrate", "_s", "_s2", "_deg", "_bytes", "_tolerance")


#: a driver parameter's annotation -> (accepted types, refused types, what to write)
_KINDS: dict[str, tuple[type | tuple[type, ...], type | tuple[type, ...], str]] = {
    "int": (int, bool, "a whole number"),
    "float": ((int, float), bool, "a number"),
    "bool": (bool, (), "true or false"),
    "str": (str, (), "a text in quotes"),
}


def driver_class(driver: str) -> type[Device]:
    module, _, cls = DRIVERS[driver].partition(":")
    return getattr(importlib.import_module(module), cls)


@dataclass
class Rig:
    """The devices of one setup, by role. Any role may be None (not fitted)."""

    turntable: Axis | None = None
    positioner: LightPositioner | None = None
    polarizer: Axis | None = None
    camera: Camera | None = None
    config: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_config(cls, source: str | Path | dict[str, Any], *, where: str | None = None,
                    **context: Any) -> "Rig":
        """Build (not connect) the devices named in a rig file or dict.

        ``where`` names a dict's file in error messages (default: the file, or "rig config").
        ``context`` is passed to every driver's ``from_config`` (e.g. ``usb_backend=`` for the
        camera, so a simulated or custom pyusb backend can be used).
        """
        cfg = load_config(source)
        where = where or ("rig config" if isinstance(source, dict) else str(source))
        devices: dict[str, Device] = {}
        for role, section in cfg.items():
            if role == "rig":
                continue
            if section["port"] == "sim":
                raise ConfigError(f"[{role}] port = 'sim': start the simulators first "
                                  "(gonio --rig sim, or sims.lab.SimLab) and pass their ports")
            try:
                device = driver_class(section["driver"]).from_config(role, section, **context)
            except (TypeError, ValueError) as exc:
                # drivers validate their own keys and values; name the file and section for all
                text = str(exc) if str(exc).startswith("[") else f"[{role}] {exc}"
                raise ConfigError(f"{where}: {text}") from None
            if not isinstance(device, ROLES[role]):
                raise ConfigError(f"{where}: [{role}] driver {section['driver']!r} cannot serve as the "
                                  f"{role} (it does not implement {ROLES[role].__name__})")
            devices[role] = device
        return cls(**devices, config=cfg)

    @property
    def devices(self) -> dict[str, Device]:
        """Fitted devices by role, in a fixed order."""
        return {role: d for role in ROLES if (d := getattr(self, role)) is not None}

    def connect(self) -> None:
        """Connect every device; on failure, close the ones already connected and re-raise."""
        done: list[Device] = []
        try:
            for device in self.devices.values():
                device.connect()
                done.append(device)
        except BaseException:
            for device in done:
                device.close()
            raise

    def close(self) -> None:
        for device in self.devices.values():
            device.close()

    def stop_all(self) -> None:
        """Emergency stop: stop every moving device, collecting (not raising) errors."""
        errors = []
        for device in self.devices.values():
            if hasattr(device, "stop"):
                try:
                    device.stop()
                except RigError as exc:
                    errors.append(exc)
        if errors:
            raise errors[0]

    def describe(self) -> dict[str, dict[str, Any]]:
        return {role: d.describe() for role, d in self.devices.items()}

    def read(self) -> dict[str, dict[str, Any]]:
        return {role: d.read() for role, d in self.devices.items()}

    def __enter__(self) -> "Rig":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
