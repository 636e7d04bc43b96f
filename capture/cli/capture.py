"""``gonio capture``: plan, run and resume capture sessions.

- ``gonio capture plan PLAN [--rig sim|FILE] [--steps]`` validates the plan (against the rig's
  limits when ``--rig`` is given) and prints steps, frames, bytes and time.
- ``gonio capture run PLAN --rig sim|FILE --store DIR [--session NAME]`` records a new session
  with a progress bar (steps, frames, ETA).
- ``gonio capture resume NAME --rig ... --store DIR`` continues from the first step not done,
  refusing (with the differences) if the plan file changed since the session was planned.

Ctrl-C pauses after the current step (state saved); a second Ctrl-C stops motion at once (the
interrupted step is re-done on resume). Exit status: 0 done, 3 paused, 4 aborted, 2 errors.
"""
from __future__ import annotations

import contextlib
import shlex
import sys
import threading
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from rig import LightTarget, RigError

from .session import (STORE_OPTION, check_store_option, display_state, fail, human_bytes, human_time, open_store,
                          unwrap)
from .sim import MAX_SIDE_PX
from .interrupts import command_line, counted, interruptible, interruptible_command
from ..events import Event, EventKind
from ..plan import Estimate, MotionModel, Plan, PlanError, Step, step_prompt
from ..store import Store, StoreError, check_session_name

if TYPE_CHECKING:
    from ..rigs import OpenedRig
    from ..runner import Runner

HELP = """Plan, run and resume capture sessions.

A plan is a TOML file naming what to measure: turntable angles, light directions on the
positioner's sphere (or xyz points), polarizer angles, the exposure bracket (base and stops, or
auto-metered), repeats, and calibration captures (dark, checkerboard, spheres, gray card, mirror
probe). Units: degrees, millimetres, seconds. Example with every field: examples/plan.toml.
'gonio capture plan PLAN --rig sim' checks it against the rig's limits and prints the steps,
frames, bytes and time it will take.

'gonio capture run PLAN --rig sim|RIG.toml --store DIR' records a new session in the store
folder DIR: DIR/gonio.sqlite holds the plan, its steps, every frame's row (read-back positions,
the camera's exposure and ISO) and every event; DIR/objects/ holds the frames, the camera's own
DNG bytes, named by their SHA-256. A step counts as done only once its frames are on disk.

Ctrl-C pauses after the current step (a second Ctrl-C stops motion at once). Device faults that
retries cannot clear and low disk space pause the session with the reason; a crash or power cut
leaves it interrupted. Either way 'gonio capture resume NAME --rig ... --store DIR' continues
from the first step not done, and refuses, listing the differences, if the plan file changed.
'gonio session list|show|verify|export' inspects what was recorded.

Exit status: 0 done, 3 paused (resume it), 4 aborted, 2 error (bad plan, rig, store or too
little disk space; nothing was captured).
"""
app = typer.Typer(name="capture", help=unwrap(HELP), no_args_is_help=True)


def _command(f):
    """``app.command()`` with the docstring's paragraphs unwrapped for the terminal."""
    return app.command(help=unwrap(f.__doc__))(f)

RIG_HELP = "'sim' for the built-in simulated lab, or a rig TOML file (driver and port per device)."
SIM_CAMERA_HELP = ("Resolution WIDTHxHEIGHT of the simulated lab's camera (--rig sim; default 320x240, "
                   "640x480 with --no-fast; examples/demo.toml is made for 640x480).")
EXIT = {"done": 0, "paused": 3, "aborted": 4}


def _load_plan(path: Path) -> Plan:
    try:
        return Plan.from_toml(path)
    except PlanError as exc:
        raise fail(str(exc)) from None


def _sim_camera(text: str | None, rig: str | None) -> dict[str, Any]:
    """``--sim-camera 640x480`` -> ``open_rig``'s ``resolution`` option (empty when not given)."""
    if text is None:
        return {}
    if rig != "sim":
        raise fail(f"--sim-camera sets the simulated lab's camera; it needs --rig sim, got --rig {rig!r}")
    width, _, height = text.lower().partition("x")
    size = (int(width), int(height)) if width.isdigit() and height.isdigit() else None
    if size is None or min(size) < 16 or max(size) > MAX_SIDE_PX or size[0] % 2 or size[1] % 2:
        raise fail(f"--sim-camera must be WIDTHxHEIGHT in pixels, each even and in 16..{MAX_SIDE_PX} (a "
                   f"Bayer mosaic; e.g. 640x480), got {text!r}")
    return {"resolution": size}


def _open_rig(spec: str, fast: bool, sim_camera: str | None = None) -> OpenedRig:
    from ..rigs import open_rig   # here, not at the top: the simulated lab and its scenes load with it
    options = _sim_camera(sim_camera, spec)
    try:
        return open_rig(spec, fast=fast, **options)
    except (RigError, OSError) as exc:   # a bad rig file is a ConfigError (a RigError)
        raise fail(f"cannot open rig {spec!r}: {exc}") from None


def _light_text(light: LightTarget | None) -> str:
    if light is None:
        return "-"
    if light.xyz_mm is not None:
        return "({:g}, {:g}, {:g}) mm".format(*light.xyz_mm)
    return f"az {light.azimuth_deg:g}° el {light.elevation_deg:g}°"


@_command
def plan(plan_file: Path = typer.Argument(..., help="Plan TOML file."),
         rig: Optional[str] = typer.Option(None, "--rig", help=RIG_HELP + " Checks limits and uses "
                                           "the devices' speeds; without it, default speeds."),
         steps: bool = typer.Option(False, "--steps", help="Also list every step."),
         fast: bool = typer.Option(True, help="Simulated devices move instantly."),
         sim_camera: Optional[str] = typer.Option(None, "--sim-camera", help=SIM_CAMERA_HELP)) -> None:
    """Validate a plan and print its steps, frames, bytes and estimated time.

    With --rig the plan is checked against the devices' limits and timed with their speeds;
    nothing moves. Exit status 0 when the plan is valid, 2 otherwise (the message names the
    field, e.g. light.elevation_deg[3]).
    """
    p = _load_plan(plan_file)
    _sim_camera(sim_camera, rig)  # --sim-camera without --rig sim: an error before anything opens
    opened = _open_rig(rig, fast, sim_camera) if rig else None
    try:
        if opened is not None:
            try:
                p.check_rig(opened.rig)
            except PlanError as exc:
                raise fail(f"{plan_file}: {exc}") from None
        the_rig = opened.rig if opened is not None else None
        expanded = p.steps(the_rig)
        est = p.estimate(the_rig, expanded)
    finally:
        if opened is not None:
            opened.close()
    c = Console(width=140, highlight=False)
    c.print(f"plan [bold]{escape(p.name or plan_file.stem)}[/] ({escape(str(plan_file))}), "
            f"hash {p.hash[:12]}")
    c.print(f"rig: {escape(rig)} (limits checked, device speeds)" if rig else
            "rig: none given (limits not checked, default speeds)")
    c.print(f"steps {est.steps}, frames {est.frames}, data {human_bytes(est.bytes)}, time "
            f"{human_time(est.seconds)} (motion {human_time(est.motion_s)}, exposure "
            f"{human_time(est.exposure_s)}, readout/transfer {human_time(est.overhead_s)})")
    c.print(_frame_size_text(est, rig is not None))
    by_kind: Counter[str] = Counter()
    frames_by_kind: Counter[str] = Counter()
    for s in expanded:
        by_kind[s.kind] += 1
        frames_by_kind[s.kind] += s.frames
    c.print("by kind: " + ", ".join(f"{escape(k)} {n} step{'s' if n > 1 else ''} / {frames_by_kind[k]} frames"
                                    for k, n in by_kind.items()))
    if steps:
        table = Table()
        for col in ("#", "kind", "target", "turntable", "light", "polarizer", "exposures (s)", "repeats"):
            table.add_column(col)
        for s in expanded:
            table.add_row(str(s.index), escape(s.kind), escape(s.target),
                          "-" if s.turntable_deg is None else f"{s.turntable_deg:g}°",
                          _light_text(s.light), "-" if s.polarizer_deg is None else f"{s.polarizer_deg:g}°",
                          ", ".join(f"{t:g}" for t in s.exposures_s), str(s.repeats))
        c.print(table)


def _frame_size_text(est: Estimate, with_rig: bool, running: bool = False) -> str:
    size = human_bytes(est.frame_bytes)
    if not est.frame_bytes_assumed:
        source = "from the camera" if est.frame_bytes_source == "camera" else "measured"
        return f"frame size {size} ({source})"
    why = "the camera does not report its image size" if with_rig else "no --rig given"
    who = ("the first frame captured will tell" if running
           else "'gonio capture run' measures the first frame")
    return f"frame size {size} assumed ({why}); {who} and the bytes are re-estimated"


class _ProgressView:
    """Turns runner events into a rich progress bar plus lines for notable events."""

    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self.task = None

    def __call__(self, e: Event) -> None:
        d = e.data
        if "steps_total" in d:
            fields = dict(frames=f"{d['frames_done']}/{d['frames_total']} frames",
                          eta=f"ETA {human_time(d.get('eta_s'))}")
            if self.task is None:
                self.task = self.progress.add_task(escape(e.session), total=d["steps_total"],
                                                   completed=d["steps_done"], **fields)
            self.progress.update(self.task, completed=d["steps_done"], **fields)
        if e.kind in (EventKind.RETRY, EventKind.FAULT, EventKind.LOW_DISK):
            self.progress.console.print(f"[yellow]{e.kind.value}[/] {escape(e.device or '')} "
                                        f"{escape(e.message)}", highlight=False)
        elif e.kind in (EventKind.TARGET, EventKind.NOTE, EventKind.METERED, EventKind.PAUSED,
                        EventKind.ABORTED):
            self.progress.console.print(f"{e.kind.value}: {escape(e.message)}", highlight=False)


def _target_handler(opened: OpenedRig, yes: bool):
    """Who sets up each calibration target: the simulated scene (``--rig sim``), the operator
    (real rig, interactive terminal, no ``--yes``), or nobody (a ``target`` line is printed)."""
    if opened.prepare_target is not None:
        return opened.prepare_target
    if yes or not sys.stdin.isatty():
        return None

    def ask(target: str, step: Step) -> None:
        typer.prompt(f"step {step.index} needs '{target}' in front of the camera ({step_prompt(step)}); "
                     "set it up and press Enter", default="", show_default=False)
    return ask


def _execute(runner: Runner, store_path: str, quiet: bool, interrupts: list[int],
             rig_spec: str) -> None:
    """Run in a worker thread so Ctrl-C here can ask for a pause (then a stop) cleanly;
    ``interrupts`` is :func:`capture.cli.interrupts.counted`'s list; ``rig_spec`` the --rig given (for the
    resume hint)."""
    from ..runner import RunnerError
    columns = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
               TextColumn("steps"), TextColumn("{task.fields[frames]}"), TimeElapsedColumn(),
               TextColumn("{task.fields[eta]}")]
    outcome: dict[str, Any] = {}
    finished = threading.Event()

    def work() -> None:
        try:
            outcome["state"] = runner.run()
        except BaseException as exc:  # noqa: BLE001 - reported on the main thread
            outcome["error"] = exc
        finally:
            finished.set()

    with Progress(*columns, console=Console(stderr=True), transient=False,
                  disable=quiet) as progress:
        runner.bus.subscribe(_ProgressView(progress))
        handled = 0
        worker = threading.Thread(target=work, name="gonio-runner", daemon=True)
        worker.start()
        while not finished.is_set():
            try:
                finished.wait(0.1)
            except KeyboardInterrupt:  # not on the main thread: no handler of ours
                interrupts.append(1)
            while handled < len(interrupts):
                handled += 1
                if handled == 1:
                    progress.console.print("[yellow]pausing after the current step[/] "
                                           "(Ctrl-C again to stop motion now)")
                    runner.request_pause()
                elif handled == 2:
                    progress.console.print("[yellow]stopping now[/]; the interrupted step will "
                                           "be re-done")
                    runner.request_pause(now=True)
        worker.join()
    if "error" in outcome:
        exc = outcome["error"]
        if isinstance(exc, (RunnerError, StoreError)):
            raise fail(str(exc))
        raise fail(f"unexpected error (session paused): {exc!r}")
    state = outcome["state"]
    if state == "done":
        typer.secho(f"session {runner.name} done", fg=typer.colors.GREEN)
    elif state == "paused":
        typer.secho(f"session {runner.name} paused; continue with:\n  gonio capture resume "
                    f"{runner.name} --rig {shlex.quote(rig_spec)} --store {shlex.quote(store_path)}",
                    fg=typer.colors.YELLOW)
    else:
        typer.secho(f"session {runner.name} aborted", fg=typer.colors.RED)
    raise typer.Exit(EXIT[state])


@_command
def run(plan_file: Path = typer.Argument(..., help="Plan TOML file."),
        rig: str = typer.Option(..., "--rig", help=RIG_HELP),
        store: str = STORE_OPTION,
        session: Optional[str] = typer.Option(None, "--session", help="Session name: ASCII letters, digits, "
                                              "'_', '.', '-' (default: <plan name>-<date>-<time>)."),
        operator: Optional[str] = typer.Option(None, help="Operator (overrides the plan's)."),
        fast: bool = typer.Option(True, help="Simulated devices move instantly."),
        sim_camera: Optional[str] = typer.Option(None, "--sim-camera", help=SIM_CAMERA_HELP),
        home: bool = typer.Option(True, help="Home axes that report not homed before starting."),
        yes: bool = typer.Option(False, "--yes", "-y", help="Do not prompt for target changes."),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar.")) -> None:
    """Record a new session from PLAN_FILE on the rig, into the store.

    The plan is checked against the rig's limits and the disk's free space against its
    estimate; then the session (plan, steps) is recorded and run step by step with a progress
    bar (steps, frames, ETA). Frames go to STORE/objects/ as the camera's own DNG files named by
    SHA-256, each listed in STORE/gonio.sqlite with the read-back positions and the settings the
    camera reported.

    Ctrl-C pauses after the current step; a second Ctrl-C stops motion at once (that step is
    re-done on resume). To continue a paused or crashed session: gonio capture resume NAME
    --rig ... --store STORE.

    Exit status: 0 done, 3 paused, 4 aborted, 2 error (nothing captured).
    """
    if session is not None:
        try:  # before the store or the rig is touched
            check_session_name(session, "--session")
        except StoreError as exc:
            raise fail(str(exc)) from None
    p = _load_plan(plan_file)
    check_store_option(store, readonly=False)   # an archive or "": refused before the rig opens
    created: list[str] = []   # the session's name once recorded (for the resume hint)
    with interruptible(lambda: _resume_hint(store, created[0] if created else None, rig)):
        from ..runner import Runner, RunnerError, create_session   # the metering's calibration and scipy load here
        opened = _open_rig(rig, fast, sim_camera)
        with counted() as interrupts, opened:
            try:  # before the store is created: a plan the rig cannot run leaves no empty store
                p.check_rig(opened.rig)
            except PlanError as exc:
                raise fail(f"{plan_file}: {exc}") from None
            with open_store(store, create=True) as st:
                try:
                    info = create_session(st, p, opened.rig, name=session, operator=operator,
                                          plan_path=str(plan_file.resolve()))
                except PlanError as exc:
                    raise fail(f"{plan_file}: {exc}") from None
                except (RunnerError, StoreError) as exc:
                    raise fail(str(exc)) from None
                created.append(info.name)
                todo = [s.step for s in st.steps(info.id)]
                est = MotionModel.from_rig(opened.rig).estimate(todo)
                typer.echo(f"session {info.name}: {est.steps} steps, {est.frames} frames, about "
                           f"{human_bytes(est.bytes)} and {human_time(est.seconds)} -> store {store}")
                typer.echo(_frame_size_text(est, True, running=True))
                runner = Runner(opened.rig, st, info, home=home,
                                prepare_target=_target_handler(opened, yes))
                _execute(runner, store, quiet, interrupts, rig)


def _resume_hint(store: str, name: str | None, rig: str) -> str:
    """What an interrupted ``capture run|resume`` leaves: nothing, a finished session, or the
    command that continues it."""
    if name is None:
        return "nothing was captured"
    with contextlib.suppress(StoreError), Store(store, create=False, readonly=True) as st:
        if st.session(name).state == "done":
            return f"session {name} is done"
    return f"every frame stored is kept; resume with: {command_line('gonio', 'capture', 'resume', name, rig=rig, store=store)}"


@_command
@interruptible_command(lambda name, rig, store, **_: _resume_hint(store, name, rig))
def resume(name: str = typer.Argument(..., help="Session name."),
           rig: str = typer.Option(..., "--rig", help=RIG_HELP),
           store: str = STORE_OPTION,
           plan_file: Optional[Path] = typer.Option(None, "--plan", help="Plan file to compare "
                                                    "against (default: the one the session was planned from)."),
           fast: bool = typer.Option(True, help="Simulated devices move instantly."),
           sim_camera: Optional[str] = typer.Option(None, "--sim-camera", help=SIM_CAMERA_HELP + " Default: "
                                                    "the one the session was recorded with."),
           home: bool = typer.Option(True, help="Home axes that report not homed before resuming."),
           yes: bool = typer.Option(False, "--yes", "-y", help="Do not prompt for target changes."),
           quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar.")) -> None:
    """Continue a paused or interrupted session from its first step not done.

    Steps already done are kept; a step that was cut short is captured again and its frames
    replaced (never duplicated). Devices whose link dropped are reconnected and axes that lost
    their reference are homed. The plan file the session was planned from (or --plan) must be
    unchanged: if it differs, resume refuses and lists the changed fields. Find NAME with
    'gonio session list --store STORE'.

    Exit status: 0 done (or already done), 3 paused again, 4 aborted, 2 error.
    """
    from ..runner import Runner, RunnerError, check_plan_unchanged, estimate_remaining
    st = open_store(store)
    with st:
        try:
            info = st.session(name)
        except StoreError as exc:
            raise fail(str(exc)) from None
        if info.state == "done":
            typer.echo(f"session {name} is already done")
            return
        path = plan_file or (Path(info.plan_path) if info.plan_path else None)
        if path is not None and path.is_file():
            try:
                check_plan_unchanged(info, _load_plan(path), f"the plan {path}")
            except RunnerError as exc:
                raise fail(str(exc)) from None
        elif path is not None:
            typer.secho(f"note: plan file {path} is gone; resuming from the plan stored with "
                        "the session", fg=typer.colors.YELLOW)
        if rig == "sim" and sim_camera is None:  # the camera the session's frames were taken with
            recorded = [s["config"].get("rig", {}).get("camera_resolution") for s in st.rig_snapshots(info.id)]
            sim_camera = next(("{}x{}".format(*r) for r in reversed(recorded) if r), None)
        opened = _open_rig(rig, fast, sim_camera)
        with counted() as interrupts, opened:
            try:
                Plan.from_dict(info.plan).check_rig(opened.rig)
            except PlanError as exc:
                raise fail(f"the session's plan does not fit this rig: {exc}") from None
            est, p = estimate_remaining(st, info, opened.rig), st.progress(info.id)
            typer.echo(f"session {name} ({display_state(st, info)}): {p.steps_done} of "
                       f"{p.steps_total} steps done; {est.steps} steps, {est.frames} frames left, about "
                       f"{human_bytes(est.bytes)} and {human_time(est.seconds)}")
            runner = Runner(opened.rig, st, info, home=home,
                            prepare_target=_target_handler(opened, yes))
            _execute(runner, store, quiet, interrupts, rig)

