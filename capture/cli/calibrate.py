"""``gonio calibrate SESSION``: run the calibration pipeline on a recorded session.

Runs :func:`capture.pipeline.calibrate.calibrate_session` with a progress bar, prints a summary table
(stage, status, key figures or the reason a stage was skipped / failed), stores the results in
the session (``gonio session show`` lists them) and writes the PNG report
``<session>-calibration.png`` next to the store (or into ``--out``).

Exit status: 0 every stage that ran succeeded; 1 a stage failed (the table names the frame);
2 usage or store errors (unknown session, unreadable store, bad --targets file);
3 nothing to calibrate (no stored frames, or no calibration captures in the session), or
interrupted (Ctrl-C; the same command calibrates again).
"""
from __future__ import annotations

import errno
import json
from dataclasses import fields
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
from rich.table import Table

from rig.tomlfile import read_toml

from .interrupts import command_line, interruptible_command
from .session import STORE_OPTION, fail, open_store
from ..outputs import OutputError, check_out_folder, session_file
from ..store import ObjectDamaged, SessionBusy, SessionNotFound

if TYPE_CHECKING:
    from ..lab import LabTargets
    from ..pipeline.progress import Progress as PipelineProgress

EXIT_OK, EXIT_FAILED, EXIT_NOTHING = 0, 1, 3


class TargetsFileError(ValueError):
    """The ``--targets`` file is missing, unreadable or not TOML (the message names it)."""


def _targets(path: Path | None) -> LabTargets | None:
    """LabTargets from a TOML file of its field names (``sphere_radius_mm = 25.0`` ...); None
    without a file (the simulator's, for a session recorded on the simulated lab only)."""
    if path is None:
        return None
    from ..lab import LabTargets   # here, not at the top: it loads trimesh
    try:
        data = read_toml(path, error=TargetsFileError, what="--targets file")
    except TargetsFileError as exc:
        raise fail(str(exc)) from None
    known = {f.name for f in fields(LabTargets)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise fail(f"--targets {path}: unknown key(s) {', '.join(unknown)}; "
                   f"known: {', '.join(sorted(known))}")
    try:   # the constructor is the check of the file's values: its errors are about them
        return LabTargets(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})
    except (TypeError, ValueError) as exc:
        raise fail(f"--targets {path}: {exc}") from None


@interruptible_command(lambda session, store, targets, out, **_: (
    "the session's frames are kept and a calibration cut short is never reused; calibrate again with: "
    + command_line("gonio", "calibrate", session, store=store, targets=targets, out=out)))
def calibrate(session: str = typer.Argument(..., help="Session name (see 'gonio session list')."),
              store: str = STORE_OPTION,
              out: str = typer.Option(None, "--out", help="Folder for the PNG report "
                                       "(default: the folder holding the store)."),
              targets: Path = typer.Option(None, "--targets", help="TOML file describing the lab's "
                                           "targets (board size and height, sphere radius and lab "
                                           "positions ...: LabTargets fields); needed unless the "
                                           "session was recorded on the simulated lab (--rig sim)."),
              measurement_hdr: bool = typer.Option(True, "--measurement-hdr/--calibration-hdr-only",
                                                   help="Merge every measurement step's bracket too "
                                                   "(slow for big sessions) or only the calibration steps."),
              as_json: bool = typer.Option(False, "--json",
                                           help="Print the stages as JSON instead of a table."),
              quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar.")) -> None:
    """Calibrate a session from its own captures and write the PNG report.

    Every stage's result is stored in the session (gonio session show lists them); the report is
    <session>-calibration.png beside the store, or in --out.

    Exit status: 0 every stage that ran succeeded, 1 a stage failed, 2 bad input, 3 nothing to
    calibrate or interrupted.
    """
    from ..pipeline.calibrate import STAGES, NothingToCalibrate, TargetsNeeded, calibrate_session
    lab_targets = _targets(targets)
    if out is not None:
        try:   # before the work: a file given as the folder would fail at the end
            out = check_out_folder(out)
        except OutputError as exc:
            raise fail(str(exc)) from None
    console = Console()
    with open_store(store) as st:
        try:
            st.session(session)
        except SessionNotFound as exc:
            raise fail(str(exc)) from None
        with Progress(TextColumn("calibrating {task.fields[stage]}"), BarColumn(), MofNCompleteColumn(),
                      console=Console(stderr=True), transient=True, disable=quiet) as progress:
            task = progress.add_task("calibrate", total=len(STAGES), stage="")

            def advance(p: PipelineProgress) -> None:
                part = p.part if p.part_total is None else f"{p.part} {p.part_done}/{p.part_total}"
                progress.update(task, completed=p.done, stage=part)

            try:
                with st.writer(session):   # one calibration or process per session at a time
                    report = calibrate_session(st, session, progress=advance, targets=lab_targets,
                                               measurement_hdr=measurement_hdr)
            except (TargetsNeeded, SessionBusy, ObjectDamaged) as exc:
                progress.stop()
                raise fail(str(exc)) from None
            except NothingToCalibrate as exc:
                progress.stop()
                typer.secho(f"nothing to calibrate: {exc}", err=True, fg=typer.colors.YELLOW)
                raise typer.Exit(EXIT_NOTHING) from None
        from ..pipeline.calibration_report import write_report  # here, not at the top: matplotlib would slow every gonio start
        folder = out if out is not None else Path(st.root).resolve().parent
        try:  # a name from before names were checked: capture.outputs.session_file
            png = write_report(report, session_file(folder, session, st.session(session).id, "-calibration.png"))
        except OutputError as exc:
            raise fail(str(exc)) from None
        except OSError as exc:
            if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            raise fail(f"the disk holding {Path(exc.filename or folder).parent} is full: the calibration is "
                       "stored (gonio session show lists it) but its PNG report could not be written (no partial "
                       "file is left); free space, then run the same command to calibrate and draw it again") from None
        if as_json:
            stages = [{"stage": s.stage, "status": s.status, "reason": s.reason, "figures": s.figures,
                       "calibration_id": s.calibration_id, "seconds": s.seconds} for s in report.stages]
            typer.echo(json.dumps({"session": session, "report": str(png), "stages": stages}, indent=2))
            raise typer.Exit(EXIT_FAILED if report.failed else EXIT_OK)
        table = Table(title=f"calibration of session {escape(session)}")
        for col in ("stage", "status", "s", "key figures / reason"):
            table.add_column(col, overflow="fold", justify="right" if col == "s" else "left")
        colour = {"ok": "green", "skipped": "yellow", "failed": "red"}
        for s in report.stages:
            text = ", ".join(f"{k} {v}" for k, v in s.figures.items()) if s.status == "ok" else s.reason
            table.add_row(s.stage, f"[{colour[s.status]}]{s.status}[/]", f"{s.seconds:.1f}", escape(text))
        console.print(table)
        stored = sum(s.calibration_id is not None for s in report.stages)
        console.print(escape(f"stored {stored} calibration result(s) in {st.root}; report: {png}"),
                      highlight=False)
    raise typer.Exit(EXIT_FAILED if report.failed else EXIT_OK)
