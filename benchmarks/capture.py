"""Capture benchmarks: runner overhead per step, frame store throughput, 10,000-step sessions.

    python benchmarks/capture.py [--quick]

1. Runner overhead per step beyond device time, on the simulated lab in fast mode (real drivers,
   real wire protocols, placeholder DNG frames): wall time of ``Runner.run()`` minus the time
   spent in device calls (moves + waits, read-backs, set_exposure + capture), per step; with a
   durable store (fsync of file, directory and commit) and a scratch one (no fsync). Target: < 5 ms.
2. Frames stored per second for 48 MB frames (hash + write + fsync + rename + commit).
3. Store operations for a 10,000-step session: create, store one frame per step (completing the
   step), query pending steps / progress / frames, verify, export.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.plan import Plan  # noqa: E402
from capture.rigs import open_rig  # noqa: E402
from capture.runner import Runner, create_session  # noqa: E402
from capture.store import Store  # noqa: E402
from sims.ptp_sim import placeholder_frame  # noqa: E402


class TimedRunner(Runner):
    """A Runner that adds up the time spent in device calls and in the store's frame writes."""

    device_s = 0.0
    store_s = 0.0

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, **kw)
        add_frame = self.store.add_frame

        def timed_add_frame(*a, **k):
            t = time.perf_counter()
            try:
                return add_frame(*a, **k)
            finally:
                self.store_s += time.perf_counter() - t
        self.store.add_frame = timed_add_frame

    def _timed(self, fn, *args):
        t = time.perf_counter()
        try:
            return fn(*args)
        finally:
            self.device_s += time.perf_counter() - t

    def _move(self, step):
        return self._timed(super()._move, step)

    def _read_back(self):
        return self._timed(super()._read_back)

    def _capture(self, exposure_s):
        return self._timed(super()._capture, exposure_s)


def runner_overhead(n_angles: int, durable: bool, tmp: Path) -> dict[str, float]:
    plan = Plan.from_dict({"name": "bench", "turntable": {"angles_deg": list(range(0, 10 * n_angles, 10))},
                           "polarizer": {"angles_deg": [0, 90]},
                           "exposure": {"base_s": 0.001, "stops": [0]}})
    with open_rig("sim", fast=True, home=True, frame_source=placeholder_frame) as opened:
        with Store(tmp / f"overhead-{durable}", durable=durable) as st:
            info = create_session(st, plan, opened.rig, name="s", reserve_bytes=0)
            r = TimedRunner(opened.rig, st, info, reserve_bytes=0)
            t = time.perf_counter()
            assert r.run() == "done"
            wall = time.perf_counter() - t
            steps = st.progress(info.id).steps_total
    return {"steps": steps, "wall_ms_per_step": 1e3 * wall / steps,
            "device_ms_per_step": 1e3 * r.device_s / steps,
            "overhead_ms_per_step": 1e3 * (wall - r.device_s) / steps,
            "store_ms_per_step": 1e3 * r.store_s / steps,
            "runner_ms_per_step": 1e3 * (wall - r.device_s - r.store_s) / steps}


def fsync_ms(tmp: Path, n: int = 20) -> float:
    """Median time of one small write + fsync on the benchmark's disk, ms: the durable store
    pays three per frame (file, directory, WAL commit), which no runner code can avoid."""
    times = []
    with open(tmp / "fsync-probe", "wb") as f:
        for _ in range(n):
            f.write(b"x" * 4096)
            f.flush()
            t = time.perf_counter()
            os.fsync(f.fileno())
            times.append(time.perf_counter() - t)
    return 1e3 * sorted(times)[n // 2]


def store_throughput(n_frames: int, frame_mb: float, tmp: Path) -> dict[str, float]:
    rng_bytes = [os.urandom(int(frame_mb * 1e6)) for _ in range(2)]
    with Store(tmp / "throughput") as st:
        info = st.create_session("t", plan={}, plan_hash="0" * 64,
                                 steps=[{"frames": 1} for _ in range(n_frames)])
        t = time.perf_counter()
        for i in range(n_frames):
            # unique bytes per frame (no dedupe): vary the first 8 bytes of one of two buffers
            data = i.to_bytes(8, "little") + rng_bytes[i % 2][8:]
            st.add_frame(info.id, i, 0, 0, data=data, filename=f"IMG_{i}.DNG", format="dng",
                         exposure_requested_s=0.01, exposure_s=0.01, completes_step=True)
        dt = time.perf_counter() - t
    return {"frames": n_frames, "frames_per_s": n_frames / dt, "MB_per_s": n_frames * frame_mb / dt}


def ten_thousand_steps(n_steps: int, durable: bool, tmp: Path) -> dict[str, float]:
    out: dict[str, float] = {"steps": n_steps}
    plan = Plan.from_dict({"turntable": {"angles_deg": {"start": 0, "stop": 359.5, "step": 0.5}},
                           "polarizer": {"count": -(-n_steps // 720)}})
    steps = [s.to_dict() for s in plan.steps()][:n_steps]
    with Store(tmp / f"big-{durable}", durable=durable) as st:
        t = time.perf_counter()
        info = st.create_session("big", plan=plan.to_dict(), plan_hash=plan.hash, steps=steps)
        out["create_s"] = time.perf_counter() - t
        t = time.perf_counter()
        for i in range(n_steps):
            st.add_frame(info.id, i, 0, 0, data=i.to_bytes(8, "little") * 128, filename="f.dng",
                         format="dng", exposure_requested_s=0.01, exposure_s=0.01,
                         positions={"turntable_deg": steps[i]["turntable_deg"]}, completes_step=True)
        out["store_frame_ms"] = 1e3 * (time.perf_counter() - t) / n_steps
        for name, fn in (("pending_steps_ms", lambda: st.steps(info.id, pending_only=True)),
                         ("all_steps_ms", lambda: st.steps(info.id)),
                         ("progress_ms", lambda: st.progress(info.id)),
                         ("frames_ms", lambda: st.frames(info.id)),
                         ("list_sessions_ms", st.sessions)):
            t = time.perf_counter()
            fn()
            out[name] = 1e3 * (time.perf_counter() - t)
        t = time.perf_counter()
        assert st.verify("big").ok
        out["verify_s"] = time.perf_counter() - t
        t = time.perf_counter()
        st.export("big", tmp / f"big-{durable}.tar")
        out["export_s"] = time.perf_counter() - t
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes (smoke run)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="gonio-bench-"))
    try:
        print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        print(f"disk: one fsync {fsync_ms(tmp):.2f} ms (median); a durable frame costs three")
        n_angles = 10 if args.quick else 36
        for durable in (True, False):
            r = runner_overhead(n_angles, durable, tmp)
            print(f"runner ({'durable' if durable else 'scratch'} store, {r['steps']} steps, fast sims): "
                  f"{r['wall_ms_per_step']:.2f} ms/step wall, {r['device_ms_per_step']:.2f} ms in devices, "
                  f"overhead {r['overhead_ms_per_step']:.2f} ms/step (target < 5 ms) = frame store "
                  f"{r['store_ms_per_step']:.2f} + runner logic {r['runner_ms_per_step']:.2f}")
        r = store_throughput(4 if args.quick else 20, 48.0, tmp)
        print(f"store 48 MB frames (durable): {r['frames_per_s']:.2f} frames/s, {r['MB_per_s']:.0f} MB/s "
              f"({r['frames']} frames)")
        n = 1000 if args.quick else 10_000
        for durable in (True, False):
            r = ten_thousand_steps(n, durable, tmp)
            print(f"{n}-step session ({'durable' if durable else 'scratch'}): create {r['create_s']:.2f} s, "
                  f"store+complete {r['store_frame_ms']:.2f} ms/step, pending steps {r['pending_steps_ms']:.1f} ms, "
                  f"all steps {r['all_steps_ms']:.1f} ms, progress {r['progress_ms']:.1f} ms, "
                  f"frames {r['frames_ms']:.1f} ms, list {r['list_sessions_ms']:.1f} ms, "
                  f"verify {r['verify_s']:.2f} s, export {r['export_s']:.2f} s")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
