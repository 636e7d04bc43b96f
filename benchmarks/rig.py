"""Rig benchmarks, every figure the rig issue asks for in one run.

    python benchmarks/rig.py [--n 3000] [--repeats 5]

Prints
- request/reply round trip (median, p99, microseconds) over a real pseudo-terminal for a Zaber
  status poll and a GRBL ``?`` status report, with the transport as built (chunked select +
  os.read) and, for comparison, with pyserial's own byte-at-a-time ``read_until``;
- PTP GetObject throughput for a 24-megapixel 16-bit DNG through the simulated USB backend
  (target >= 200 MB/s), a full ``capture()`` of it, and a bracket's per-frame overhead
  (the functions of ``benchmarks/rig_camera.py``);
- concurrent moves: turntable and positioner (non-fast simulators, ~0.7-0.9 s moves) each alone,
  then together; the ratio together / max(alone) should be close to 1 (not ~2 = sum).

Exits with status 1 if the throughput target is missed or the concurrent ratio exceeds 1.25.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import sys
import time
from typing import Callable

# this file is named rig.py: drop its folder from the path so `import rig` finds the package
# (the camera benchmarks beside it are then loaded by file path, see _camera_benchmarks)
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]

import serial  # noqa: E402

from rig import LightTarget, wait_all  # noqa: E402
from rig.errors import DeviceTimeout  # noqa: E402
from rig.grbl import GrblPositioner  # noqa: E402
from rig.transport import SerialTransport  # noqa: E402
from rig.zaber import ZaberRotaryStage  # noqa: E402
from sims.grbl_sim import GrblSim  # noqa: E402
from sims.zaber_sim import ZaberSim  # noqa: E402


class PyserialReadTransport(SerialTransport):
    """The transport as it was: pyserial ``read_until`` (one byte per read) and a timeout
    reconfiguration whenever the requested timeout changes. For comparison only."""

    def read_until(self, terminator: bytes = b"\n", timeout_s: float | None = None) -> bytes:
        timeout = self.timeout_s if timeout_s is None else timeout_s
        port = self._port()
        if port.timeout != timeout:
            port.timeout = timeout
        buf = port.read_until(terminator)
        if not buf.endswith(terminator):
            raise DeviceTimeout("no complete reply", device=self.device, timeout_s=timeout)
        return bytes(buf)


def _time(fn: Callable[[], object], n: int, rounds: int = 5) -> tuple[float, float, float]:
    """Median and p99 over all ``n`` calls, and the best per-round median (robust to other load
    on the machine), microseconds."""
    for _ in range(50):  # warm up
        fn()
    samples, round_medians = [], []
    for _ in range(rounds):
        chunk = []
        for _ in range(max(1, n // rounds)):
            t0 = time.perf_counter()
            fn()
            chunk.append(time.perf_counter() - t0)
        round_medians.append(statistics.median(chunk))
        samples += chunk
    samples.sort()
    return (statistics.median(samples) * 1e6, samples[int(0.99 * (len(samples) - 1))] * 1e6,
            min(round_medians) * 1e6)


def bench_round_trip(n: int = 3000) -> None:
    print(f"serial round trip over a pty ({n} requests each), microseconds")
    print(f"  {'exchange':<34} {'transport':<22} {'median':>8} {'p99':>8} {'best-round median':>18}")
    for label, transport_cls in (("chunked select+os.read", SerialTransport),
                                 ("pyserial read_until", PyserialReadTransport)):
        with ZaberSim(fast=True, homed=True) as sim:
            stage = ZaberRotaryStage("turntable", transport=transport_cls(sim.port, device="turntable"))
            stage.connect()
            med, p99, best = _time(lambda: stage.request(""), n)
            print(f"  {'zaber status poll (/1 1 id:CC)':<34} {label:<22} {med:8.1f} {p99:8.1f} {best:18.1f}")
            stage.close()
        with GrblSim(fast=True, settings={22: 0}) as sim:  # homing off: no machine map needed
            light = GrblPositioner("positioner", transport=transport_cls(sim.port, device="positioner"))
            light.connect()
            med, p99, best = _time(light.status, n)
            print(f"  {'grbl status report (?)':<34} {label:<22} {med:8.1f} {p99:8.1f} {best:18.1f}")
            light.close()


def bench_concurrent(repeats: int = 3) -> float:
    """Time each move alone, then both together; print and return the median ratio
    together / max(alone)."""
    print("concurrent moves (turntable 60 deg at 90 deg/s, 360 deg/s^2; arm 50x20 deg at 90 deg/s)")
    with ZaberSim(fast=False, homed=True, speed_deg_s=90, accel_deg_s2=360) as zsim, \
            GrblSim(fast=False, settings={22: 0}) as gsim:
        table = ZaberRotaryStage("turntable", zsim.port, poll_interval_s=0.01)
        light = GrblPositioner("positioner", gsim.port, kinematics=gsim.kinematics, poll_interval_s=0.01)
        table.connect()
        light.connect()
        ratios = []
        try:
            for _ in range(repeats):
                t0 = time.monotonic()
                table.move_to(60).wait(5)
                t_table = time.monotonic() - t0
                t0 = time.monotonic()
                light.move_to(LightTarget(azimuth_deg=50, elevation_deg=20)).wait(5)
                t_light = time.monotonic() - t0
                t0 = time.monotonic()
                wait_all([table.move_to(0), light.move_to(LightTarget(azimuth_deg=0, elevation_deg=0))],
                         timeout=5)
                t_both = time.monotonic() - t0
                ratios.append(t_both / max(t_table, t_light))
                print(f"  alone: turntable {t_table:.3f} s, positioner {t_light:.3f} s; together {t_both:.3f} s "
                      f"(sum would be {t_table + t_light:.3f} s)")
        finally:
            table.close()
            light.close()
    ratio = statistics.median(ratios)
    print(f"  ratio together / max(alone): median {ratio:.3f} (1.0 = fully concurrent, ~2 = serial)")
    return ratio


def _camera_benchmarks():
    """``benchmarks/rig_camera.py`` as a module, loaded by path (its folder is off sys.path)."""
    spec = importlib.util.spec_from_file_location("gonio_bench_rig_camera", os.path.join(_HERE, "rig_camera.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=3000, help="round trips to time per case")
    ap.add_argument("--repeats", type=int, default=5, help="PTP downloads / brackets to time")
    args = ap.parse_args()
    camera = _camera_benchmarks()
    print(f"pyserial {serial.__version__}, Python {sys.version.split()[0]}, {os.cpu_count()} CPUs")
    bench_round_trip(args.n)
    print()
    print("PTP camera through the simulated USB backend (pyusb IBackend)")
    mb_s = camera.bench_get_object(args.repeats)
    camera.bench_bracket(args.repeats)
    print()
    ratio = bench_concurrent()
    failed = []
    if mb_s < camera.TARGET_MB_S:
        failed.append(f"GetObject {mb_s:.0f} MB/s < {camera.TARGET_MB_S:.0f} MB/s")
    if ratio > 1.25:
        failed.append(f"concurrent ratio {ratio:.2f} > 1.25")
    if failed:
        print("FAILED: " + "; ".join(failed))
        sys.exit(1)


if __name__ == "__main__":
    main()
