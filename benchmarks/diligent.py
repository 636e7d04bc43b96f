"""DiLiGenT (real photographs, calibrated directional lights): normals and relighting per method.

    PYTHONPATH=. python benchmarks/diligent.py [--texels 5000] [--objects pot1,bear,goblet]
                                               [--ablation] [--rng 0] [--draws 1]

For each object of ``../shared/data/diligent`` (8-bit crops; every 4th light held out, as in
``gonio import diligent``) prints
1. the mean angular error of the normals (deg, against ``Normal_gt``) of least squares, the
   robust variant and Lensch normal fitting, on the same ``--texels`` random mask pixels, beside
   the published rows of the benchmark (L2, IA14, ST14, PS-FCN: the README's table, 16-bit data,
   all pixels; least squares on the whole mask is printed too);
2. held-out relighting: relative RMS of each model's prediction of the held-out lights
   (Lambertian with least-squares / robust normals and per-channel albedo; Lensch's per-texel
   BRDFs with its fitted normals);
3. Lensch's material count and the time per stage (read, photometric stereo, lumitexels, each
   Lensch stage, CPU), and Lensch's mean over the objects against ST14's.

``--ablation`` also runs Lensch the paper's way and one step at a time, to say what each step
buys: frames from least squares with every sample; from the robust normals; plus robust sample
selection; plus a second lobe; plus each texel's brightest 10 % of samples left out of normal
fitting (ST14's low-intensity part); plus robust selection within 1.5 instead of 3 sigma; plus
Tukey's biweight loss (cut off at 2 robust sigmas of each texel's residuals) in the normal fit;
plus each material's lobes alone in its projection basis; plus the peak test; plus the
Lafortune fits stopped where they crawl (round lensch7); the peak test at 1.5 with every
flagged texel held, an inter-reflection lobe about its free fit's normal and the per-texel undo
(round lensch8); that undo judged by Tukey's loss (3 robust sigmas) and only where the free
normal fits clearly better (round lensch9); in the last round each texel's samples below 0.1x
its median left out of the normal fit as cast shadows (round lensch10); after the normal fit a
diffuse term about each held texel's input normal (the final configuration, ``LENSCH_OPTIONS``;
round lensch11).
``--draws N`` repeats every figure on N draws of texels (rng RNG .. RNG+N-1), prints the tables
with each object's mean over the draws, then per object each draw's figures, their spread and
on how many draws Lensch relights ahead of the Lambertian reference, and the mean of the
per-object means against ST14's: goblet's normals move 0.5-1 deg from one draw to another.
Timings are wall-clock and CPU on whatever machine runs it.
"""
from __future__ import annotations

import argparse
import ast
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from capture.importers import read_diligent  # noqa: E402
from capture.pipeline.imported import LENSCH_OPTIONS, ImportedInputs  # noqa: E402
from reconstruct.lensch import SvbrdfOptions, fit_svbrdf_lumitexels  # noqa: E402
from reconstruct.metrics import relative_rms  # noqa: E402
from reconstruct.photometric_stereo import angular_error_deg  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "diligent"
#: Published mean angular errors (deg) from the benchmark's tables (16-bit originals, all pixels),
#: as listed in ``../shared/data/diligent/README.md``.
PUBLISHED = {"L2 (least squares)": {"pot1": 8.89, "bear": 8.39, "goblet": 18.50},
             "IA14": {"pot1": 6.64, "bear": 7.11, "goblet": 9.71},
             "ST14": {"pot1": 6.51, "bear": 6.12, "goblet": 10.09},
             "PS-FCN (learned)": {"pot1": 7.13, "bear": 7.55, "goblet": 8.60}}
LAMBERTIAN = "Lambertian, LS normals"   #: the relighting reference every Lensch fit must beat
FINAL_LABEL = "Lensch (final: LENSCH_OPTIONS)"
#: Lensch options of the final configuration (what ``gonio process`` runs on an imported set).
FINAL = {"frames_from": "robust", **LENSCH_OPTIONS}
_TUKEY = {"frames_from": "robust", "robust_samples": True, "n_lobes": 2, "robust_spread": 1.5,
          "brightest_dropped": 0.1, "tukey_cutoff": 2.0}
_TWO_LOBES = {"frames_from": "robust", "robust_samples": True, "n_lobes": 2}
ABLATION = {"paper (LS frames, all samples)": {"frames_from": "least_squares", "robust_samples": False,
                                               "n_lobes": 1},
            "+ robust frames": {"frames_from": "robust", "robust_samples": False, "n_lobes": 1},
            "+ robust samples": {"frames_from": "robust", "robust_samples": True, "n_lobes": 1},
            "+ second lobe": _TWO_LOBES,
            "+ brightest 10 % dropped": {**_TWO_LOBES, "brightest_dropped": 0.1},
            "+ samples within 1.5 sigma": {**_TWO_LOBES, "brightest_dropped": 0.1, "robust_spread": 1.5},
            "+ Tukey loss (2 sigma) in the normal fit": _TUKEY,
            "+ each material's lobes alone in the basis": {**_TUKEY, "lobes_alone": True},
            "+ the peak test (3x)": {**_TUKEY, "lobes_alone": True, "peak_ratio": 3.0},
            "+ Lafortune fits stopped where they crawl": {**_TUKEY, "lobes_alone": True, "peak_ratio": 3.0,
                                                          "lm_stall": (20, 1e-4)},
            "+ peak test 1.5, inter-reflection lobe, per-texel undo": {
                **FINAL, "undo_tukey": None, "undo_margin": 1.0, "shadow_ratio": None, "interreflection_diffuse": False},
            "+ the undo by Tukey's loss, free normal clearly better": {**FINAL, "shadow_ratio": None,
                                                                      "interreflection_diffuse": False},
            "+ dark samples out of the last round's normal fit": {**FINAL, "interreflection_diffuse": False},
            "+ a diffuse term about the held texels' input normals (final)": FINAL}


def run_lensch(inp: ImportedInputs, options: dict, rng: int = 0):
    stages, t0, c0 = [], time.perf_counter(), time.process_time()
    settings = SvbrdfOptions(fit_normals=True, **{k: v for k, v in options.items() if k != "frames_from"})
    fit = fit_svbrdf_lumitexels(inp.train, settings, rng=rng,
                                progress=lambda d, n: stages.append(time.process_time() - c0))
    cpu = time.process_time() - c0
    held = inp.held
    use = held.weight > 0
    pred = fit.predict(held.texel, held.wi, held.wo)
    rel = relative_rms(pred[use], held.reflectance[use])
    return fit, time.perf_counter() - t0, cpu, np.diff([0.0, *stages]), rel


def measure_draw(obj: str, data, texels: int, rng: int, configs: dict, ablation: bool):
    """One draw of ``texels`` mask pixels of one object: the normals error (deg) and the held-out
    relative RMS of every method, keyed by method, printing each Lensch fit as it ends."""
    per_frames, t = {}, time.perf_counter()
    for frames_from in sorted({c["frames_from"] for c in configs.values()}):
        per_frames[frames_from] = ImportedInputs(data, max_texels=texels, rng=rng, frames_from=frames_from)
    t_inputs = time.perf_counter() - t
    inp = per_frames["robust" if "robust" in per_frames else "least_squares"]
    rows = {"least squares, whole mask":
            angular_error_deg(inp.ls.normals[data.mask], data.normals_gt[data.mask]).mean(),
            "least squares": inp.normal_errors(inp.normals_ls),
            "robust least squares": inp.normal_errors(inp.normals_robust)}
    relight = {LAMBERTIAN: inp.lambertian_relighting(inp.ls),
               "Lambertian, robust normals": inp.lambertian_relighting(inp.robust)}
    print(f"\n== {obj}, rng {rng}: {inp.train.n_texels} texels, {inp.train.n_samples / inp.train.n_texels:.1f} "
          f"training samples per texel; photometric stereo + lumitexels {t_inputs:.1f} s ==", flush=True)
    for name, opts in configs.items():
        fit, secs, cpu, stage_s, rel = run_lensch(per_frames[opts["frames_from"]], opts, rng)
        label = name if ablation else FINAL_LABEL
        rows[label], relight[label] = inp.normal_errors(fit.normals), rel
        print(f"  {label}: {fit.n_materials} material(s), normals "
              f"{rows[label]:.2f} deg, held-out rel. RMS {rel:.4f}, {secs:.1f} s wall, {cpu:.1f} s CPU "
              f"(stages' CPU: {', '.join(f'{s:.1f}' for s in stage_s)} s; clustering first)", flush=True)
        for line in fit.history:
            if line.startswith("normal-fitting"):
                print(f"    {line}", flush=True)
    return rows, relight


def _table(title: str, per: dict[str, dict[str, float]], objects: list[str], fmt: str) -> None:
    print(f"\n== {title} ==")
    print(f"{'method':40s}" + "".join(f"{o:>9s}" for o in objects) + f"{'mean':>9s}")
    for name, r in per.items():
        vals = [r.get(o, np.nan) for o in objects]
        print(f"{name:40s}" + "".join(f"{v:9{fmt}}" for v in vals) + f"{np.nanmean(vals):9{fmt}}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--texels", type=int, default=5000)
    ap.add_argument("--objects", default="pot1,bear,goblet")
    ap.add_argument("--ablation", action="store_true")
    ap.add_argument("--rng", type=int, default=0, help="the draw of texels (the first, with --draws)")
    ap.add_argument("--draws", type=int, default=1,
                    help="draws of texels, rng RNG .. RNG+DRAWS-1: each object's figures are averaged over them")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="an SvbrdfOptions setting over the final configuration (a Python literal), "
                         "e.g. --set peak_ratio=1.5 --set lobes_alone=True")
    a = ap.parse_args(argv)
    if a.draws < 1:
        ap.error(f"--draws must be >= 1, got {a.draws}")
    final = {**FINAL}
    for item in a.set:
        name, _, value = item.partition("=")
        final[name] = ast.literal_eval(value)
    if not DATA.is_dir():
        sys.exit(f"{DATA} is absent (it ships beside the repository)")
    objects = [o for o in a.objects.split(",") if o]
    draws = list(range(a.rng, a.rng + a.draws))
    # per method, per object: one figure per draw
    rows: dict[str, dict[str, list[float]]] = {}
    relight: dict[str, dict[str, list[float]]] = {}
    configs = ABLATION if a.ablation else {"lensch": final}
    for obj in objects:
        t = time.perf_counter()
        data = read_diligent(DATA / obj)
        print(f"\n== {obj}: read {time.perf_counter() - t:.1f} s ==", flush=True)
        for rng in draws:
            r, rel = measure_draw(obj, data, a.texels, rng, configs, a.ablation)
            for name, v in r.items():
                rows.setdefault(name, {}).setdefault(obj, []).append(v)
            for name, v in rel.items():
                relight.setdefault(name, {}).setdefault(obj, []).append(v)
    mean = {name: {o: float(np.mean(v)) for o, v in r.items()} for name, r in rows.items()}
    on = f"rng {draws[0]}" if len(draws) == 1 else f"the mean of rng {draws[0]}-{draws[-1]}"
    _table(f"mean angular error of the normals (deg), {on}; published rows: 16-bit, all pixels",
           {**mean, **{f"published {k}": v for k, v in PUBLISHED.items()}}, objects, ".2f")
    st14 = np.mean([PUBLISHED["ST14"][o] for o in objects])
    lensch = [name for name in rows if name == FINAL_LABEL or name in ABLATION]
    for name in lensch:
        m = np.mean([mean[name][o] for o in objects])
        print(f"{name}: mean {m:.2f} deg over {', '.join(objects)} ({on}) against ST14's {st14:.2f} "
              f"({'beats' if m < st14 else 'does not reach'} it; ST14 on 16-bit data, all pixels)")
    _table(f"held-out lights (every 4th): relative RMS of the predicted reflectance, {on}",
           {name: {o: float(np.mean(v)) for o, v in r.items()} for name, r in relight.items()}, objects, ".4f")
    if len(draws) > 1:
        print(f"\n== per draw (rng {', '.join(map(str, draws))}): normals (deg) / held-out rel. RMS; "
              f"spread = max - min over the draws ==")
        for name in lensch:
            for o in objects:
                n, rl, ref = rows[name][o], relight[name][o], relight[LAMBERTIAN][o]
                ahead = sum(x < y for x, y in zip(rl, ref))
                print(f"{name} {o:>7s}: normals " + " / ".join(f"{v:.2f}" for v in n)
                      + f" (mean {np.mean(n):.2f}, spread {np.ptp(n):.2f}); relighting "
                      + " / ".join(f"{v:.4f}" for v in rl) + f" against {LAMBERTIAN} "
                      + " / ".join(f"{v:.4f}" for v in ref) + f": ahead on {ahead} of {len(draws)}")
            per_draw = [np.mean([rows[name][o][k] for o in objects]) for k in range(len(draws))]
            print(f"{name}: the {len(objects)}-object mean per draw " + " / ".join(f"{v:.2f}" for v in per_draw)
                  + f"; the mean of the per-object means {np.mean(per_draw):.3f} deg against ST14's {st14:.2f}")


if __name__ == "__main__":
    main()
