"""``gonio tui``: the operator console (a Textual terminal UI) over the rig, store and runner."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

#: the slowest device-table refresh, s
MAX_POLL_S = 60.0


def tui(rig: str = typer.Option("sim", "--rig",
                                help="'sim' for the built-in simulated lab, or a rig TOML file."),
        store: str = typer.Option("gonio-store", "--store", envvar="GONIO_STORE",
                                  help="Session store directory (created if missing). Env: GONIO_STORE."),
        plan: Optional[Path] = typer.Option(None, "--plan", help="Open this plan file at start."),
        fast: bool = typer.Option(False, help="Simulated devices move instantly."),
        poll: float = typer.Option(0.25, help="Device table refresh period, seconds."),
        mesh: Optional[Path] = typer.Option(None, "--mesh", help="The object's mesh, for processing "
                                            "sessions (P on the Session tab); sessions recorded on "
                                            "--rig sim bring their own.")) -> None:
    """Open the operator console (terminal UI).

    Devices (jog, home, stop, camera test shot), sessions (plan, start, pause, resume, abort,
    progress, process), preview with histograms, and the event log. Press F1 inside for the keys.
    """
    if not 0 < poll <= MAX_POLL_S:   # also false for NaN
        raise typer.BadParameter(f"must be > 0 seconds and at most {MAX_POLL_S:g}, got {poll}", param_hint="--poll")
    from .session import check_store_option
    check_store_option(store, readonly=False)   # "" (the current folder) or an archive: refused
    if plan is not None and not plan.is_file():
        raise typer.BadParameter(f"plan file {plan} does not exist", param_hint="--plan")
    process_options: dict = {}
    if mesh is not None:
        from ..pipeline.mesh_checks import MeshError, load_mesh
        try:
            process_options["mesh"] = load_mesh(mesh)
        except MeshError as exc:
            raise typer.BadParameter(str(exc), param_hint="--mesh") from None
    from ..tui import GonioApp  # Textual loads only for this command
    GonioApp(rig, Path(store), fast=fast, poll_s=poll, plan=plan, process_options=process_options).run()
