"""The simulated lab's capture of a demo plan: wall and CPU time, and every stored frame's
SHA-256, so a faster renderer can be shown to give the same bytes.

    python benchmarks/sim_capture.py [--full] [--store DIR] [--hashes FILE] [--compare FILE]

Captures ``examples/demo-quick.toml`` (``--full``: ``examples/demo.toml``) on the simulated lab
exactly as ``gonio demo`` does (no processing), prints wall time, process CPU time (all threads;
on a shared machine the CPU time is the figure to compare) and the load average, and writes the
sorted object names of the store (content-addressed: SHA-256 of each frame's bytes) to
``--hashes``. ``--compare FILE`` checks them against an earlier run's list.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.pipeline.demo import demo_plan  # noqa: E402
from capture.plan import Plan  # noqa: E402
from capture.rigs import open_rig  # noqa: E402
from capture.runner import Runner, create_session  # noqa: E402
from capture.store import Store  # noqa: E402
from sims.world import SimWorld  # noqa: E402


def timed_frames() -> dict[str, list[float]]:
    """Patch :meth:`SimWorld.frame_source` to add up each scene's frames: label -> [frames,
    process CPU s (all threads: the render's pool, and the little the simulators use meanwhile)]. The label names what stands in front of the camera and the supersampling."""
    per_scene: dict[str, list[float]] = {}
    original = SimWorld.frame_source

    def frame_source(world, state=None):
        t0 = time.process_time()
        try:
            return original(world, state)
        finally:
            what = "dark" if world.dark else "flat" if world.flat_radiance is not None else "+".join(
                [type(world.object).__name__ if world.object is not None else ""]
                + [t.name for t in world.targets]).strip("+")
            label = f"{what} s={world.supersample}{' env' if world.environment is not None else ''}"
            entry = per_scene.setdefault(label, [0, 0.0])
            entry[0] += 1
            entry[1] += time.process_time() - t0

    SimWorld.frame_source = frame_source
    SimWorld.__call__ = frame_source
    return per_scene


def capture(root: Path, quick: bool) -> tuple[float, float, list[str]]:
    """Capture the demo plan into a new store under ``root``: (wall s, CPU s, object names)."""
    settings = demo_plan(quick)
    plan = Plan.from_toml(settings.plan)
    store = Store(root / "store", durable=False)
    try:
        wall0, cpu0 = time.perf_counter(), time.process_time()
        with open_rig("sim", fast=True, home=True, resolution=settings.resolution) as opened:
            name = create_session(store, plan, opened.rig, name=plan.name, reserve_bytes=0).name
            state = Runner(opened.rig, store, name, reserve_bytes=0,
                           prepare_target=opened.prepare_target).run()
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        if state != "done":
            raise SystemExit(f"capture ended {state}")
    finally:
        store.close()
    names = sorted(p.parent.name + p.name for p in (root / "store" / "objects").glob("*/*")
                   if not p.name.startswith(".tmp-"))
    return wall, cpu, names


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="examples/demo.toml instead of demo-quick")
    ap.add_argument("--store", type=Path, help="folder for the store (default: a temporary one)")
    ap.add_argument("--hashes", type=Path, help="write the sorted object names here")
    ap.add_argument("--compare", type=Path, help="an earlier --hashes file to compare with")
    args = ap.parse_args()
    root = args.store or Path(tempfile.mkdtemp(prefix="gonio-simcap-"))
    root.mkdir(parents=True, exist_ok=True)
    print(f"load average before: {os.getloadavg()}")
    per_scene = timed_frames()
    wall, cpu, names = capture(root, quick=not args.full)
    for label, (frames, seconds) in sorted(per_scene.items(), key=lambda kv: -kv[1][1]):
        print(f"  {label}: {frames} frames, {seconds:.1f} s CPU")
    print(f"load average after: {os.getloadavg()}")
    print(f"capture: {len(names)} objects, wall {wall:.1f} s, CPU {cpu:.1f} s (all threads)")
    if args.hashes:
        args.hashes.write_text("\n".join(names) + "\n")
    if args.compare:
        before = set(args.compare.read_text().split())
        same = before == set(names)
        print(f"object names equal to {args.compare}: {same} "
              f"({len(before - set(names))} only before, {len(set(names) - before)} only now)")
        if not same:
            raise SystemExit(1)


if __name__ == "__main__":
    main()
