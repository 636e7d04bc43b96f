"""Intrinsics end to end on the simulated lab: how many hand-held board views reach the
calibration targets (focal length within 0.2 %, principal point ~1 px at 320 x 240).

Captures a calibration-only session (dark frames, ``views`` hand-held board views, the quick
demo's turntable sweep) through the simulated rig's real drivers into DNG files, runs the
session pipeline's dark / HDR / intrinsics stages, and prints the errors against the truth::

    python benchmarks/handheld_intrinsics.py --size 320x240 --views 0 8 16 24 --seeds 0 1

``--views 0`` is the turntable sweep alone (what the demo had before the hand-held views).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repo's capture, not ./capture.py

from capture.pipeline.calibrate import calibrate_session  # noqa: E402
from capture.pipeline.demo_lab import DemoLab  # noqa: E402
from capture.plan import Plan  # noqa: E402
from capture.rigs import open_rig  # noqa: E402
from capture.runner import Runner, create_session  # noqa: E402
from capture.store import Store  # noqa: E402

SWEEP_DEG = [300, 310, 320, 330, 340, 350, 0, 10, 20, 30, 40, 50, 60]   # examples/demo-quick.toml


def board_plan(views: int) -> Plan:
    """Dark frames, ``views`` hand-held views (0: none) and the quick demo's turntable sweep."""
    cal = [{"kind": "dark", "frames": 2, "exposure_s": 0.02},
           {"kind": "checkerboard", "exposure_s": 0.02, "turntable_angles_deg": SWEEP_DEG}]
    if views:
        cal.insert(1, {"kind": "handheld_board", "views": views, "exposure_s": 0.15})
        cal.insert(1, {"kind": "dark", "frames": 2, "exposure_s": 0.15})
    return Plan.from_dict({"name": "board", "calibration": cal})


def capture(root: Path, plan: Plan, lab: DemoLab) -> tuple[Store, str]:
    """Run ``plan`` on the simulated rig with ``lab`` as the camera's scene; the store and session."""
    store = Store(root, durable=False)
    with open_rig("sim", fast=True, home=True, frame_source=lab) as opened:
        name = create_session(store, plan, opened.rig, name=plan.name, reserve_bytes=0).name
        state = Runner(opened.rig, store, name, reserve_bytes=0, prepare_target=lab.prepare_target).run()
    if state != "done":
        raise RuntimeError(f"capture ended {state}")
    return store, name


def intrinsics_errors(store: Store, name: str, lab: DemoLab) -> dict:
    """``gonio calibrate``'s dark / HDR / intrinsics stages on the session, against the lab's
    true camera: focal errors (fx, fy) %, principal point errors (x, y) px and their 1-sigma."""
    rep = calibrate_session(store, name, targets=lab.targets(), stages=("dark", "hdr", "intrinsics"))
    stage = rep.stage("intrinsics")
    if stage.status != "ok":
        raise RuntimeError(f"intrinsics {stage.status}: {stage.reason}")
    f, true = stage.figures, lab.truth().camera.K
    stored = [r for r in store.results(store.session(name).id, "calibration") if r.kind == "intrinsics"][-1]
    return {"f_err_pct": 100 * (np.array([f["fx_px"], f["fy_px"]]) / true[0, 0] - 1),
            "pp_err_px": np.array([f["cx_px"], f["cy_px"]]) - true[:2, 2],
            "pp_std_px": np.asarray(stored.result["K_std"], float)[2:4], "figures": f}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default=["320x240"], nargs="+", help="camera resolutions WxH")
    ap.add_argument("--views", type=int, nargs="+", default=[0, 16], help="hand-held view counts")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="sensor-noise seeds")
    args = ap.parse_args()
    for size in args.size:
        w, h = map(int, size.split("x"))
        for views in args.views:
            for seed in args.seeds:
                lab = DemoLab(w, h, seed=seed)
                with tempfile.TemporaryDirectory() as tmp:
                    t0 = time.perf_counter()
                    store, name = capture(Path(tmp) / "store", board_plan(views), lab)
                    t1 = time.perf_counter()
                    e = intrinsics_errors(store, name, lab)
                    store.close()
                f = e["figures"]
                print(f"{w}x{h} views={views:3d} seed={seed}: focal {e['f_err_pct'][0]:+.3f} / "
                      f"{e['f_err_pct'][1]:+.3f} %  principal point {e['pp_err_px'][0]:+.2f} / "
                      f"{e['pp_err_px'][1]:+.2f} px (1-sigma {e['pp_std_px'][0]:.2f} / {e['pp_std_px'][1]:.2f})  "
                      f"rms {f['rms_px']:.3f} px  coverage {f['coverage_pct']} %  views used "
                      f"{f.get('views_handheld_board', 0)} + {f.get('views_checkerboard', 0)}  "
                      f"capture {t1 - t0:.1f} s, calibrate {time.perf_counter() - t1:.1f} s", flush=True)


if __name__ == "__main__":
    main()
