"""``gonio rig``: check, home and simulate the rig.

- ``gonio rig check --rig sim|FILE`` connects every device and prints a table (role, driver,
  model, firmware, serial, position with units, homed, port); exit status 1 if any device fails.
- ``gonio rig home --rig sim|FILE`` homes every axis (or those named with ``--role``) at once.
- ``gonio rig sim`` starts the simulated lab, prints the ports and a rig TOML another process can
  use, and serves until Ctrl-C.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from rig import RigError
from rig.rig import MAX_DURATION_S, ROLES

from ..outputs import OutputError, check_out_file, write_atomically

app = typer.Typer(name="rig", help="Check, home and simulate the measurement rig.", no_args_is_help=True)

RIG_HELP = "'sim' for the built-in simulated lab, or a rig TOML file (driver and port per device)."


def _fail(message: str, code: int = 2) -> typer.Exit:
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    return typer.Exit(code)


def _open(rig: str, fast: bool, connect: bool):
    from ..rigs import open_rig   # here, not at the top: the simulated lab and its scenes load with it
    try:
        return open_rig(rig, fast=fast, connect=connect)
    except (RigError, OSError) as exc:   # a bad rig file is a ConfigError (a RigError)
        raise _fail(f"cannot open rig {rig!r}: {exc}") from None


@app.command()
def check(rig: str = typer.Option("sim", "--rig", help=RIG_HELP),
          fast: bool = typer.Option(True, help="Simulated devices move instantly."),
          as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table.")) -> None:
    """Connect every device, print what it is and where it stands; exit 1 if any fails."""
    from ..rigs import position_text
    opened = _open(rig, fast, connect=False)
    rows: list[dict[str, Any]] = []
    with opened:
        for role, device in opened.rig.devices.items():
            row: dict[str, Any] = {"role": role, "driver": opened.rig.config[role]["driver"],
                                   "port": opened.rig.config[role]["port"]}
            try:
                device.connect()
                info = device.describe()
                row.update(model=info.get("model", ""), firmware=info.get("firmware", ""),
                           serial=str(info.get("serial") or info.get("serial_number") or ""), position=position_text(device),
                           homed=getattr(device, "homed", None), ok=True)
            except RigError as exc:
                row.update(ok=False, error=str(exc))
            rows.append(row)
    failed = [r for r in rows if not r["ok"]]
    if as_json:
        typer.echo(json.dumps(rows, indent=2))
    else:
        table = Table(title=f"rig: {escape(rig)}")
        for column in ("role", "driver", "model", "firmware", "serial", "position", "homed", "port"):
            table.add_column(column, overflow="fold")
        e = lambda v: escape(str(v))  # noqa: E731 - file and device text, never markup
        for r in rows:
            if r["ok"]:
                homed = {True: "yes", False: "no", None: "-"}[r["homed"]]
                table.add_row(r["role"], e(r["driver"]), e(r["model"]), e(r["firmware"]),
                              e(r["serial"]), e(r["position"]), homed, e(r["port"]))
            else:
                table.add_row(r["role"], e(r["driver"]), "[red]FAILED[/red]", "", "", e(r["error"]),
                              "", e(r["port"]))
        Console(width=160).print(table)
    if not rows:
        raise _fail("the rig has no devices", 1)
    if failed:
        raise _fail(f"{len(failed)} of {len(rows)} device(s) failed: "
                    + "; ".join(f"{r['role']}: {r['error']}" for r in failed), 1)


def _check_seconds(option: str, value: float, why: str = "") -> None:
    """A duration option: more than 0 and at most a day (the rig file's bound), else exit 2."""
    if not 0 < value <= MAX_DURATION_S:   # also false for NaN
        raise _fail(f"{option} must be more than 0 and at most {MAX_DURATION_S:g} s (a day){why}, got {value!r}")


@app.command()
def home(rig: str = typer.Option("sim", "--rig", help=RIG_HELP),
         role: Optional[list[str]] = typer.Option(None, "--role", help="Only these roles (repeatable)."),
         fast: bool = typer.Option(True, help="Simulated devices move instantly."),
         timeout: float = typer.Option(120.0, help="Seconds allowed for homing.")) -> None:
    """Home the axes and the light positioner (all at the same time)."""
    from ..rigs import home_all, position_text
    if role:
        bad = set(role) - set(ROLES)
        if bad:
            raise _fail(f"unknown role(s) {sorted(bad)}; roles are {', '.join(ROLES)}")
    _check_seconds("--timeout", timeout)
    opened = _open(rig, fast, connect=True)
    with opened:
        try:
            results = home_all(opened.rig, timeout_s=timeout, roles=role or None)
        except RigError as exc:
            raise _fail(f"homing failed: {exc}", 1) from None
        for name in results:
            typer.echo(f"{name:<11} homed at {position_text(opened.rig.devices[name])}")


@app.command()
def sim(fast: bool = typer.Option(False, help="Complete moves instantly (default: real motion time)."),
        kinematics: str = typer.Option("arm", help="Positioner kinematics: arm or gantry."),
        write: Optional[Path] = typer.Option(None, help="Also write the rig TOML to this file."),
        duration: Optional[float] = typer.Option(None, help="Stop after this many seconds (scripts)."),
        ) -> None:
    """Run the simulated serial devices for another process; print their ports and a rig TOML."""
    from sims.lab import KINEMATICS, SimLab
    from ..rigs import to_toml

    if kinematics not in KINEMATICS:
        raise _fail(f"--kinematics must be one of {', '.join(KINEMATICS)}, got {kinematics!r}")
    if duration is not None:
        _check_seconds("--duration", duration, " (without it the simulators serve until Ctrl-C)")
    if write is not None:
        try:   # before the simulators start: a folder, /dev/full or a missing folder
            check_out_file(write, "--write")
        except OutputError as exc:
            raise _fail(str(exc)) from None
    lab = SimLab(fast=fast, kinematics=kinematics, roles=("turntable", "positioner", "polarizer")).start()
    try:
        cfg = lab.rig_config()
        toml = ("# gonio simulated lab: serial devices on pseudo-terminals.\n"
                "# The camera simulator is an in-process pyusb backend; use --rig sim for it.\n"
                + to_toml(cfg))
        for role, section in cfg.items():
            if role != "rig":
                typer.echo(f"{role:<11} {section['driver']:<9} {section['port']}")
        typer.echo("")
        typer.echo(toml)
        if write is not None:
            try:
                write_atomically(write, toml)
            except OSError as exc:
                raise _fail(f"--write {write}: {exc.strerror or exc}") from None
            typer.echo(f"rig file written to {write}")
        typer.echo("serving; press Ctrl-C to stop", err=True)
        try:
            if duration is not None:
                time.sleep(duration)
            else:
                while True:  # the simulators serve on their own threads
                    time.sleep(3600)
        except KeyboardInterrupt:
            pass
    finally:
        lab.stop()
    typer.echo("simulators stopped", err=True)
