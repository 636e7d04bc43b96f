"""The console's only contact with the capture layer: the same rig opener, store, plans and
runner the CLI uses. Every function here blocks (I/O); the app calls them from thread workers."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from rig.rig import Rig

from ..lab_resolver import resolve_lab
from ..pipeline.progress import Progress as ProgressEvent
from ..pipeline.run import process_session
from ..plan import MotionModel, Plan, Step
from ..rigs import OpenedRig, home_all
from ..rigs import open_rig as _open_rig
from ..runner import Runner, create_session
from ..store import Store, StoredStep
from .session import RESUMABLE, fmt_bytes, fmt_duration


def open_rig(spec: str, *, fast: bool = False,
             sim_options: dict[str, dict[str, Any]] | None = None) -> OpenedRig:
    """Open and connect the rig named by ``spec`` (``"sim"`` or a rig TOML file); ``.lab`` is
    the SimLab behind simulated devices (None for real hardware). ``sim_options`` are per-role
    simulator settings (``{"turntable": {"speed_deg_s": 30}}``)."""
    return _open_rig(spec, fast=fast, **({"options": sim_options} if sim_options else {}))


def home_every_axis(rig: Rig) -> str:
    """Home all axes and the positioner at once (blocking); returns a line for the log."""
    done = home_all(rig)
    return f"homed {', '.join(done)}"


def target_handler(opened: OpenedRig, ask: Callable[[str, Step], None], *,
                   prompt: bool | None = None) -> Callable[[str, Step], None] | None:
    """Who sets up the scene a step needs (``object``, ``dark``, ``checkerboard`` ...), as
    in ``gonio capture run``: the opened rig's ``prepare_target`` where it has one (a simulated
    camera), else the operator is asked (``ask``). ``prompt`` True / False forces asking / not asking."""
    if prompt is None:
        prompt = opened.prepare_target is None
    return ask if prompt else opened.prepare_target


def open_store(root: str | Path) -> Store:
    return Store(root)


def load_plan(path: str | Path) -> Plan:
    """Read and validate a plan file (``PlanError``, a ValueError, names the bad field)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"plan file {path} does not exist")
    return Plan.from_toml(path)


def plan_steps(plan: Plan, rig: Rig | None = None) -> list[StoredStep]:
    """The plan's steps as the store would hold them, none done."""
    return [StoredStep(s.index, s.to_dict(), False) for s in plan.steps(rig)]


def plan_summary(plan: Plan, rig: Rig | None = None) -> str:
    """``"24 steps · 72 frames · ~3m20s · ~1.8 GB"`` from the plan's own motion model."""
    return _summary(plan.estimate(rig), plan.name or "plan")


def _summary(est: Any, name: str) -> str:
    return (f"{name}: {est.steps} steps · {est.frames} frames · ~{fmt_duration(est.seconds)} "
            f"(motion {fmt_duration(est.motion_s)}) · ~{fmt_bytes(est.bytes)}")


def session_rows(store: Store) -> list[tuple[str, str, str]]:
    """``(name, state, "done/total steps")`` per stored session, newest first; a session
    marked running that no process is writing shows as ``interrupted``."""
    rows = []
    for info in sorted(store.sessions(), key=lambda s: s.updated, reverse=True):
        p = store.progress(info.id)
        state = info.state
        if state == "running" and not store.session_active(info.name):
            state = "interrupted"
        rows.append((info.name, state, f"{p.steps_done}/{p.steps_total}"))
    return rows


def interrupted(store: Store) -> list[str]:
    """Sessions that can be resumed (paused, or left ``running`` by a crash), newest first."""
    return [i.name for i in sorted(store.sessions(), key=lambda s: s.updated, reverse=True)
            if i.state in RESUMABLE]


def make_runner(rig: Rig, store: Store, *, plan: Plan | None = None, plan_path: str | None = None,
                resume: str | None = None, **runner_options: Any
                ) -> tuple[Runner, list[tuple[int, dict, bool]], str]:
    """A runner for a new session from ``plan`` (``resume`` None), or for resuming the stored
    session ``resume`` (``""``: the most recently updated interrupted one).

    Returns the runner (not started), the session's steps as ``(index, dict, done)`` and a
    summary of the work left (steps, frames, estimated time and bytes).

    Raises
    ------
    PlanError, RunnerError
        The plan does not fit the rig or the disk (from :func:`capture.runner.create_session`).
    ValueError
        Nothing to resume, or the named session cannot be resumed.
    """
    if resume is None:
        if plan is None:
            raise ValueError("no plan is open: open a plan file first")
        info = create_session(store, plan, rig, plan_path=plan_path)
    else:
        candidates = interrupted(store)
        name = resume or (candidates[0] if candidates else None)
        if name is None:
            raise ValueError(f"no interrupted session in the store {store.root}")
        info = store.session(name)
        if info.state not in RESUMABLE:
            raise ValueError(f"session {name!r} is {info.state}; only paused or interrupted "
                             "sessions can be resumed")
    steps = store.steps(info.id)
    todo = [s.step for s in steps if not s.done]
    summary = _summary(MotionModel.from_rig(rig).estimate(todo), f"{info.name} (to do)")
    return Runner(rig, store, info, **runner_options), steps, summary


def process(store: Store, session: str, *, progress: Callable[[ProgressEvent], None] | None = None,
            mesh: Any = None, **options: Any) -> Any:
    """``gonio process`` on ``session``: ``mesh`` the object's (trimesh; a session recorded in the
    built-in simulated lab brings its own, with targets and truth); ``options`` go to
    :func:`capture.pipeline.run.process_session` (``methods`` ...). Returns its ``ProcessReport``."""
    lab = resolve_lab(store, session, mesh=mesh)
    if lab.mesh is None:
        raise ValueError("processing needs the object's mesh: start the console with --mesh FILE "
                         "(sessions recorded on --rig sim bring their own)")
    return process_session(store, session, progress=progress, lab=lab, **options)


def headline(report: Any) -> list[tuple[str, str, str]]:
    """Per method ``(name, status, figure)``: the held-out relative RMS (and against the truth
    where known), or why it was skipped."""
    rows = []
    for m in report.methods:
        f = m.figures
        if "held_out_rel_rms" in f:
            figure = f"held-out rel. RMS {f['held_out_rel_rms']:.3f}"
            if "truth_rel_rms" in f:
                figure += f", vs truth {f['truth_rel_rms']:.3f}"
        else:
            figure = m.reason
        rows.append((m.method, m.status, figure))
    return rows
