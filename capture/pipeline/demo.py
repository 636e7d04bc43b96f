"""``gonio demo``: the whole job on the simulated lab, start to finish, in a fresh folder.

:func:`run_demo` does what ``gonio capture run PLAN --rig sim --sim-camera WxH`` and then ``gonio
process`` do: it starts the simulated rig (all four devices on their real protocols, the camera
rendering :class:`capture.pipeline.demo_lab.DemoLab`), creates a store, captures the demo plan
(``examples/demo-quick.toml`` or ``examples/demo.toml``: dark frames, board views at many
turntable angles, mirror balls at every light, gray card, mirror probe, the object over
turntable angles x lights x polarizer states x exposures, the passive capture and a held-out
light), then runs :func:`capture.pipeline.run.process_session` with the lab
:func:`capture.lab_resolver.resolve_lab` finds from the session's rig snapshots (mesh, targets,
ground truth), and writes ``report.html``. The same
plan captured by ``gonio capture run`` gives the same frames, byte for byte.
"""
from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..lab_resolver import resolve_lab
from ..plan import Plan
from ..rigs import open_rig
from ..runner import Runner, create_session
from ..store import Store
from .demo_lab import FAST_RESOLUTION, FULL_RESOLUTION
from .progress import ProgressSink, counter
from .run import ProcessReport, process_session

__all__ = ["DEMO_PLANS", "DemoSettings", "run_demo", "demo_plan"]

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
#: the demo's two sizes: plan file and simulated camera resolution (the methods' options follow
#: the resolution: :meth:`capture.pipeline.demo_lab.DemoLab.method_options`)
DEMO_PLANS = {"quick": ("demo-quick.toml", FAST_RESOLUTION), "full": ("demo.toml", FULL_RESOLUTION)}


@dataclass(frozen=True)
class DemoSettings:
    """Which demo: ``plan`` file, camera ``resolution`` (width, height)."""

    plan: Path
    resolution: tuple[int, int]


def demo_plan(quick: bool) -> DemoSettings:
    """The demo's plan file and camera resolution (``--quick`` or the full demo)."""
    name, res = DEMO_PLANS["quick" if quick else "full"]
    return DemoSettings(EXAMPLES / name, res)


def run_demo(out_dir: str | Path | None = None, *, quick: bool = False,
             progress: ProgressSink | None = None,
             say: Callable[[str], None] = lambda text: None) -> ProcessReport:
    """Capture, calibrate, reconstruct and report on the simulated lab.

    Parameters
    ----------
    out_dir : path, optional
        A folder for the store and the report (created; default: a new temporary folder).
    quick : bool
        The small plan at 320 x 240 (under 3 minutes on 2 cores) instead of the full one.
    progress : callable(Progress), optional
        ``capture`` (frames stored of the plan's), then the stages of :func:`process_session`.
    say : callable(str), optional
        Receives one-line news for the console (folders, what is happening).

    Returns
    -------
    ProcessReport
        With ``report_path`` the written ``report.html``.
    """
    out = (Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="gonio-demo-"))).resolve()
    out.mkdir(parents=True, exist_ok=True)
    settings = demo_plan(quick)
    plan = Plan.from_toml(settings.plan)
    store = Store(out / "store", durable=False)
    say(f"store: {store.root}")
    try:
        with open_rig("sim", fast=True, home=True, resolution=settings.resolution) as opened:
            name = create_session(store, plan, opened.rig, name=plan.name, reserve_bytes=0).name
            runner = Runner(opened.rig, store, name, reserve_bytes=0, prepare_target=opened.prepare_target)
            runner.on_frame_stored(counter(progress, "capture"))
            say(f"capturing {settings.plan.name} on the simulated lab ({settings.resolution[0]} x "
                f"{settings.resolution[1]} camera)")
            state = runner.run()
            if state != "done":
                raise RuntimeError(f"the demo capture ended {state}; see `gonio session show {name} "
                                   f"--store {store.root}`")
        say("processing: calibration, reconstruction inputs, methods, report")
        return process_session(store, name, progress=progress, report_path=out / "report.html",
                               lab=resolve_lab(store, name))
    finally:
        store.close()
