"""The demo end to end against its targets: ``python benchmarks/demo.py [--quick] [--out DIR]``.

Runs :func:`capture.pipeline.demo.run_demo` (capture on the simulated rig, calibration,
every method, the report) and prints the calibration's errors against the simulation's truth
beside the calibration targets (focal length 0.2 %, light position 0.5 % of its distance, light
direction 0.25 deg), each method's held-out and truth errors beside the matte reference's, and
the wall time per stage. The full demo (640 x 480) takes ~6 min on two idle cores, too long for
the test suite, which runs the quick one (tests/capture/test_demo.py).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the package, not benchmarks/capture.py

from capture.pipeline.demo import run_demo  # noqa: E402

TARGETS = {"focal length, worst axis (%)": 0.2, "light position, worst (% of distance)": 0.5,
           "light direction, worst (deg)": 0.25}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the 320 x 240 quick demo")
    parser.add_argument("--out", help="folder for the store and report (default: a temporary one)")
    args = parser.parse_args()
    out = args.out or tempfile.mkdtemp(prefix="gonio-demo-bench-")
    started = time.perf_counter()
    rep = run_demo(out, quick=args.quick)
    wall = time.perf_counter() - started
    t = rep.calibration_truth
    measured = {"focal length, worst axis (%)": max(abs(v) for v in t["focal_error_pct"]),
                "light position, worst (% of distance)": t["max_light_error_pct_of_distance"],
                "light direction, worst (deg)": t["max_light_direction_error_deg"]}
    print(f"gonio demo{' --quick' if args.quick else ''}: {wall:.0f} s wall; report {rep.report_path}")
    print(f"{'calibration against the truth':<40} {'measured':>9} {'target':>7}")
    for name, value in measured.items():
        print(f"{name:<40} {value:9.3f} {TARGETS[name]:7.2f}  {'met' if value <= TARGETS[name] else 'NOT met'}")
    print(f"{'principal point error (px)':<40} {max(abs(v) for v in t['principal_point_error_px']):9.3f}")
    print(f"{'lamp intensity, worst channel (%)':<40} {max(abs(v) for v in t['intensity_error_pct']):9.3f}")
    print(f"floor (the true model on the held-out captures): {rep.floor.held_out_rel_rms:.3f}, "
          f"trimmed {rep.floor.held_out_rel_rms_trimmed:.3f}")
    print(f"{'method':<12} {'held out':>9} {'trimmed':>8} {'x floor':>8} {'vs truth':>9} {'s':>6}")
    for m in rep.methods:
        f = m.figures
        print(f"{m.method:<12} {f.get('held_out_rel_rms', float('nan')):9.3f} "
              f"{f.get('held_out_rel_rms_trimmed', float('nan')):8.3f} "
              f"{m.floor_ratio if m.floor_ratio is not None else float('nan'):8.2f} "
              f"{f.get('truth_rel_rms', float('nan')):9.3f} {m.seconds:6.1f}")
    print("stages (s): " + ", ".join(f"{k} {v:.1f}" for k, v in rep.timings.items()))


if __name__ == "__main__":
    main()
