"""Streaming and Dask: the same lumitexels from every executor, resumed runs and killed workers;
time and peak memory against today's in-memory inputs.

    python benchmarks/scale.py --store /tmp/demo/store        # a `gonio demo --quick --out /tmp/demo` store
    python benchmarks/scale.py --store ... --only scheduler    # one part

Parts (each prints its figures):

- ``memory``: peak RSS (a fresh process each) of today's in-memory route (every view merged,
  then :func:`reconstruct.lumitexels.assemble_lumitexels`, Lambertian and Lensch on the gathered
  lumitexels) against the streamed one under ``--memory-limit`` MiB followed by the block
  methods over the stored blocks (Lambertian, Lensch with its discovery subsample sized by the
  limit, both scored block by block), with time;
- ``process_memory``: peak RSS of ``gonio process --methods lambertian,lensch --memory-limit``
  next to the limit (where the gathered lumitexels would exceed it, ``gonio process`` runs over
  texel blocks: the pictures from one view's samples, the export on a subsample of texels); on
  the quick demo or an :func:`upscale`d store (its stored calibration kept: the frame digest of
  its closing record updated);
- ``growth``: the streamed route (lumitexels, Lambertian, Lensch) at 1x, 4x and 16x pixels
  (:func:`upscale`): time per stage, peak RSS and the growth exponents against the texel count;
- ``today``: ``gonio process --methods lambertian,lensch`` with the base commit's code against
  this branch's, alternated (needs ``git archive BASE | tar -x -C /tmp/gonio_today``, or
  ``$SCALE_TODAY``);
- ``executors``: the streamed lumitexels in-process, on 1 and on 2 local workers: stored
  ``samples`` array and gathered lumitexels compared bit for bit with the in-memory route's;
  time with 1 and 2 workers (ratio);
- ``method_workers``: ``gonio process --methods lambertian,lensch`` in-process, with
  ``--workers 1`` and ``--workers 2`` (the methods' per-block tasks on the cluster): time, the
  1-vs-2 ratio, and the figures against in-process (1e-9 relative);
- ``resume``: a streamed run SIGKILLed after a third of its views, then run again: the views
  reused and the result compared;
- ``resume_methods``: ``gonio process --methods lensch`` beyond ``--memory-limit`` SIGKILLed mid-Lensch
  and run again: the block tasks the re-run computed, and its figures, ``model.npz`` and stored
  per-block results against an uninterrupted run's (:mod:`capture.pipeline.block_results`);
- ``kill_worker``: a 2-worker run in which one worker process is SIGKILLed mid-run;
- ``scheduler``: ``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1 over TCP,
  ``gonio process --scheduler`` on the session (lambertian), figures compared with in-process.

Timings are wall-clock on whatever machine runs it; on a shared, loaded machine they swing.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import resource
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import zarr

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from calibration.raw import read_raw  # noqa: E402
from capture.pipeline.calibration_record import RUN_KIND, frames_digest  # noqa: E402
from capture.pipeline.cluster import ClusterOptions, Executor  # noqa: E402
from capture.pipeline.block_scoring import score_blocks  # noqa: E402
from capture.pipeline.lumitexel_arrays import (block_texels_for, discovery_texels_for, method_texels_for,  # noqa: E402
                                              stream_lumitexels)
from capture.pipeline.methods import BlockRoute, fit_method  # noqa: E402
from capture.pipeline.stored_blocks import StoredBlocks  # noqa: E402
from capture.pipeline.run import process_session  # noqa: E402
from capture.pipeline.process import (lumitexels_with_held_out, read_calibration, session_images,  # noqa: E402
                                      session_inputs, view_plan)
from capture.lab_resolver import resolve_lab  # noqa: E402
from capture.store import Store  # noqa: E402
from sims.dng import write_dng  # noqa: E402

SESSION = "demo-quick"
#: rounds of the today part (each runs both codes once, alternated)
ROUNDS = int(os.environ.get("SCALE_ROUNDS", "2"))
#: the code the today part compares against (``git archive BASE | tar -x -C`` it)
TODAY = os.environ.get("SCALE_TODAY", "/tmp/gonio_today")
BLOCK = 4096


def _setup(store_path: str):
    store = Store(store_path, durable=False)
    lab = resolve_lab(store, SESSION)
    cal = read_calibration(store, SESSION, gray_card=lab.gray_card, probe_reflectance=lab.probe_reflectance)
    return store, lab.mesh, cal


def _same(a, b) -> bool:
    for x, y in zip(a, b):
        for f in fields(x):
            u, v = getattr(x, f.name), getattr(y, f.name)
            if not ((u is None and v is None) or (u.dtype == v.dtype and np.array_equal(u, v))):
                return False
    return True


def _stream(store, mesh, cal, workers: int, *, fresh: bool = True, on_start=None):
    if fresh:
        shutil.rmtree(Path(store.root) / "arrays", ignore_errors=True)
    images = session_images(store, SESSION)
    plan = view_plan(images, SESSION, cal, mesh=mesh)
    with Executor(ClusterOptions(workers=workers), store_root=store.root) as ex:
        if on_start is not None:
            on_start(ex)
        t = time.perf_counter()
        arrays = stream_lumitexels(images, SESSION, cal, plan, mesh, ex, block_texels=BLOCK)
        lt = arrays.gather()
        return lt, arrays, time.perf_counter() - t


def one(route: str, store_path: str, limit_mib: float) -> None:
    """Run one route in this (fresh) process and print its time and peak RSS as JSON: today's
    in-memory inputs and methods, or the streamed ones under ``limit_mib`` followed by the block
    methods (Lambertian, Lensch) over the stored blocks, scored block by block."""
    store, mesh, cal = _setup(store_path)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t = time.perf_counter()
    stages: dict[str, float] = {}
    figures = {}
    if route == "in_memory":
        train, held = lumitexels_with_held_out(mesh, session_inputs(store, SESSION, calibration=cal, mesh=mesh))
        texels, samples = train.n_texels, train.n_samples + held.n_samples
        stages["lumitexels"] = time.perf_counter() - t
        for name in ("lambertian", "lensch"):
            t1 = time.perf_counter()
            fit = fit_method(name, train, None)
            figures[name] = float(np.sqrt(np.sum((fit.predict(held) - held.reflectance) ** 2) / np.sum(held.reflectance ** 2)))
            stages[name] = time.perf_counter() - t1
    else:
        shutil.rmtree(Path(store.root) / "arrays", ignore_errors=True)
        images = session_images(store, SESSION)
        plan = view_plan(images, SESSION, cal, mesh=mesh)
        block = block_texels_for(int(limit_mib * 2**20), n_views=len(plan.poses),
                                 pixels=cal.camera.width * cal.camera.height)
        with Executor(ClusterOptions(), store_root=store.root) as ex:
            arrays = stream_lumitexels(images, SESSION, cal, plan, mesh, ex, block_texels=block)
        stages["lumitexels"] = time.perf_counter() - t
        method_block = method_texels_for(int(limit_mib * 2**20), arrays.n_train)
        blocks = StoredBlocks(arrays, method_block)
        here = BlockRoute(blocks, lambda fn, args: [fn(*a) for a in args])
        # the per-texel normals only (the samples come from the blocks)
        normals = _TexelsOnly(np.concatenate([arrays.block(t0, t1)[0].normal for t0, t1 in arrays.parts(method_block)]))
        texels, samples = blocks.n_texels, -1
        for name in ("lambertian", "lensch"):
            t1 = time.perf_counter()
            opts = {"discovery_texels": discovery_texels_for(int(limit_mib * 2**20), arrays.n_train)} if name == "lensch" else {}
            fit = fit_method(name, normals, None, route=here, **opts)
            figures[name] = score_blocks(fit.predict_samples, arrays, max_texels=method_block).held_out.relative_rms
            if name == "lensch":
                figures["lensch_discovery"] = fit.figures["material_discovery"]
            stages[name] = time.perf_counter() - t1
    dt = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"route": route, "seconds": dt, "peak_rss_mib": peak / 1024, "stages": stages,
                      "peak_above_setup_mib": (peak - base) / 1024, "texels": texels, "samples": samples,
                      "held_out_rel_rms": figures}))


class _TexelsOnly:
    """What the block methods read of the training lumitexels when given a route: the per-texel
    normals (the samples come from the blocks)."""

    def __init__(self, normal: np.ndarray) -> None:
        self.normal = normal


def _one(route: str, store_path: str, limit_mib: float) -> dict:
    """:func:`one` in a fresh process (so its peak RSS is its own)."""
    out = subprocess.run([sys.executable, __file__, "--store", store_path, "--one", route,
                          "--memory-limit", str(limit_mib)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def memory(store_path: str, limit_mib: float) -> None:
    for route in ("in_memory", "streamed"):
        r = _one(route, store_path, limit_mib)
        print(f"memory  {route:10s} {r['seconds']:6.1f} s  peak RSS {r['peak_rss_mib']:7.0f} MiB "
              f"({r['peak_above_setup_mib']:6.0f} MiB above the set-up: imports, store, calibration)"
              + (f"  limit {limit_mib:.0f} MiB" if route == "streamed" else "") + f"  {r['texels']} texels  "
              f"stages {json.dumps({k: round(v, 1) for k, v in r['stages'].items()})}  held-out {r['held_out_rel_rms']}")


def _process(store_path: str, args: list[str], code: str = str(ROOT)) -> tuple[dict, float, float, float]:
    """``gonio process SESSION ARGS --json`` on a scratch copy without reconstructions: the summary,
    wall seconds, CPU seconds (user + sys) and the child's peak RSS (MiB)."""
    scratch = _without_reconstructions(store_path)
    env = {**os.environ, "PYTHONPATH": code}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    # run from the code's folder: ``python -m`` puts the working directory before PYTHONPATH
    r = subprocess.run([sys.executable, "-m", "capture.cli", "process", SESSION, "--store", scratch, "--json", "-q",
                        *args], env=env, capture_output=True, text=True, cwd=code)
    dt = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    shutil.rmtree(scratch, ignore_errors=True)
    if r.returncode != 0:
        raise RuntimeError(f"gonio process {' '.join(args)} exited {r.returncode}: {r.stderr[-2000:]}")
    cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
    return json.loads(r.stdout[r.stdout.index("{"):]), dt, cpu, after.ru_maxrss / 1024


def setup_rss(store_path: str) -> None:
    """Print, as JSON, the peak RSS (MiB) of ``gonio process``'s set-up alone: its imports, the
    store, the lab and the calibration read (what no memory limit covers)."""
    _setup(store_path)
    print(json.dumps({"setup_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "imports": process_session.__module__}))


def process_memory(store_path: str, limit_mib: float) -> None:
    r = subprocess.run([sys.executable, __file__, "--store", store_path, "--one", "setup"], capture_output=True,
                       text=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=ROOT, check=True)
    setup = json.loads(r.stdout[r.stdout.index("{"):])["setup_mib"]
    summary, dt, cpu, peak = _process(store_path, ["--methods", "lambertian,lensch", "--memory-limit", str(limit_mib)])
    held = {m["method"]: m["figures"].get("held_out_rel_rms") for m in summary["methods"]}
    found = {m["method"]: m["figures"].get("material_discovery") for m in summary["methods"] if m["method"] == "lensch"}
    print(f"process_memory  gonio process --methods lambertian,lensch --memory-limit {limit_mib:.0f}: {dt:.1f} s "
          f"(CPU {cpu:.1f} s)  peak RSS {peak:.0f} MiB, {peak - setup:.0f} above the set-up's {setup:.0f} "
          f"(limit {limit_mib:.0f} MiB)  texels {summary['inputs']['texels']}  "
          f"over blocks: {summary['inputs'].get('over_blocks', 'no (gathered)')}  {found}  "
          f"held-out {held}  stages {summary['timings']}")


def method_workers(store_path: str) -> None:
    """The methods' per-block tasks in-process, on 1 and on 2 local workers (ratio), and their figures."""
    runs = {}
    for w in (0, 1, 2):
        summary, dt, _, _ = _process(store_path, ["--methods", "lambertian,lensch", "--workers", str(w)])
        runs[w] = (summary, dt)
        print(f"method_workers  {'in-process' if w == 0 else f'{w} worker(s)':11s} {dt:6.1f} s  stages {summary['timings']}")
    figs = {w: {m["method"]: m["figures"] for m in s["methods"]} for w, (s, _) in runs.items()}

    def close(a, b) -> bool:
        if isinstance(a, dict):
            return a.keys() == b.keys() and all(close(a[k], b[k]) for k in a)
        if isinstance(a, float) and isinstance(b, float):
            return abs(a - b) <= 1e-9 * max(abs(a), abs(b), 1e-300)
        return a == b
    print(f"method_workers  1 vs 2 workers: time ratio {runs[1][1] / runs[2][1]:.2f}; figures equal in-process's to "
          f"1e-9: 1 worker {close(figs[0], figs[1])}, 2 workers {close(figs[0], figs[2])}")


def growth(store_path: str, limit_mib: float) -> None:
    """The streamed route (assembly, then the block methods) on the session enlarged 1, 2 and
    4 times a side (1x, 4x and 16x pixels and texels; :func:`upscale`): time per stage and peak
    RSS in a fresh process each, and the growth exponent b of cost ~ texels^b (least squares in
    log-log)."""
    rows = []
    for f in (1, 2, 4):
        path = store_path
        if f > 1:
            path = str(Path(store_path).resolve().parent / f"scale-growth-{f}")
            upscale(store_path, f, path)
        r = _one("streamed", path, limit_mib)
        rows.append(r)
        print(f"growth  {f}x{f}  {r['texels']:8d} texels  {r['seconds']:7.1f} s  (lumitexels "
              f"{r['stages']['lumitexels']:.1f} s, lambertian {r['stages']['lambertian']:.2f} s, lensch "
              f"{r['stages']['lensch']:.1f} s)  peak RSS "
              f"{r['peak_rss_mib']:6.0f} MiB ({r['peak_above_setup_mib']:5.0f} above the set-up)  limit {limit_mib:.0f} MiB")
        if f > 1:
            shutil.rmtree(path, ignore_errors=True)
    x = np.log([r["texels"] for r in rows])
    for what, ys in (("time", [r["seconds"] for r in rows]),
                     ("lumitexels time", [r["stages"]["lumitexels"] for r in rows]),
                     ("Lensch time", [r["stages"]["lensch"] for r in rows]),
                     ("peak above the set-up", [max(r["peak_above_setup_mib"], 1.0) for r in rows])):
        print(f"growth  exponent of {what} against texels: {np.polyfit(x, np.log(ys), 1)[0]:.2f}")


def today(store_path: str, limit_mib: float) -> None:
    """``gonio process --methods lambertian,lensch`` with today's code (unpacked by ``git archive
    BASE`` into ``$SCALE_TODAY``, default /tmp/gonio_today) and this branch's, alternated on
    scratch copies of the store: wall time, CPU time (the fairer figure on a shared machine), the
    stage timings it reports and the held-out figures."""
    for rnd in range(ROUNDS):
        for name, code in (("today", TODAY), ("branch", str(ROOT))):
            summary, dt, cpu, _ = _process(store_path, ["--methods", "lambertian,lensch"], code)
            held = {m["method"]: m["figures"].get("held_out_rel_rms") for m in summary["methods"]}
            print(f"today  round {rnd}  {name:8s} wall {dt:6.1f} s  CPU (user + sys) {cpu:6.1f} s  "
                  f"stages {summary['timings']}  held-out rel. RMS {held}")


def executors(store_path: str) -> None:
    store, mesh, cal = _setup(store_path)
    t = time.perf_counter()
    ref = lumitexels_with_held_out(mesh, session_inputs(store, SESSION, calibration=cal, mesh=mesh))
    print(f"executors in-memory route {time.perf_counter() - t:6.1f} s")
    samples = None
    for w in (0, 1, 2):
        lt, arrays, dt = _stream(store, mesh, cal, w)
        s = zarr.open_array(str(arrays.path / "samples"), mode="r")[...]
        same_store = samples is None or np.array_equal(s, samples)
        samples = s if samples is None else samples
        print(f"executors {'in-process' if w == 0 else f'{w} worker(s)':11s} {dt:6.1f} s  lumitexels identical to "
              f"the in-memory route: {_same(lt, ref)}  stored samples identical to in-process: {same_store}")


def resume(store_path: str) -> None:
    store, mesh, cal = _setup(store_path)
    ref, arrays, _ = _stream(store, mesh, cal, 0)
    shutil.rmtree(Path(store.root) / "arrays")
    proc = subprocess.Popen([sys.executable, __file__, "--store", store_path, "--one", "streamed_keep"])
    done = arrays.path / "done"
    target = arrays.n_views + arrays.n_views // 3
    while proc.poll() is None and (not done.is_dir() or len(list(done.glob("*-*"))) < target):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    marks = len(list(done.glob("samples-*")))
    lt, arrays2, dt = _stream(store, mesh, cal, 0, fresh=False)
    print(f"resume  killed with {marks}/{arrays.n_views} views sampled; the re-run reused {arrays2.reused_views} "
          f"and took {dt:.1f} s; identical to an uninterrupted run: {_same(lt, ref)}")


def _method_run(store: str, args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "capture.cli", "process", SESSION, "--store", store, "--json", "-q",
                             *args], env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)


def _stored_model(store: str, method: str) -> dict[str, np.ndarray]:
    s = Store(store, durable=False)
    rec = next(r for r in s.results(s.session(SESSION).id, "reconstruction") if r.kind == method)
    with np.load(io.BytesIO(s.read_object(rec.artifacts["model.npz"]))) as z:
        return {k: z[k] for k in z.files}


def resume_methods(store_path: str, limit_mib: float) -> None:
    """``gonio process --methods lensch --memory-limit`` (over blocks, each block task's result
    stored in ``block_results.zarr``) SIGKILLed once a third of an uninterrupted run's block
    tasks are stored, then run again: the tasks it computed, and its figures, ``model.npz`` and
    stored block arrays against the uninterrupted run's."""
    args = ["--methods", "lensch", "--memory-limit", str(limit_mib)]
    runs = {}
    for how in ("whole", "killed"):
        copy = _without_reconstructions(store_path)
        scratch = f"{copy}-{how}"
        shutil.rmtree(scratch, ignore_errors=True)
        os.rename(copy, scratch)
        done = Path(scratch) / "arrays" / SESSION / "block_results.zarr" / "done"
        t = time.perf_counter()
        proc = _method_run(scratch, args)
        if how == "killed":
            while proc.poll() is None and len(list(done.glob("[0-9a-f]*"))) < runs["whole"]["tasks"] // 3:
                time.sleep(0.02)
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            killed_at = len(list(done.glob("[0-9a-f]*")))
            proc = _method_run(scratch, args)
        out, _ = proc.communicate()
        summary = json.loads(out[out.index("{"):])
        runs[how] = {"figures": summary["methods"][0]["figures"], "model": _stored_model(scratch, "lensch"),
                     "tasks": len(list(done.glob("[0-9a-f]*"))), "dt": time.perf_counter() - t,
                     "blocks": zarr.open_group(str(done.parent), mode="r"), "path": scratch}
    whole, again = runs["whole"], runs["killed"]
    same_model = whole["model"].keys() == again["model"].keys() and all(
        np.array_equal(whole["model"][k], again["model"][k]) for k in whole["model"])
    same_blocks = sorted(whole["blocks"].group_keys()) == sorted(again["blocks"].group_keys()) and all(
        np.array_equal(a[...], again["blocks"][key][name][...])
        for key, g in whole["blocks"].groups() for name, a in g.arrays())
    print(f"resume_methods  SIGKILLed with {killed_at} of {whole['tasks']} block tasks stored; the re-run computed "
          f"{again['tasks'] - killed_at} ({whole['dt']:.1f} s uninterrupted, {again['dt']:.1f} s killed + resumed); "
          f"figures identical: {whole['figures'] == again['figures']} (held-out {again['figures'].get('held_out_rel_rms')}), "
          f"model.npz identical: {same_model}, stored block arrays identical: {same_blocks}")
    for r in runs.values():
        shutil.rmtree(r["path"], ignore_errors=True)


def kill_worker(store_path: str) -> None:
    store, mesh, cal = _setup(store_path)
    ref, _, _ = _stream(store, mesh, cal, 0)
    killed = {}

    def arm(ex: Executor) -> None:
        pids = ex.client.run(os.getpid)
        victim = sorted(pids.values())[0]

        def later():
            time.sleep(4.0)
            os.kill(victim, signal.SIGKILL)
            killed["pid"] = victim
        threading.Thread(target=later, daemon=True).start()

    lt, _, dt = _stream(store, mesh, cal, 2, on_start=arm)
    print(f"kill_worker  worker pid {killed.get('pid')} SIGKILLed 4 s into a 2-worker run ({dt:.1f} s): "
          f"run completed, identical: {_same(lt, ref)}")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _without_reconstructions(store_path: str) -> str:
    """A scratch copy of the store without its reconstruction results (so ``gonio process``
    runs the methods again but keeps the stored calibration)."""
    dest = Path(store_path).resolve().parent / f"scale-scratch-{os.getpid()}"
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(store_path, dest, ignore=shutil.ignore_patterns("arrays"))
    with sqlite3.connect(dest / "gonio.sqlite") as db:
        db.execute("DELETE FROM result_objects WHERE result_id IN (SELECT id FROM results WHERE category = 'reconstruction')")
        db.execute("DELETE FROM results WHERE category = 'reconstruction'")
    return str(dest)


def _enlarge(mosaic: np.ndarray, f: int) -> np.ndarray:
    """A Bayer mosaic with each 2 x 2 colour tile repeated f x f times (the pattern kept)."""
    H, W = mosaic.shape
    tiles = mosaic.reshape(H // 2, 2, W // 2, 2).transpose(0, 2, 1, 3)
    tiles = tiles.repeat(f, axis=0).repeat(f, axis=1)
    return np.ascontiguousarray(tiles.transpose(0, 2, 1, 3).reshape(H * f, W * f))


def upscale(store_path: str, f: int, dest: str) -> None:
    """A synthesised large session: the quick demo's with every measurement and passive frame and
    the master darks enlarged f x f (each Bayer tile repeated, so the merge, demosaic and
    sampling run on f^2 times the pixels), the intrinsics scaled to match (same field of view).
    Not a re-rendered scene: the figures of its fits are not the point, its time and memory are."""
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(store_path, dest, ignore=shutil.ignore_patterns("arrays"))
    store = Store(dest, durable=False)
    sid = store.session(SESSION).id
    kinds = {s.index: s.step.kind for s in store.steps(sid)}
    with sqlite3.connect(Path(dest) / "gonio.sqlite") as db:
        for fr in store.frames(sid):
            if kinds.get(fr.step) not in ("measure", "passive"):
                continue
            raw = read_raw(store.read_object(fr.sha256))
            blob = write_dng(_enlarge(raw.data, f), cfa_pattern=raw.cfa,
                             black_level=tuple(int(round(v)) for v in raw.black_level_cfa.ravel()),
                             white_level=int(raw.white_level), exposure_s=raw.exposure_s, iso=raw.iso)
            sha = store.put_object(blob)
            db.execute("UPDATE frames SET sha256 = ?, size = ? WHERE id = ?", (sha, len(blob), fr.id))
        for rid, name, old in db.execute("SELECT result_id, name, sha256 FROM result_objects WHERE result_id IN "
                                         "(SELECT id FROM results WHERE kind = 'dark')").fetchall():
            dark = np.load(store.object_path(old))
            buf = io.BytesIO()
            np.save(buf, _enlarge(dark, f))
            sha = store.put_object(buf.getvalue())
            db.execute("UPDATE result_objects SET sha256 = ?, size = ? WHERE result_id = ? AND name = ?",
                       (sha, len(buf.getvalue()), rid, name))
        # every stored intrinsics (a re-calibrated session holds several; the newest is read)
        for rid, text in db.execute("SELECT id, result_json FROM results WHERE kind = 'intrinsics'").fetchall():
            r = json.loads(text)
            K = np.array(r["K"])
            K[0, 0] *= f
            K[1, 1] *= f
            K[:2, 2] = f * (K[:2, 2] + 0.5) - 0.5   # pixel centres: the enlarged pixel grid's
            r["K"], r["image_size"] = K.tolist(), [f * v for v in r["image_size"]]
            db.execute("UPDATE results SET result_json = ? WHERE id = ?", (json.dumps(r), rid))
    # the stored calibration stays valid for the enlarged frames (darks and intrinsics enlarged
    # with them; the rest is in mm, degrees and DN): its closing record names the new frames, so
    # gonio process reuses it instead of recalibrating from frames that were not enlarged
    digest = frames_digest(store, sid)
    with sqlite3.connect(Path(dest) / "gonio.sqlite") as db:
        for rid, text in db.execute("SELECT id, result_json FROM results WHERE kind = ?", (RUN_KIND,)).fetchall():
            run = json.loads(text)
            run["frames_digest"] = digest
            db.execute("UPDATE results SET result_json = ? WHERE id = ?", (json.dumps(run), rid))
    store.close()
    print(f"upscale  {dest}: measurement and passive frames and darks enlarged {f} x {f}, "
          f"{r['image_size'][0]} x {r['image_size'][1]}; the stored calibration kept (its frame digest updated)")


def scheduler(store_path: str) -> None:
    port = _free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    procs = [subprocess.Popen(["dask", "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--dashboard-address", "127.0.0.1:0"], env=env, stderr=subprocess.DEVNULL)]
    addr = f"tcp://127.0.0.1:{port}"
    try:
        time.sleep(3)
        procs += [subprocess.Popen(["dask", "worker", addr, "--nthreads", "1", "--host", "127.0.0.1",
                                    "--dashboard-address", "127.0.0.1:0"], env=env, stderr=subprocess.DEVNULL)
                  for _ in range(2)]
        time.sleep(5)
        figures = {}
        for how in ("in-process", "scheduler"):
            scratch = _without_reconstructions(store_path)
            cmd = ["gonio", "process", SESSION, "--store", scratch, "--methods", "lambertian",
                   "--json", "-q"] + (["--scheduler", addr] if how == "scheduler" else [])
            t = time.perf_counter()
            r = subprocess.run(cmd, env=env, capture_output=True, text=True)
            dt = time.perf_counter() - t
            summary = json.loads(r.stdout[r.stdout.index("{"):])
            figures[how] = summary["methods"][0]["figures"]
            print(f"scheduler  {how:10s} exit {r.returncode}  {dt:6.1f} s  lambertian held-out rel. RMS "
                  f"{figures[how].get('held_out_rel_rms')}")
        print(f"scheduler  figures identical: {figures['in-process'] == figures['scheduler']}")
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait()


PARTS = {"memory": memory, "process_memory": process_memory, "growth": growth, "today": today, "executors": executors,
         "method_workers": method_workers, "resume": resume, "resume_methods": resume_methods, "kill_worker": kill_worker, "scheduler": scheduler}
#: the parts that take the memory limit
_LIMITED = {"memory", "process_memory", "growth", "today", "resume_methods"}

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True, help="a store holding the quick demo's session")
    ap.add_argument("--only", choices=sorted(PARTS), action="append")
    ap.add_argument("--memory-limit", type=float, default=64.0, help="MiB for the streamed route (memory part)")
    ap.add_argument("--upscale", type=int, metavar="F", help="only make a synthesised session F x F larger "
                    "(every Bayer tile repeated) at --dest")
    ap.add_argument("--dest", help="where --upscale writes its store")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.upscale:
        upscale(a.store, a.upscale, a.dest)
    elif a.one == "setup":
        setup_rss(a.store)
    elif a.one == "streamed_keep":   # the resume part's victim: a streamed run left to be killed
        s, m, c = _setup(a.store)
        _stream(s, m, c, 0, fresh=False)
    elif a.one:
        one(a.one, a.store, a.memory_limit)
    else:
        for name in a.only or PARTS:
            PARTS[name](a.store, a.memory_limit) if name in _LIMITED else PARTS[name](a.store)
