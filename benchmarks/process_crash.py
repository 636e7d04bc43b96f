"""Crash run of ``gonio process``: SIGKILL at every stage boundary and at random hook points, each
followed by a plain re-run that must complete with the same figures.

A small session is captured on the simulated lab and calibrated once (the reference, with the
``lambertian`` figures of an uninterrupted run). Then, for every kill point, a copy of that store
is processed with ``force`` (calibration and method run again) in a forked child armed with
``GONIO_CRASH_AFTER=N`` (the N-th hook: calibration and process stage boundaries, object writes,
row commits), and a plain ``process_session`` re-run on the killed copy must: finish, say why a
cut-short calibration is run again, store one complete calibration, give the reference
held-out figure to 1e-9, and leave every stored file hashing to its name.

Usage: ``python benchmarks/process_crash.py [--store DIR] [--random N] [--seed S]`` (DIR: a
store holding the calibrated session ``proc``, made there when absent). Prints one line per kill.
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import random
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests" / "capture")]

from capture.store import crash  # noqa: E402
from capture.pipeline.calibration_record import stored_calibration  # noqa: E402
from capture.pipeline.run import process_session  # noqa: E402
from capture.store import Store  # noqa: E402

METHODS = ["lambertian"]
FORK = multiprocessing.get_context("fork")


def make_store(root: Path) -> None:
    from capture.pipeline.calibrate import calibrate_session
    from capture.plan import Plan
    from capture.rigs import open_rig
    from capture.runner import Runner, create_session
    from test_process import PLAN
    with Store(root, durable=False) as st, open_rig("sim", fast=True, home=True) as opened:
        create_session(st, Plan.from_dict(PLAN), opened.rig, name="proc", reserve_bytes=0)
        assert Runner(opened.rig, st, "proc", reserve_bytes=0, prepare_target=opened.prepare_target).run() == "done"
        calibrate_session(st, "proc", measurement_hdr=False)


def hook_names(store_dir: Path, tmp: Path) -> list[str]:
    """Every hook a forced run passes, in order (:func:`capture.store.crash.point` recorded)."""
    names: list[str] = []
    real = crash.point

    def record(name: str) -> None:
        names.append(name)
        real(name)
    copy = tmp / "count"
    shutil.copytree(store_dir, copy)
    crash.point = record
    try:
        with Store(copy, durable=False) as st:
            process_session(st, "proc", methods=METHODS, force=True, report_path=tmp / "count.html")
    finally:
        crash.point = real
    return names


def _killed_child(store_dir: Path, after: int, report: Path) -> None:
    os.environ["GONIO_CRASH_AFTER"] = str(after)
    crash.count = 0
    os.dup2(os.open(os.devnull, os.O_WRONLY), 2)
    with Store(store_dir, durable=False) as st:
        process_session(st, "proc", methods=METHODS, force=True, report_path=report)
    os._exit(0)


def kill_and_rerun(store_dir: Path, tmp: Path, after: int, reference: float) -> dict:
    copy = tmp / f"kill{after}"
    shutil.copytree(store_dir, copy)
    child = FORK.Process(target=_killed_child, args=(copy, after, tmp / f"kill{after}.html"))
    child.start()
    child.join()
    t0 = time.perf_counter()
    with Store(copy, durable=False) as st:
        rep = process_session(st, "proc", methods=METHODS, report_path=tmp / f"rerun{after}.html")
        sid = st.session("proc").id
        complete = stored_calibration(st, sid).complete
        bad = st.verify("proc")
    lam = rep.method("lambertian")
    figure = lam.figures["held_out_rel_rms"]
    shutil.rmtree(copy)
    return {"exit": child.exitcode, "redone": any(c["status"] == "redone" for c in rep.calibration),
            "status": lam.status, "figure": figure, "same": abs(figure - reference) <= 1e-9 * reference,
            "complete": complete, "damaged": len(bad.missing) + len(bad.corrupt), "rerun_s": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", type=Path, default=None)
    ap.add_argument("--random", type=int, default=4, help="random hook points besides the stage boundaries")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    os.environ.pop("GONIO_CRASH_AFTER", None)
    tmp = Path(tempfile.mkdtemp(prefix="gonio-process-crash-"))
    store_dir = args.store or tmp / "reference"
    if not (store_dir / "gonio.sqlite").is_file():
        t0 = time.perf_counter()
        make_store(store_dir)
        print(f"captured and calibrated the session in {time.perf_counter() - t0:.0f} s")
    with Store(store_dir, durable=False) as st:
        ref = process_session(st, "proc", methods=METHODS, report_path=tmp / "reference.html")
    reference = ref.method("lambertian").figures["held_out_rel_rms"]
    names = hook_names(store_dir, tmp)
    boundaries = [i + 1 for i, n in enumerate(names) if n.startswith(("stage ", "calibration "))]
    rest = [i + 1 for i in range(len(names)) if i + 1 not in boundaries]
    picks = boundaries + sorted(random.Random(args.seed).sample(rest, min(args.random, len(rest))))
    print(f"reference held-out rel. RMS {reference:.6f}; {len(names)} hook points, {len(boundaries)} "
          f"stage boundaries; killing at {len(picks)}")
    failures = 0
    for n in picks:
        r = kill_and_rerun(store_dir, tmp, n, reference)
        ok = r["exit"] == -9 and r["same"] and r["complete"] and not r["damaged"]
        failures += not ok
        print(f"kill at hook {n:3d} ({names[n - 1]:<28}) exit {r['exit']}: re-run {r['status']}, "
              f"calibration {'redone' if r['redone'] else 'reused'}, figure {r['figure']:.6f} "
              f"{'same' if r['same'] else 'DIFFERENT'}, complete {r['complete']}, damaged files "
              f"{r['damaged']}, {r['rerun_s']:.1f} s  {'ok' if ok else 'FAILED'}")
    shutil.rmtree(tmp, ignore_errors=True)
    print(f"{len(picks) - failures} of {len(picks)} kills followed by a re-run with the same figures")
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
