"""PTP camera path through the simulated USB backend: GetObject throughput and bracket overhead.

    python benchmarks/rig_camera.py [--repeats 5]

Prints
- GetObject throughput (MB/s) for a 24-megapixel 16-bit DNG (6000 x 4000, ~48 MB) through
  pyusb and :class:`sims.ptp_sim.PtpCameraSim` (target >= 200 MB/s);
- one full ``capture()`` of that frame (InitiateCapture, events, ObjectInfo, GetObject, Delete);
- a bracket's per-frame overhead: protocol and driver time per frame with a tiny cached frame
  (the simulator answers at once, so this is what the host side adds to each exposure).

``benchmarks/rig.py`` imports :func:`bench_get_object` and :func:`bench_bracket` so that one run
prints every rig figure.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

# benchmarks/rig.py would shadow the rig package when this runs as a script: drop this folder
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != os.path.dirname(os.path.abspath(__file__))]

import numpy as np  # noqa: E402

from rig.ptp_camera import PtpCamera  # noqa: E402
from sims.dng import write_dng  # noqa: E402
from sims.ptp_sim import PtpCameraSim, placeholder_frame  # noqa: E402

#: the throughput the driver must reach so that USB 3 (not the host) is the bottleneck, MB/s
TARGET_MB_S = 200.0


def big_dng(width: int = 6000, height: int = 4000) -> bytes:
    """A ``width`` x ``height`` 16-bit CFA DNG (uncompressed, ~48 MB for 24 MP)."""
    rng = np.random.default_rng(0)
    raw = rng.integers(512, 15000, size=(height, width), dtype=np.uint16)
    return write_dng(raw, black_level=512, white_level=15871, exposure_s=0.01, iso=100, fnumber=8)


def bench_get_object(repeats: int = 5) -> float:
    """Time GetObject of a 24 MP 16-bit DNG and a full ``capture()``; print them.

    Returns
    -------
    float
        Median GetObject throughput, MB/s (10^6 bytes per second).
    """
    dng = big_dng()
    sim = PtpCameraSim(lambda state: dng)
    cam = PtpCamera("camera", sim.vendor_id, sim.product_id, backend=sim, keep_on_camera=True)
    cam.connect()
    try:
        frame = cam.capture()
        handle = frame.metadata["handle"]
        if frame.data != dng:
            raise RuntimeError("the downloaded frame differs from the camera's file")
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            data = cam.session.get_object(handle)
            times.append(time.perf_counter() - t0)
            if len(data) != len(dng):
                raise RuntimeError(f"GetObject returned {len(data)} of {len(dng)} bytes")
        mb = len(dng) / 1e6
        best, med = min(times), statistics.median(times)
        verdict = "meets" if mb / med >= TARGET_MB_S else "MISSES"
        print(f"  GetObject, 24 MP 16-bit DNG ({mb:.1f} MB): median {med * 1e3:.1f} ms = "
              f"{mb / med:.0f} MB/s (best {mb / best:.0f} MB/s; {verdict} the >= {TARGET_MB_S:.0f} MB/s target)")
        cam.keep_on_camera = False
        caps = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            cam.capture()
            caps.append(time.perf_counter() - t0)
        print(f"  capture() of the 24 MP frame end to end: median {statistics.median(caps) * 1e3:.1f} ms")
    finally:
        cam.close()
    return mb / med


def bench_bracket(repeats: int = 5) -> float:
    """Time 7-exposure brackets of a tiny frame; print and return the per-frame overhead, ms."""
    small = placeholder_frame({"exposure_s": 0.01, "iso": 100, "fnumber": 8.0}, size=(64, 48))
    sim = PtpCameraSim(lambda state: small)
    cam = PtpCamera("camera", sim.vendor_id, sim.product_id, backend=sim)
    cam.connect()
    try:
        exposures = [1 / 1000, 1 / 500, 1 / 250, 1 / 125, 1 / 60, 1 / 30, 1 / 15]
        per_frame = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            frames = cam.bracket(exposures)
            per_frame.append((time.perf_counter() - t0) / len(frames))
    finally:
        cam.close()
    ms = statistics.median(per_frame) * 1e3
    print(f"  bracket of {len(exposures)} exposures: host/protocol overhead {ms:.2f} ms per frame "
          "(set exposure + capture + download + delete, tiny frame)")
    return ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="downloads / brackets to time")
    args = ap.parse_args()
    print("PTP camera through the simulated USB backend (pyusb IBackend)")
    bench_get_object(args.repeats)
    bench_bracket(args.repeats)


if __name__ == "__main__":
    main()
