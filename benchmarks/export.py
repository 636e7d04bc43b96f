"""gonio export checked by Mitsuba 3: ``python benchmarks/export.py [--quick] [--store DIR --session NAME]``.

Without ``--store`` it runs the demo (:func:`capture.pipeline.demo.run_demo`, 640 x 480, or
320 x 240 with ``--quick``) into a temporary folder. For each exported method (lensch, sharing,
passive) it writes the maps, the glTF file and the Mitsuba scenes, renders every held-out capture
with Mitsuba 3 (scalar_rgb, a 3x finer film, 4 samples per pixel) and prints, at the held-out
samples: the export's stated approximation error (its formula through the textures against the
method's predictions; glTF's beside it), Mitsuba's render against the method's predictions and
against the captures, the method's own held-out error, and the times of the export and the
renders. The test suite checks the quick demo's Lensch export (tests/capture/test_demo.py).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the package, not benchmarks/capture.py

from capture.export.appearance import EXPORTED_METHODS, Appearance  # noqa: E402
from capture.export.session import export_session  # noqa: E402
from reconstruct.metrics import relative_rms  # noqa: E402
from capture.store import Store  # noqa: E402
from capture.export.check import render_held_out  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="run the 320 x 240 quick demo")
    parser.add_argument("--store", help="an existing store (processed by gonio process)")
    parser.add_argument("--session", default="demo-quick")
    parser.add_argument("--spp", type=int, default=4)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="gonio-export-bench-"))
    if args.store is None:
        from capture.pipeline.demo import run_demo
        started = time.perf_counter()
        run_demo(work / "demo", quick=args.quick)
        print(f"demo{' --quick' if args.quick else ''}: {time.perf_counter() - started:.0f} s wall")
        store_dir, session = work / "demo" / "store", ("demo-quick" if args.quick else "demo")
    else:
        store_dir, session = Path(args.store), args.session
    print(f"{'method':<8} {'stated':>7} {'glTF':>6} {'mitsuba/pred':>12} {'mitsuba/capt':>12} "
          f"{'method/capt':>11} {'samples':>8} {'export s':>8} {'render s':>8}")
    with Store.open(store_dir, readonly=True) as st:
        sid = st.session(session).id
        runs = {r.kind: r for r in st.results(sid, "reconstruction")}
        for method in EXPORTED_METHODS:
            if method not in runs or "appearance.npz" not in runs[method].artifacts:
                print(f"{method:<8} not stored with export data")
                continue
            app = Appearance.from_npz(st.read_object(runs[method].artifacts["appearance.npz"]))
            started = time.perf_counter()
            rep = export_session(st, session, method=method, formats=["maps", "gltf", "mitsuba"], out=work / method)
            t_export = time.perf_counter() - started
            a = rep.model["approximation"]
            started = time.perf_counter()
            n_train = int(np.sum(~app.view_held_out))
            renders = [render_held_out(work / method / "mitsuba" / f"heldout-{k:03d}.xml", app, n_train + k,
                                       spp=args.spp) for k in range(int(app.view_held_out.sum()))]
            got, pred, capt = (np.concatenate([getattr(r, k) for r in renders])
                               for k in ("rendered", "predicted", "captured"))
            t_render = time.perf_counter() - started
            print(f"{method:<8} {a['export_vs_method_held_out_rel_rms']:7.3f} {a['gltf_vs_method_held_out_rel_rms']:6.3f} "
                  f"{relative_rms(got, pred):12.3f} {relative_rms(got, capt):12.3f} {relative_rms(pred, capt):11.3f} "
                  f"{len(got):8d} {t_export:8.1f} {t_render:8.1f}")
            print(f"         per-material fit error: {json.dumps(a['brdf_fit_rel_rms_per_material'])}")
    print(f"files in {work}")


if __name__ == "__main__":
    main()
