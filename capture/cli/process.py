"""``gonio process SESSION``: calibrate (if needed), reconstruct with every method, write the report.

Runs :func:`capture.pipeline.run.process_session` with a progress bar, prints one row per method
(stored, skipped with the reason, failed with the error; held-out relative RMS) and the path of
the HTML report (``<session>-report.html`` beside the store, or ``--out``).

Exit status: 0 every method that ran succeeded; 1 a method failed; 2 usage or store errors
(unknown session, unreadable mesh or targets file, a bad --out, the session being written by
another process, a damaged frame: the message names its step); 3 the session cannot give
reconstruction inputs (no measurement steps, a stage of the calibration missing: the message says
which), or it was interrupted (Ctrl-C, SIGTERM: what was stored is kept, and the same command
resumes); 4 the disk filled up: what was stored is kept, and the same command resumes.
"""
from __future__ import annotations

import errno
from pathlib import Path
from typing import Callable

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
from rich.table import Table

from ..outputs import OutputError, check_out_file, session_file
from ..pipeline.progress import Progress as PipelineProgress
from ..store import ObjectDamaged, SessionBusy, SessionNotFound, StoreFull
from .calibrate import _targets
from .interrupts import command_line, interruptible_command
from .session import STORE_OPTION, fail, open_store

EXIT_OK, EXIT_FAILED, EXIT_NO_INPUTS, EXIT_DISK_FULL = 0, 1, 3, 4


def progress_bar(quiet: bool) -> tuple[Progress, Callable[[PipelineProgress], None]]:
    """A rich progress bar on stderr and the progress sink (:mod:`capture.pipeline.progress`)
    feeding it."""
    bar = Progress(TextColumn("{task.fields[stage]:<12}"), BarColumn(), MofNCompleteColumn(),
                   console=Console(stderr=True), transient=True, disable=quiet)
    task = bar.add_task("process", total=1, stage="")

    def update(p: PipelineProgress) -> None:
        label = f"{p.stage} {p.part}" if p.part else p.stage
        bar.update(task, completed=p.done, total=max(p.total, 1), stage=label)
    return bar, update


def print_outcome(rep, console: Console) -> None:
    """The methods table and the report path."""
    table = Table(title=f"reconstruction of session {escape(rep.session)}")
    for col in ("method", "status", "s", "held-out rel. RMS", "x floor", "vs truth", "note"):
        table.add_column(col, overflow="fold")
    colour = {"ok": "green", "done": "cyan", "skipped": "yellow", "failed": "red"}
    for m in rep.methods:
        f = m.figures
        table.add_row(m.method, f"[{colour[m.status]}]{m.status}[/]", f"{m.seconds:.1f}",
                      f"{f['held_out_rel_rms']:.3f}" if "held_out_rel_rms" in f else "",
                      f"{m.floor_ratio:.2f}" if m.floor_ratio is not None else "",
                      f"{f['truth_rel_rms']:.3f}" if "truth_rel_rms" in f else "",
                      escape(f"outside its assumption: {m.outside_assumption}" if m.outside_assumption
                             else m.reason or "; ".join(m.warnings)))
    console.print(table)
    console.print(f"floor (the true model on the same held-out captures): {rep.floor.held_out_rel_rms:.3f}"
                  if rep.floor is not None else "floor: none (no ground truth; it exists for sessions "
                  "captured in the simulated lab)", highlight=False, soft_wrap=True)
    console.print(f"report: {escape(str(rep.report_path))}", highlight=False, soft_wrap=True)


def process_command(session: str, store: str, methods: str | None = None, mesh: Path | None = None,
                    targets: Path | None = None, out: Path | None = None, **_) -> str:
    """The ``gonio process`` command line that continues an interrupted one."""
    return command_line("gonio", "process", session, store=store, methods=methods, mesh=mesh,
                        targets=targets, out=out)


@interruptible_command(lambda **kw: "every calibration stage and method stored so far is kept; resume "
                       "with: " + process_command(**kw))
def process(session: str = typer.Argument(..., help="Session name (see 'gonio session list')."),
            store: str = STORE_OPTION,
            methods: str = typer.Option(None, "--methods", help="Comma-separated methods to run "
                                        "(default: lambertian,lensch,sharing,passive)."),
            mesh: Path = typer.Option(None, "--mesh", help="The object's mesh (any format trimesh "
                                      "reads), object frame = lab frame at turntable reading 0, mm. "
                                      "A session recorded on --rig sim brings its own (with targets, "
                                      "gray-card pose and ground truth)."),
            targets: Path = typer.Option(None, "--targets", help="TOML file of the lab's targets "
                                         "(LabTargets fields), for a calibration run here."),
            force: bool = typer.Option(False, "--force", help="Re-run the calibration and every method "
                                       "even when stored."),
            out: Path = typer.Option(None, "--out", help="Report file (default: <session>-report.html "
                                     "beside the store)."),
            as_json: bool = typer.Option(False, "--json", help="Print the outcome as JSON."),
            workers: int = typer.Option(0, "--workers", min=0, help="Run the per-view tasks on a local Dask "
                                        "cluster of N worker processes (0: in this process)."),
            scheduler: str = typer.Option(None, "--scheduler", help="Address of a running Dask scheduler "
                                          "(tcp://HOST:8786); its workers must see the store at the same path."),
            memory_limit: float = typer.Option(None, "--memory-limit", min=1, help="MiB the per-view tasks may "
                                               "hold together (sets the texel chunk; default: half the "
                                               "machine's memory)."),
            quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar.")) -> None:
    """Reconstruct a captured session with every method its captures allow and write the report."""
    from ..pipeline.methods import DEFAULT_METHODS, METHODS
    from ..pipeline.run import process_session
    from ..pipeline.imported import is_imported
    from ..pipeline.mesh_checks import MeshError, load_mesh
    from ..pipeline.process import ProcessError
    names = DEFAULT_METHODS if methods is None else tuple(m.strip() for m in methods.split(",") if m.strip())
    if not names:
        raise fail(f"--methods {methods!r} names no method; known: {', '.join(METHODS)}")
    unknown = [m for m in names if m not in METHODS]
    if unknown:
        raise fail(f"--methods: unknown {', '.join(unknown)}; known: {', '.join(METHODS)}")
    from ..rigs import recorded_in_built_in_lab
    if out is not None:
        try:   # before any work: a folder, /dev/full or a missing folder would fail at the end
            check_out_file(out)
        except OutputError as exc:
            raise fail(str(exc)) from None
    from ..pipeline.cluster import ClusterError, ClusterOptionError, ClusterOptions
    from ..pipeline.images import FrameDataError
    from ..pipeline.lumitexel_arrays import MemoryLimitError
    try:
        cluster = ClusterOptions(workers=workers, scheduler=scheduler)
    except ClusterOptionError as exc:
        raise fail(str(exc)) from None
    kw = {"cluster": cluster, "memory_limit": None if memory_limit is None else int(memory_limit * 2**20)}
    if mesh is not None:
        try:
            kw["mesh"] = load_mesh(mesh)
        except MeshError as exc:
            raise fail(str(exc)) from None
    if targets is not None:
        kw["targets"] = _targets(targets)
    console = Console()
    with open_store(store) as st:
        try:
            info = st.session(session)
        except SessionNotFound as exc:
            raise fail(str(exc)) from None
        if mesh is None and not recorded_in_built_in_lab(st.rig_snapshots(info.id)) and \
                not is_imported(st, session):
            raise fail("--mesh FILE is needed: the object's mesh (sessions recorded on --rig sim bring "
                       "their own)")
        # a stored name is not trusted as a file name (``../../x``): see capture.outputs
        report_path = out if out is not None else session_file(Path(st.root).resolve().parent, session,
                                                               info.id, "-report.html")
        bar, update = progress_bar(quiet)
        with bar:
            try:
                rep = process_session(st, session, methods=names, force=force, progress=update,
                                      report_path=report_path, say=lambda text: console.print(escape(text)), **kw)
            except MeshError as exc:   # the mesh against the calibration: the user's input
                bar.stop()
                raise fail(str(exc)) from None
            except ProcessError as exc:
                bar.stop()
                typer.secho(f"cannot process: {exc}", err=True, fg=typer.colors.YELLOW)
                raise typer.Exit(EXIT_NO_INPUTS) from None
            except (ClusterError, MemoryLimitError, FrameDataError, SessionBusy, ObjectDamaged, OutputError) as exc:
                bar.stop()   # any other error is a bug: its traceback is kept
                raise fail(str(exc)) from None
            except (StoreFull, OSError) as exc:
                if isinstance(exc, OSError) and exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                    raise
                bar.stop()
                raise fail(f"the disk is full ({exc}); every calibration stage and method stored so "
                           f"far is kept: free space and run the same command again to resume",
                           EXIT_DISK_FULL) from None
    failed = any(m.status == "failed" for m in rep.methods)
    if as_json:
        typer.echo(rep.report_path.with_suffix(".json").read_text())
    else:
        print_outcome(rep, console)
    raise typer.Exit(EXIT_FAILED if failed else EXIT_OK)
