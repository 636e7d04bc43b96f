"""PTP camera path through the simulated USB backend: GetObject throughput and bracket overhead.

    python benchmarks/rig_camera.py [--repeats 5]

Prints
- GetObject throughput (MB/s) for a 24-megapixel 16-bit DNG (6000 x 4000, ~48 MB) through
  pyusb and :class:`sims.ptp_sim.PtpCameraSim` (target >= 200 MB/s);
- one full ``capture()`` of that frame (InitiateCapture, events, ObjectInfo, GetObject, Delete);
- a bracket's per-frame overhead: protocol and driver time per frame with a tiny cached frame
  (the simulator answers at once, so this is what the host side adds to each exposure).
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


def big_dng(width: int = 6000, height: int = 4000) -> bytes:
    rng = np.random.default_rng(0)
    raw = rng.integers(512, 15000, size=(height, width), dtype=np.uint16)
    return write_dng(raw, black_level=512, white_level=15871, exposure_s=0.01, iso=100, fnumber=8)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="downloads / brackets to time")
    args = ap.parse_args()

    dng = big_dng()
    sim = PtpCameraSim(lambda state: dng)
    cam = PtpCamera("camera", sim.vendor_id, sim.product_id, backend=sim, keep_on_camera=True)
    cam.connect()
    frame = cam.capture()
    handle = frame.metadata["handle"]
    assert frame.data == dng
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        data = cam.session.get_object(handle)
        times.append(time.perf_counter() - t0)
        assert len(data) == len(dng)
    mb = len(dng) / 1e6
    best, med = min(times), statistics.median(times)
    print(f"GetObject, 24 MP 16-bit DNG ({mb:.1f} MB): median {med * 1e3:.1f} ms = "
          f"{mb / med:.0f} MB/s (best {mb / best:.0f} MB/s; target >= 200 MB/s)")
    cam.keep_on_camera = False
    caps = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        cam.capture()
        caps.append(time.perf_counter() - t0)
    print(f"capture() of the 24 MP frame end to end: median {statistics.median(caps) * 1e3:.1f} ms")
    cam.close()

    small = placeholder_frame({"exposure_s": 0.01, "iso": 100, "fnumber": 8.0}, size=(64, 48))
    sim = PtpCameraSim(lambda state: small)
    cam = PtpCamera("camera", sim.vendor_id, sim.product_id, backend=sim)
    cam.connect()
    exposures = [1 / 1000, 1 / 500, 1 / 250, 1 / 125, 1 / 60, 1 / 30, 1 / 15]
    per_frame = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        frames = cam.bracket(exposures)
        per_frame.append((time.perf_counter() - t0) / len(frames))
    print(f"bracket of {len(exposures)} exposures: host/protocol overhead "
          f"{statistics.median(per_frame) * 1e3:.2f} ms per frame (set exposure + capture + "
          "download + delete, tiny frame)")
    cam.close()


if __name__ == "__main__":
    main()
