"""``gonio process SESSION``: calibrate (if needed), reconstruct with every method, write the report.

Runs :func:`capture.pipeline.run.process_session` with a progress bar, prints one row per method
(stored, skipped with the reason, failed with the error; held-out relative RMS) and the path of
the HTML report (``<session>-report.html`` beside the store, or ``--out``).

Exit status: 0 every method that ran succeeded; 1 a method failed; 2 usage or store errors
(unknown session, unreadable mesh or targets file, a bad --out, the session being written by
another process, a damaged frame: the message names its step); 3 the session cannot give
reconstruction inputs (no measurement steps, a stage of the calibration missing: the message says
which), or it was interrupted (Ctrl-C, SIGTERM: what was stored is kept, and the same command
resumes). A full disk pauses it (the message says where and how much space it waits for) and it
resumes by itself once there is room.
"""
from __future__ import annotations

import errno
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
from rich.table import Table

from ..outputs import OutputError, check_out_file, session_file
from ..store import ObjectDamaged, SessionBusy, SessionNotFound, StoreFull
from .calibrate import _targets
from .interrupts import command_line, interruptible_command
from .session import STORE_OPTION, fail, human_bytes, open_store

if TYPE_CHECKING:
    from ..pipeline.progress import Progress as PipelineProgress
    from ..pipeline.run import ProcessReport

EXIT_OK, EXIT_FAILED, EXIT_NO_INPUTS = 0, 1, 3
#: how often a process paused on a full disk looks at the free space again, s
SPACE_POLL_S = 5.0
#: the largest --memory-limit, MiB (beyond any machine: a typo, or inf)
MAX_MEMORY_LIMIT_MIB = float(2**30)
#: the least free space a paused process waits for, bytes
MIN_FREE_TO_RESUME = 64 << 20


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
    from ..pipeline.report_html import summary_note
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
                      escape(summary_note(m, f) or m.reason or "; ".join(m.warnings)))
    console.print(table)
    console.print(f"floor (the true model on the same held-out captures): {rep.floor.held_out_rel_rms:.3f}"
                  if rep.floor is not None else "floor: none (no ground truth; it exists for sessions "
                  "captured in the simulated lab)", highlight=False, soft_wrap=True)
    console.print(f"report: {escape(str(rep.report_path))}", highlight=False, soft_wrap=True)


def _full_disk_folder(exc: BaseException, store_root: Path) -> Path | None:
    """The folder whose disk filled up when ``exc`` is a full disk (the store's, or the file's
    that ``write_atomically`` names), else None."""
    if isinstance(exc, StoreFull):
        return store_root
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return Path(exc.filename).parent if exc.filename else store_root
    return None


def free_bytes(folder: Path) -> int:
    """Free space on the disk holding ``folder``, bytes."""
    return shutil.disk_usage(folder).free


def _pausing_on_a_full_disk(run: Callable[[bool], ProcessReport], store_root: Path, frame_bytes: int,
                            console: Console) -> ProcessReport:
    """``run(first)`` (:func:`process_session`; ``first`` False once resuming, so ``--force``
    redoes the work once only), paused while the disk is full, as a capture pauses: what was
    stored is kept; the message says where and how much space is wanted; the free space is looked
    at every :data:`SPACE_POLL_S` until there is that much, then ``run(False)`` resumes (stored
    calibration, lumitexel arrays and methods are reused). Ctrl-C ends the wait (exit 3); the same
    command resumes later.

    The space wanted is the session's frames' bytes ``frame_bytes`` (processing writes less:
    6.4 MB of lumitexel arrays, 0.3 MB of report and results for the 11.6 MB of frames of the
    suite's session), at least :data:`MIN_FREE_TO_RESUME`."""
    need, first = max(MIN_FREE_TO_RESUME, frame_bytes), True
    while True:
        try:
            return run(first)
        except (StoreFull, OSError) as exc:
            folder = _full_disk_folder(exc, store_root)
            if folder is None:
                raise
            console.print(escape(f"paused: the disk holding {folder} is full ({human_bytes(free_bytes(folder))} "
                                 f"free: {exc}); every calibration stage and method stored so far is kept. "
                                 f"Waiting for {human_bytes(need)} free there, then resuming (Ctrl-C stops; "
                                 "the same command resumes later)"), highlight=False, soft_wrap=True)
            while free_bytes(folder) < need:
                time.sleep(SPACE_POLL_S)
            console.print(f"resuming: {human_bytes(free_bytes(folder))} free", highlight=False)
            first = False


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
                                               "machine's memory). Where the gathered lumitexels would "
                                               "exceed it, the methods run over texel blocks (Lensch's "
                                               "materials and sharing's RBFs on a stated subsample)."),
            quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar.")) -> None:
    """Reconstruct a captured session with every method its captures allow and write the report.

    What is stored is reused: a calibration complete for the session's captures, the lumitexel
    arrays of the same inputs, each method already fitted (--force redoes them). Ctrl-C, a killed
    process or a full disk (which pauses until there is room) keep everything stored; run the
    same command again to carry on.

    Exit status: 0 done, 1 a method failed, 2 bad input, 3 interrupted or no measurement to
    process.
    """
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
    from ..lab_resolver import resolve_lab
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
    if memory_limit is not None and not memory_limit <= MAX_MEMORY_LIMIT_MIB:   # also true for NaN
        raise fail(f"--memory-limit must be at most {MAX_MEMORY_LIMIT_MIB:g} MiB (1 PiB), got {memory_limit!r}")
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
        imported = is_imported(st, session)
        if not imported:   # an imported set has no rig and no mesh: its own path
            lab = resolve_lab(st, session, mesh=kw.pop("mesh", None), targets=kw.pop("targets", None))
            if lab.mesh is None:
                raise fail("--mesh FILE is needed: the object's mesh (sessions recorded on --rig sim bring "
                           "their own)")
            kw["lab"] = lab
        # a stored name is not trusted as a file name (``../../x``): see capture.outputs
        report_path = out if out is not None else session_file(Path(st.root).resolve().parent, session,
                                                               info.id, "-report.html")
        bar, update = progress_bar(quiet)
        with bar:
            try:
                rep = _pausing_on_a_full_disk(
                    lambda first: process_session(st, session, methods=names, force=force and first, progress=update,
                                            report_path=report_path, say=lambda text: console.print(escape(text)),
                                            **kw),
                    Path(st.root), st.progress(info.id).bytes_stored, bar.console)
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
    failed = any(m.status == "failed" for m in rep.methods)
    if as_json:
        typer.echo(rep.report_path.with_suffix(".json").read_text())
    else:
        print_outcome(rep, console)
    raise typer.Exit(EXIT_FAILED if failed else EXIT_OK)
