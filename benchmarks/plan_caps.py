"""What the plan caps cost and save: refusing a 10^9-step plan, and expanding one at the cap.

Run: ``python benchmarks/plan_caps.py``. Prints the wall time to refuse a plan of 10^9 steps
(three ranges of 1000 values each, every range under the per-range cap), and the wall time and
peak Python memory (tracemalloc) of validating and expanding the largest plan the caps allow
(200,000 steps) -- the most a plan can now cost before its session starts.
"""
from __future__ import annotations

import sys
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/capture.py shadows the package
from capture.plan import MAX_STEPS, Plan, PlanError  # noqa: E402

HUGE = {"turntable": {"angles_deg": {"start": 0, "stop": 359.64, "step": 0.36}},
        "light": {"azimuth_deg": {"start": -180, "stop": 179.64, "step": 0.36},
                  "elevation_deg": {"start": 0, "stop": 89.91, "step": 0.09}},
        "exposure": {"base_s": 0.01}}
AT_CAP = {"turntable": {"angles_deg": {"start": 0, "stop": 399, "step": 1}},
          "light": {"azimuth_deg": {"start": 0, "stop": 99, "step": 1}, "elevation_deg": [10, 20, 30, 40, 50]},
          "exposure": {"base_s": 0.01}}


def main() -> None:
    t0 = time.perf_counter()
    try:
        Plan.from_dict(HUGE)
    except PlanError as exc:
        print(f"10^9-step plan refused in {1e3 * (time.perf_counter() - t0):.2f} ms: {exc}")
    t0 = time.perf_counter()
    steps = Plan.from_dict(AT_CAP).steps()
    seconds = time.perf_counter() - t0
    assert len(steps) == MAX_STEPS
    del steps
    tracemalloc.start()  # a second pass for memory: tracing slows Python several-fold
    steps = Plan.from_dict(AT_CAP).steps()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    print(f"plan at the cap ({len(steps):,} steps): validated and expanded in {seconds:.2f} s, "
          f"peak {peak / 1e6:.0f} MB of Python memory")


if __name__ == "__main__":
    main()
