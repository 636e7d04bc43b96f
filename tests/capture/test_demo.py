"""``gonio demo --quick`` end to end, as a new user runs it: a subprocess in a clean folder.

It captures the quick demo plan on the simulated lab (real drivers, real DNG files), calibrates,
reconstructs with every method that is installed and writes ``report.html``. The test checks the
report is one self-contained file and that the ground-truth errors it states are within the
targets the calibration and reconstruction tests state for a 320 x 240 camera.
"""
from __future__ import annotations

import base64
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


def test_gonio_demo_quick_writes_a_self_contained_report_within_the_targets(tmp_path):
    cwd = tmp_path / "clean"
    cwd.mkdir()
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    started = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "capture.cli", "demo", "--quick", "--out", "demo", "-q"],
                         cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - started
    assert run.returncode == 0, run.stdout + run.stderr
    out = cwd / "demo"
    assert f"store: {out / 'store'}" in run.stdout            # absolute paths, printed
    report = out / "report.html"
    assert report.is_file() and f"report: {report}" in run.stdout
    # nothing but the folder it was given: the report and the store
    assert sorted(p.name for p in cwd.iterdir()) == ["demo"]

    text = report.read_text()
    srcs = re.findall(r'<img src="([^"]*)"', text)
    assert len(srcs) >= 4 and len(srcs) == text.count("<img")
    assert not re.search(r'(href|src)="(?!data:)', text)   # no file or web references
    for s in srcs:
        assert base64.b64decode(s.removeprefix("data:image/png;base64,"))[:8] == b"\x89PNG\r\n\x1a\n"

    summary = json.loads((out / "report.json").read_text())
    cal = summary["calibration_truth"]
    stages = {c["stage"]: c["status"] for c in summary["calibration"]}
    assert all(stages[s] == "ok" for s in ("intrinsics", "turntable", "lights", "positioner", "gray_card",
                                           "mirror_probe")), stages
    # the calibration tests' bounds at 320 x 240 (tests/capture/test_calibrate.py): focal length
    # 1.5 %, light direction 4 deg; the demo's arm model over nine lights does better than their
    # 25 % distance (seen: focal 0.9 %, lights <= 2.3 % of their distance, 1.1 deg)
    assert max(abs(v) for v in cal["focal_error_pct"]) < 1.5
    assert cal["max_light_direction_error_deg"] < 4.0
    assert cal["max_light_error_pct_of_distance"] < 6.0
    assert max(abs(v) for v in cal["intensity_error_pct"]) < 15.0       # seen: -3.5 %
    inputs = summary["inputs"]
    assert inputs["held_out_views"] == 4 and inputs["polarization_separated"] and inputs["passive_capture"]
    # the typical measured sample within 5 % of the true reflectance (seen: +1 %)
    assert abs(inputs["measured_vs_truth_median_ratio"] - 1) < 0.05
    methods = {m["method"]: m for m in summary["methods"]}
    assert set(methods) == {"lambertian", "lensch", "sharing", "passive"}
    assert methods["lambertian"]["status"] == "ok"
    # a matte model misses every highlight (seen: 0.74 held out, 0.77 against the truth)
    assert 0.3 < methods["lambertian"]["figures"]["held_out_rel_rms"] < 0.95
    for m in methods.values():
        assert m["status"] in ("ok", "skipped"), (m["method"], m["reason"])
        if m["status"] == "ok":
            assert np.isfinite(m["figures"]["held_out_rel_rms"])
    lam = methods["lambertian"]["figures"]
    if methods["lensch"]["status"] == "ok":
        f = methods["lensch"]["figures"]
        t2 = f["table_ii_rms"]
        # the paper's Table II: clustering and projection lower the fitting error (seen: 0.091,
        # 0.039, 0.032, 0.022). Normal fitting lowers it too on most noise draws but raised it
        # above the projection's on one in five (0.054 vs 0.035; see docs/architecture.md), so
        # here it must only stay below the single average BRDF; the strict order is tested on
        # fixed draws in tests/reconstruct/test_lensch_object.py
        assert t2["single"] > t2["cluster"] > t2["projection"], t2
        assert t2["normal_fit"] < t2["single"], t2
        # normal fitting recovers relief the smooth mesh lacks (seen: 1.41 -> 0.82 deg median),
        # or, on the clusterings where its first round raised the error (about one run in
        # four; docs/architecture.md), the method says it undid it and keeps the mesh normals
        undone = [w for w in methods["lensch"]["warnings"] if "normal-fitting round 1" in w]
        if undone:
            assert abs(f["normal_error_fitted_deg"] - f["normal_error_mesh_deg"]) < 1e-6, f
        else:
            assert f["normal_error_fitted_deg"] < 0.8 * f["normal_error_mesh_deg"], f
        # better than the matte reference under lights it never saw and against the truth (seen:
        # 0.63 vs 0.80 held out, 0.65 vs 0.83 vs truth; the measured samples themselves are
        # 0.27 from the truth at 320 x 240)
        # The pooled figure is carried by the 1 % worst highlight samples and swings with the
        # noise draw (seen 0.63-1.06 against the matte 0.80): the robust figure must beat the
        # matte reference clearly, the pooled one must not run away
        assert f["held_out_rel_rms_trimmed"] < 0.8 * lam["held_out_rel_rms_trimmed"], f
        assert f["held_out_rel_rms"] < 1.5 * lam["held_out_rel_rms"], f
        assert f["truth_rel_rms"] < 1.5 * lam["truth_rel_rms"], f
    if methods["sharing"]["status"] == "ok":
        # about normals fitted to the diffuse samples it beats matte under new lights (seen: 0.37
        # vs 0.80, trimmed 0.27 vs 0.70; about the smooth mesh's normals it was 0.72-0.81: the
        # bumps move the highlights)
        f = methods["sharing"]["figures"]
        assert f["held_out_rel_rms"] < 0.75 * lam["held_out_rel_rms"], f
        assert f["held_out_rel_rms_trimmed"] < 0.75 * lam["held_out_rel_rms_trimmed"], f
    if methods["passive"]["status"] == "ok":
        # the 320 x 240 probe (a 19 px ball) cannot explain the image: the method must say so
        # rather than return a confident answer (seen: relative residual 83 %)
        assert any("residual" in w for w in methods["passive"]["warnings"]), methods["passive"]["warnings"]
    # `gonio process` on the stored session recomputes the demo's figures (a fresh calibration
    # included: --force)
    again = subprocess.run([sys.executable, "-m", "capture.cli", "process", "demo-quick", "--store",
                            str(out / "store"), "--demo-lab", "--methods", "lambertian", "--force", "-q",
                            "--json", "--out", str(out / "again.html")],
                           cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stdout + again.stderr
    redo = {m["method"]: m for m in json.loads(again.stdout)["methods"]}["lambertian"]["figures"]
    for key in ("held_out_rel_rms", "truth_rel_rms"):
        assert redo[key] == pytest.approx(lam[key], rel=0.01), key   # OpenCV fits: not bit-exact
    print(f"gonio demo --quick: {wall:.0f} s wall; stages {summary['timings']}")
