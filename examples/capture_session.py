"""Record a capture session from Python on the simulated lab, then inspect and export it.

    python examples/capture_session.py [STORE_DIR]

The same steps as ``gonio capture run examples/plan.toml --rig sim --store STORE_DIR``, with a
smaller plan built in Python, an event subscriber, a simulated cable pull that pauses the session,
and a resume that completes it.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from capture.events import EventKind
from capture.plan import Calibration, Exposure, LightGrid, Plan
from capture.rigs import open_rig
from capture.runner import Runner, create_session
from capture.store import Store


def main(store_dir: Path) -> None:
    plan = Plan(name="example", object="simulated sphere",
                turntable_deg=(0, 45, 90, 135),
                light=LightGrid(azimuth_deg=(0.0, 90.0), elevation_deg=(30.0, 60.0)),
                polarizer_deg=(0, 90),
                exposure=Exposure(base_s=0.01, stops=(-1.0, 1.0)),
                calibration=(Calibration(kind="dark", frames=2),))
    with open_rig("sim", fast=True, home=True) as opened, Store(store_dir) as store:
        plan.check_rig(opened.rig)  # limits from the devices' describe()
        est = plan.estimate(opened.rig)
        print(f"{est.steps} steps, {est.frames} frames, ~{est.seconds / 60:.1f} min on a real rig")
        info = create_session(store, plan, opened.rig)
        runner = Runner(opened.rig, store, info)

        def show(event):
            if event.kind in (EventKind.FAULT, EventKind.PAUSED, EventKind.RESUMED, EventKind.DONE,
                              EventKind.TARGET, EventKind.NOTE):
                print(f"  {event}")
            if event.kind == EventKind.FRAME_STORED and event.data["frames_done"] == 20:
                opened.lab.sims["positioner"].disconnect()  # somebody trips over the cable
        runner.bus.subscribe(show)

        print("run:", runner.run())                # paused, with the fault recorded
        opened.lab.sims["positioner"].reconnect()  # plugged back in
        print("resume:", runner.run())             # reconnects, re-homes, finishes

        p = store.progress(info.id)
        print(f"{info.name}: {p.steps_done}/{p.steps_total} steps, {p.frames_stored} frames, "
              f"{p.bytes_stored / 1e6:.1f} MB; verify ok: {store.verify(info.name).ok}")
        first = store.frames(info.id)[0]
        print(f"first frame: step {first.step}, {first.filename}, {first.exposure_s:g} s, "
              f"read-backs {first.positions}")
        out = store.export(info.name, store_dir.parent / f"{info.name}.tar")
        print(f"exported to {out}; open it with: gonio session show {info.name} --store {out}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="gonio-example-")) / "store")
