"""``gonio demo --quick`` end to end, as a new user runs it: a subprocess in a clean folder.

It captures the quick demo plan on the simulated lab (real drivers, real DNG files), calibrates,
reconstructs with every method (a skipped or failed one fails the test) and writes ``report.html``. The test checks the
report is one self-contained file and that the ground-truth errors it states are within the
targets the calibration and reconstruction tests state for a 320 x 240 camera.
"""
from __future__ import annotations

import base64
import html
import io
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from background import load, save
from capture.store import Store

REPO = Path(__file__).resolve().parents[2]


ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _gonio(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """``gonio ARGS`` in a subprocess in ``cwd``, as a user types it."""
    return subprocess.run([sys.executable, "-m", "capture.cli", *args], cwd=cwd, env=ENV, capture_output=True,
                          text=True, timeout=600)


def run_demo(root: Path) -> None:
    """The background job (tests/background.py) behind ``demo``: ``gonio demo --quick --out demo``
    in the clean folder ``root / "clean"``; its run and wall seconds kept."""
    cwd = root / "clean"
    cwd.mkdir()
    started = time.perf_counter()
    run = _gonio(cwd, "demo", "--quick", "--out", "demo", "-q")
    save(root, (run, time.perf_counter() - started))


@pytest.fixture(scope="module")
def demo(background):
    """``gonio demo --quick --out demo`` run once in a clean folder: (folder, run, wall seconds)."""
    root = background.folder("demo")
    return (root / "clean", *load(root))


#: the methods ``gonio process`` runs again on the recaptured session. Two of the four, for the
#: suite's time (Lensch and passive: ~17 s on 2 idle cores): the calibration, the lumitexels and
#: the floor, which every method starts from, are compared whole, and each method is a
#: deterministic function of them and the lab's options
REPROCESSED = ["lambertian", "sharing"]


def capture_then_process(root: Path) -> None:
    """The background job behind ``recaptured``: ``gonio capture run examples/demo-quick.toml
    --rig sim`` in the clean folder ``root``, then ``gonio process`` of that session with
    :data:`REPROCESSED` (None when the capture failed); both runs kept."""
    plan = REPO / "examples" / "demo-quick.toml"
    capture = _gonio(root, "capture", "run", str(plan), "--rig", "sim", "--store", "store", "--session",
                     "demo-quick", "-q")
    process = None if capture.returncode != 0 else _gonio(
        root, "process", "demo-quick", "--store", "store", "-q", "--json", "--out", "report.html",
        "--methods", ",".join(REPROCESSED))
    save(root, (capture, process))


@pytest.fixture(scope="module")
def recaptured(background):
    """(folder, ``gonio capture run``, ``gonio process`` or None) of :func:`capture_then_process`."""
    root = background.folder("recapture")
    return (root, *load(root))


def test_gonio_demo_quick_writes_a_self_contained_report_within_the_targets(demo):
    cwd, run, wall = demo
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
    # The calibration at 320 x 240, where its targets (focal 0.2 %, lights 0.5 % of their distance
    # and 0.25 deg; met by the full demo at 640 x 480, docs/measurements.md) sit at the limit of
    # what a 0.13 px corner and a 0.1 px highlight allow: focal within 0.4 % (seen: -0.13/-0.19 %;
    # other noise seeds -0.14..-0.32 %, tests/capture/test_calibrate.py), principal point within
    # 3 px (seen: 1.7), lights within 1.5 % of their distance and 0.75 deg (seen: 1.05 %, 0.50
    # deg; 0.42 % and 0.23 deg with the true camera handed in), lamp intensity 3 % (seen: -0.8 %)
    assert max(abs(v) for v in cal["focal_error_pct"]) < 0.4
    assert max(abs(v) for v in cal["principal_point_error_px"]) < 3.0
    assert cal["max_light_error_pct_of_distance"] < 1.5
    assert cal["max_light_direction_error_deg"] < 0.75
    assert max(abs(v) for v in cal["intensity_error_pct"]) < 3.0
    inputs = summary["inputs"]
    assert inputs["held_out_views"] == 4 and inputs["polarization_separated"] and inputs["passive_capture"]
    assert inputs["passive_on"] == "the sample sphere"   # the plan's passive_sphere capture
    # the typical measured sample within 5 % of the true reflectance (seen: +1 %)
    assert abs(inputs["measured_vs_truth_median_ratio"] - 1) < 0.05
    methods = {m["method"]: m for m in summary["methods"]}
    assert set(methods) == {"lambertian", "lensch", "sharing", "passive"}
    assert methods["lambertian"]["status"] == "ok"
    # a matte model misses every highlight (seen: 0.74 held out, 0.77 against the truth)
    assert 0.3 < methods["lambertian"]["figures"]["held_out_rel_rms"] < 0.95
    on_object = {k: m for k, m in methods.items() if k != "passive"}   # passive ran on the sample sphere
    for m in methods.values():   # the quick plan captures what every method needs: none may skip
        assert m["status"] == "ok", (m["method"], m["status"], m["reason"])
    for m in on_object.values():
        assert np.isfinite(m["figures"]["held_out_rel_rms"])
    lam = methods["lambertian"]["figures"]
    f = methods["lensch"]["figures"]
    t2 = f["table_ii_rms"]
    # the paper's Table II: clustering and projection lower the fitting error (seen: 0.091,
    # 0.039, 0.032, 0.022). Normal fitting lowers it too on most noise draws but raised it
    # above the projection's on one in five (0.054 vs 0.035; see docs/measurements.md), so
    # here it must only stay below the single average BRDF; the strict order is tested on
    # fixed draws in tests/reconstruct/test_lensch_object.py
    assert t2["single"] > t2["cluster"] > t2["projection"], t2
    assert t2["normal_fit"] < t2["single"], t2
    assert f["materials"] == 3, f   # the demo object's three (seen: 3 in 3 clusters)
    # normal fitting recovers relief the smooth mesh lacks (seen: 1.41 -> 0.82 deg median),
    # or, on the clusterings where its first round raised the error (about one run in
    # four; docs/measurements.md), the method says it undid it and keeps the mesh normals
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
    # about normals fitted to the diffuse samples it beats matte under new lights (seen: 0.37
    # vs 0.80, trimmed 0.27 vs 0.70; about the smooth mesh's normals it was 0.72-0.81: the
    # bumps move the highlights)
    f = methods["sharing"]["figures"]
    assert f["held_out_rel_rms"] < 0.75 * lam["held_out_rel_rms"], f
    assert f["held_out_rel_rms_trimmed"] < 0.75 * lam["held_out_rel_rms_trimmed"], f
    # the 320 x 240 probe (a 20 px ball) does not explain the image to 5 %: the method must say so
    # rather than return a confident answer (seen: relative residual 10-18 % on the sample sphere)
    assert any("residual" in w for w in methods["passive"]["warnings"]), methods["passive"]["warnings"]
    # passive on the sample sphere is scored against the sphere's true material, not on the
    # object's held-out lights. The probe map of a 20 px ball limits it: the true BRDF rendered
    # under that map is 0.15 off the photograph (0.85 before the probe's limb fit and smooth-hue
    # demosaic; the truth's own map: 0.09, tests/capture/test_passive_sample.py); the recovered
    # BRDF, which fits the photograph under that map, must explain it better than the truth
    # does (seen 0.11 vs 0.15), and must beat a matte BRDF on Eq. 1 against the truth (seen
    # 0.47 vs 0.68, the reduction's 0.07; before the probe fix 1.69 vs 1.62; docs/measurements.md)
    f = methods["passive"]["figures"]
    assert f["render_rel_rms"] < f["floor_render_rel_rms"] < 0.3, f
    assert f["eq1_error"] < 0.85 * f["eq1_error_lambertian"], f
    assert 0 < f["eq1_error_reduction"] < 0.1 and f["eq1_error_reduction"] < f["eq1_error"], f
    assert np.isfinite(f["eq1_error_lambertian"]) and np.isfinite(f["held_out_env_rel_rms"]), f
    assert "held_out_rel_rms" not in f and methods["passive"]["floor_ratio"] is None, f
    # The floor: the simulation's true model scored on the same held-out captures as the methods
    # (seen: 0.26, trimmed 0.14; ratios lambertian 3.06, lensch 1.79, sharing 1.25).
    # Every model is fitted to noisy captures through the same calibration, so none may come out
    # below the truth; each ratio is its held-out error over the floor's; issue 24's target: the
    # best spatially varying method within 1.5x of the floor (sharing 1.46x before its polar form)
    floor = summary["floor"]
    assert min(methods[m]["floor_ratio"] for m in ("lensch", "sharing")) < 1.5, methods
    assert 0 < floor["held_out_rel_rms"] < 1 and 0 < floor["held_out_rel_rms_trimmed"] <= floor["held_out_rel_rms"]
    for m in on_object.values():
        f = m["figures"]
        assert f["held_out_rel_rms"] > floor["held_out_rel_rms"], (m["method"], f, floor)
        assert m["floor_ratio"] == pytest.approx(f["held_out_rel_rms"] / floor["held_out_rel_rms"], rel=1e-9)
        assert m["floor_ratio_trimmed"] == pytest.approx(
            f["held_out_rel_rms_trimmed"] / floor["held_out_rel_rms_trimmed"], rel=1e-9)
    assert "floor (the true model on the same held-out captures)" in run.stdout
    # passive runs on the homogeneous sample sphere, within its assumption; no method is labelled
    # outside it (the old plans' object capture: test_an_old_plan_runs_passive_on_the_object_...)
    assert not any(m["outside_assumption"] for m in methods.values())
    assert "Outside its assumption" not in text
    # passive's adequacy report is a table in its section, not only warnings: the paper's regions
    # with the share of their nodes the room lit too little, and the theta_d bands it left to the prior
    passive = text.split("<h3>4. passive</h3>")[1]
    # the sample sphere's part: its figures against the truth, the sphere photographed, recovered
    # and true, and under a room the method never saw
    eq1 = methods["passive"]["figures"]["eq1_error"]
    assert "On the sample sphere" in passive and f"<td>{eq1:.4g}</td>" in passive
    assert "sample sphere: photograph, recovered and true" in passive
    assert "sample sphere under a held-out environment" in passive
    poor = methods["passive"]["figures"]["poorly_observed"]
    assert len(poor) == 3 and "What the room's light could not constrain" in passive
    for region, share in poor.items():
        assert f"<td>{html.escape(region)}</td><td>{share:.0%}</td>" in passive, region
    for band in methods["passive"]["figures"]["unconstrained"]:
        assert f"theta_d {band['theta_d_deg'][0]}–{band['theta_d_deg'][1]}°, theta_h {band['theta_h_deg']}°" in passive
    # the plan reads as a table (the quick plan's four turntable angles as one run), the stored
    # JSON behind a fold
    assert "0–270 by 90 (4)" in text and "<details><summary>the plan as stored (JSON)" in text
    # `gonio process` recomputing these figures: test_capture_run_then_process_gives_the_demos_...
    print(f"gonio demo --quick: {wall:.0f} s wall; stages {summary['timings']}")


def _numbers(tree, path: str = ""):
    """Every number in a JSON tree as (path, value), run times and store row ids left out (the
    processing may store other methods first)."""
    if isinstance(tree, dict):
        for key, value in tree.items():
            if key not in ("seconds", "timings", "result_id"):
                yield from _numbers(value, f"{path}.{key}")
    elif isinstance(tree, list):
        for i, value in enumerate(tree):
            yield from _numbers(value, f"{path}[{i}]")
    elif isinstance(tree, (int, float)) and not isinstance(tree, bool):
        yield path, tree


def _frames(store_dir: Path, session: str) -> list[tuple[int, int, int, str]]:
    with Store(store_dir) as store:
        return [(f.step, f.bracket_index, f.repeat, f.sha256) for f in store.frames(store.session(session).id)]


def test_capture_run_then_process_gives_the_demos_frames_and_figures(demo, recaptured):
    """Issue 13: ``gonio process`` on a session captured with ``gonio capture run`` gives the same
    figures as the demo's own processing of the same plan. ``--rig sim`` renders the demo's lab
    with every scene's noise seeded and the DNG clock counting captures, so the frames are the
    demo's byte for byte; the processing, a fresh calibration included, then reproduces every
    figure: calibration, calibration against truth, inputs, the floor, and the held-out and truth
    errors of Lambertian and sharing. Tolerance: 1e-9 relative (measured: equal to the bit in every run;
    benchmarks/reproducibility.py measures the re-calibration's spread, none with OpenCV's
    solvers on one thread)."""
    demo_cwd, demo_run, _ = demo
    assert demo_run.returncode == 0, demo_run.stdout + demo_run.stderr
    cwd, run, process = recaptured
    assert run.returncode == 0 and "session demo-quick done" in run.stdout, run.stdout + run.stderr
    captured, demoed = _frames(cwd / "store", "demo-quick"), _frames(demo_cwd / "demo" / "store", "demo-quick")
    assert len(captured) == len(demoed) > 100
    assert captured == demoed   # same steps, exposures, repeats and DNG bytes (sha256)

    run = process
    assert run.returncode == 0, run.stdout + run.stderr   # no --mesh, no targets: the lab states them
    got = json.loads(run.stdout)
    want = json.loads((demo_cwd / "demo" / "report.json").read_text())
    want["methods"] = [m for m in want["methods"] if m["method"] in REPROCESSED]
    assert [m["method"] for m in got["methods"]] == REPROCESSED
    for part in ("calibration", "calibration_truth", "inputs", "methods", "floor"):
        mine, theirs = dict(_numbers(got[part])), dict(_numbers(want[part]))
        assert mine.keys() == theirs.keys(), part
        assert mine, part
        for key, value in theirs.items():
            assert mine[key] == pytest.approx(value, rel=1e-9, abs=1e-12, nan_ok=True), f"{part}{key}"
    for m in want["methods"]:   # the headline figures are among them: say so plainly
        assert m["status"] == "ok", m["method"]
        assert {"held_out_rel_rms", "truth_rel_rms"} <= set(m["figures"]), m["method"]


def test_export_of_the_quick_demo_renders_in_mitsuba_as_gonio_predicts(demo, tmp_path):
    """Issue 22 on the demo's own session: ``gonio export`` writes Lensch's model; Mitsuba 3
    renders each held-out capture's scene (the calibrated camera, the held-out light; a 3x finer
    film, so a pixel's footprint does not blur the highlights); at the held-out samples the
    render matches gonio's own predictions within the export's stated approximation error (plus
    0.03 for what remains of the pixel footprint and Monte Carlo: seen 0.199 against a stated
    0.184) and the captures within 1.2x gonio's own held-out error (seen 0.656 vs 0.668).
    Passive reflectometry's table goes out as a MERL file holding its values at MERL's nodes."""
    pytest.importorskip("mitsuba")
    from typer.testing import CliRunner

    from capture.cli import app as cli
    from capture.export.appearance import Appearance
    from reconstruct.metrics import relative_rms
    from capture.store import Store
    from capture.export.check import render_held_out
    demo_cwd, demo_run, _ = demo
    assert demo_run.returncode == 0, demo_run.stdout + demo_run.stderr
    store = demo_cwd / "demo" / "store"
    with Store.open(store, readonly=True) as st:
        sid = st.session("demo-quick").id
        runs = {r.kind: r for r in st.results(sid, "reconstruction")}
        app = Appearance.from_npz(st.read_object(runs["lensch"].artifacts["appearance.npz"]))
        bivariate = np.load(io.BytesIO(st.read_object(runs["passive"].artifacts["model.npz"])))["bivariate"]
    report = demo_cwd / "demo" / "report.html"
    res = CliRunner().invoke(cli, ["export", "demo-quick", "--store", str(store), "--method", "lensch",
                                   "--format", "mitsuba", "--out", str(tmp_path / "lensch")])
    assert res.exit_code == 0, res.output
    stated = json.loads((tmp_path / "lensch" / "model.json").read_text())["approximation"]
    # gonio demo's report beside the store now links the export's page (relative to the report's
    # folder), with its stated error; the page shows Mitsuba's render of the first held-out capture
    text = report.read_text()
    (href,) = re.findall(r'<a href="([^"]*)">', text.split("<h2>6. Exports</h2>")[1])
    assert (report.parent / href).resolve() == (tmp_path / "lensch" / "report.html").resolve()
    assert f"<td>lensch</td><td>mitsuba</td><td>{stated['export_vs_method_held_out_rel_rms']:.4g}</td>" in text
    page = (tmp_path / "lensch" / "report.html").read_text()
    assert page.count('<img src="data:image/png;base64,') == 1 and "mitsuba/heldout-000.xml" in page
    n_train = int(np.sum(~app.view_held_out))
    renders = [render_held_out(tmp_path / "lensch" / "mitsuba" / f"heldout-{k:03d}.xml", app, n_train + k)
               for k in range(int(app.view_held_out.sum()))]
    got, predicted, captured = (np.concatenate([getattr(r, k) for r in renders])
                                for k in ("rendered", "predicted", "captured"))
    assert len(got) > 0.9 * len(app.held_texel)
    assert relative_rms(got, predicted) < stated["export_vs_method_held_out_rel_rms"] + 0.03
    assert relative_rms(got, captured) < 1.2 * relative_rms(predicted, captured)
    # MERL: the passive table at MERL's nodes (read back by gonio's reader)
    res = CliRunner().invoke(cli, ["export", "demo-quick", "--store", str(store), "--method", "passive",
                                   "--format", "merl", "--out", str(tmp_path / "passive")])
    assert res.exit_code == 0, res.output
    from reconstruct.brdf import Bivariate
    from reconstruct.coords import from_halfway_difference
    from reconstruct.merl import read_merl
    merl = read_merl(tmp_path / "passive" / "brdf.binary")
    th, td, pd = (a.ravel()[::211] for a in np.meshgrid(*merl.node_angles(), indexing="ij"))
    wi, wo = from_halfway_difference(th, 0.0, td, pd)
    ok = (wi[:, 2] > 1e-3) & (wo[:, 2] > 1e-3)
    want = Bivariate(bivariate).evaluate(wi[ok], wo[ok])
    assert np.allclose(merl.table.reshape(-1, 3)[::211][ok], want, rtol=1e-9, atol=1e-12)
