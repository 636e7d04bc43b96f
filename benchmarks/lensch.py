"""Lensch et al. 2003 reconstruction: accuracy and speed figures in one run.

    PYTHONPATH=. python benchmarks/lensch.py [--object-width 160] [--png lensch_normals.png]

Prints
1. the paper's synthetic experiment at its size (5 modified-Phong materials, ~46,000 samples,
   ~11 per texel, 5 views, +-5 % noise) on ``--seeds``: materials found without the count, kd / N
   errors, labelling accuracy, each next to a fit given the true assignment;
2. the bumpy multi-material object (rendered with sensor noise, smooth mesh to the fitter): the
   Table II columns, held-out frames, normal error before / after, and a PNG of the normal maps;
3. the material count on random material sets (``--count-sets``): 3-5 modified-Phong materials
   of random colour, specular albedo and exponent per set, 600 texels each at the paper's
   sampling, counted without being told, with the clustering's look-ahead and without it;
4. projection of 1,000,000 texels x 6 samples x 4 basis BRDFs, normal fitting of 100,000
   texels, and the speed-up over per-texel scipy.optimize loops measured on subsets.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.optimize import least_squares, nnls

from reconstruct.brdf import Lafortune
from reconstruct.frames import tangent_frames, to_local, to_world
from reconstruct.lensch import SvbrdfOptions, fit_svbrdf, fit_svbrdf_lumitexels
from reconstruct.lensch import clustering
from reconstruct.lensch.lafortune_fit import lobe_geometry, model_and_jacobian, params_of
from reconstruct.lensch.normals import _mixture, fit_normals_chunk
from reconstruct.lensch.projection import basis_values, make_bases, project_chunk
from reconstruct.lumitexels import assemble_lumitexels
from sims.objects import BUMPY_MATERIALS, make_object
from sims.reflectance_samples import (fit_true_assignment, paper_phong_materials, synthetic_samples,
                                      turntable_capture)

#: The paper's Table II (bird, bust, elk, angels): RMS per column, in the paper's units.
PAPER_TABLE2 = {"single": (.1513, .1025, .0768, .2953), "cluster": (.0627, .0839, .0556, .1163),
                "projection": (.0387, .0583, .0275, .1113), "pfa": (.0387, .0581, .0274, .1111),
                "normal_fit": (.0269, .0113, .0202, .0703)}


def paper_experiment(seeds):
    """Sec. 11 at the paper's size on each seed (data and fit): kd / N errors and labels against
    a fit given the true assignment (``sims.reflectance_samples.fit_true_assignment``)."""
    materials = paper_phong_materials()
    trueN = np.array([m.n[0] for m in materials])
    print("\n== paper's synthetic experiment: 4200 texels, ~11 samples per texel, 5 views, +-5 % noise "
          "(paper: kd, N within 0.2 %) ==")
    worst_all, gap_all = 0.0, -np.inf
    for seed in seeds:
        d = synthetic_samples(materials, 4200, rng=seed)
        t0 = time.process_time()
        fit = fit_svbrdf(d.texel, d.wi, d.wo, d.reflectance, SvbrdfOptions(noise="relative"), rng=seed)
        dt = time.process_time() - t0
        match = np.array([int(np.argmin(np.abs(trueN - np.asarray(m.n)[0].mean()))) for m in fit.materials])
        worst = 0.0
        for k, m in zip(match, fit.materials):
            e_kd = np.abs(np.asarray(m.rho_d) / np.asarray(materials[k].rho_d) - 1)
            e_n = np.abs(np.asarray(m.n)[0] / trueN[k] - 1)
            worst = max(worst, 100 * e_kd.max(), 100 * e_n.max())
        ref = fit_true_assignment(d)
        ref_worst = 100 * max(max(np.abs(p[:, 0] / np.asarray(materials[k].rho_d) - 1).max(),
                                  np.abs(p[:, 3] / trueN[k] - 1).max()) for k, p in enumerate(ref.params))
        acc = np.mean(match[fit.labels] == d.material) if len(set(match)) == 5 else np.nan
        acc_ref = np.mean(ref.labels == d.material)
        worst_all, gap_all = max(worst_all, worst), max(gap_all, 100 * (acc_ref - acc))
        print(f"  seed {seed}: {fit.n_materials} materials in {len(fit.materials)} clusters ({dt:.1f} s CPU), worst kd / N error "
              f"{worst:.3f} % (true assignment's fit {ref_worst:.3f} %), labels {100 * acc:.2f} % "
              f"(true assignment's fit {100 * acc_ref:.2f} %)", flush=True)
    print(f"  over the seeds: worst kd / N error {worst_all:.3f} %, labels at most {gap_all:.2f} points "
          "below the true assignment's fit")


def material_count(n_sets: int):
    """Random sets of 3-5 materials (set s drawn from seed 500 + s, its samples from seed s):
    the count found without being told, and the labels (each found material named by its
    majority), with ``clustering.LOOK_AHEAD`` as it is and at 0."""
    print(f"\n== material count on {n_sets} random sets of 3-5 materials (600 texels each, ~11 "
          "samples per texel, +-5 % noise) ==")
    levels = clustering.LOOK_AHEAD
    right = {levels: 0, 0: 0}
    for s in range(n_sets):
        r = np.random.default_rng(500 + s)
        k = int(r.integers(3, 6))
        materials = tuple(Lafortune.phong(rho_d=tuple(r.uniform(0.05, 0.6, 3)),
                                          rho_s=float(r.uniform(0.2, 1)),
                                          exponent=float(np.exp(r.uniform(np.log(8), np.log(150)))))
                          for _ in range(k))
        d = synthetic_samples(materials, 600 * k, rng=s)
        line = []
        for look in (levels, 0):
            clustering.LOOK_AHEAD = look
            try:
                t0 = time.process_time()
                fit = fit_svbrdf(d.texel, d.wi, d.wo, d.reflectance, SvbrdfOptions(noise="relative"), rng=s)
            finally:
                clustering.LOOK_AHEAD = levels
            label = fit.cluster_material[fit.labels]
            majority = np.array([np.argmax(np.bincount(d.material[label == m], minlength=k))
                                 for m in range(fit.n_materials)])
            right[look] += fit.n_materials == k
            line.append(f"look-ahead {look}: {fit.n_materials} found, labels "
                        f"{100 * np.mean(majority[label] == d.material):.1f} % "
                        f"({time.process_time() - t0:.1f} s CPU)")
        print(f"  set {s}: {k} materials; " + "; ".join(line), flush=True)
    print(f"  count right: {right[levels]} of {n_sets} with LOOK_AHEAD = {levels}, {right[0]} of "
          f"{n_sets} with 0 (no look-ahead)")


def bumpy_object(width: int, png: str | None):
    t0 = time.perf_counter()
    obj = make_object("bumpy")
    views, held = turntable_capture(obj, width=width, rng=0)
    lt = assemble_lumitexels(obj.fitter_mesh, views + held)
    t_lt = time.perf_counter() - t0
    ho = lt.view >= len(views)
    lt.weight = np.where(ho, 0.0, 1.0).astype(np.float32)
    t0 = time.perf_counter()
    fit = fit_svbrdf_lumitexels(lt, SvbrdfOptions(fit_normals=True, pfa=True), rng=0)
    dt = time.perf_counter() - t0
    print(f"\n== bumpy object: {len(views)} frames {width} x {width * 3 // 4} (+{len(held)} held out), "
          f"{lt.n_texels} texels, {int((~ho).sum())} samples; render + lumitexels {t_lt:.0f} s, "
          f"fit {dt:.0f} s ==")
    print(fit.report())
    print("  Table II (relative RMS here; paper's RMS for bird / bust / elk / angels):")
    for k, v in fit.relative_rms.items():
        print(f"    {k:11s} {v:.4f}   paper {PAPER_TABLE2[k]}")
    truth = obj.material_at(lt.position)
    for k, true in enumerate(BUMPY_MATERIALS):
        main = np.bincount(fit.labels[truth == k]).argmax()
        m = fit.materials[main]
        own = fit.cluster_material[main]
        print(f"  material {k}: {100 * np.mean(fit.labels[truth == k] == main):.1f} % of its texels in "
              f"cluster {main}, {100 * np.mean(fit.cluster_material[fit.labels[truth == k]] == own):.1f} % "
              f"in its material {own}: rho_d {np.round(m.rho_d, 3)} (true {np.round(true.rho_d, 3)}), "
              f"N {np.round(np.asarray(m.n)[0], 1)} (true {np.ravel(true.n)[0]})")
    tx, r = lt.texel[ho], lt.reflectance[ho]
    wi, wo = lt.wi[ho], lt.wo[ho]
    cl = np.zeros_like(r)  # baseline: each texel's cluster BRDF on the mesh normal
    for k, m in enumerate(fit.materials):
        s = fit.labels[tx] == k
        cl[s] = m.evaluate(wi[s], wo[s]) * wi[s, 2:3]
    true_n = obj.normal_at(lt.position)
    oracle = np.zeros_like(r)  # the true BRDFs on the true normals: the floor point rendering sets
    frames = tangent_frames(true_n[tx])
    mesh = tangent_frames(lt.normal[tx])
    wi_t, wo_t = to_local(to_world(wi, mesh), frames), to_local(to_world(wo, mesh), frames)
    for k, m in enumerate(BUMPY_MATERIALS):
        s = truth[tx] == k
        oracle[s] = m.evaluate(wi_t[s], wo_t[s]) * np.maximum(wi_t[s, 2:3], 0.0)
    print("  held-out frames (relative RMS pooled / median sample error / p90 / RMS without the worst 1 %):")
    for name, p in (("full fit (projection + normals)", fit.predict(tx, wi, wo)),
                    ("cluster BRDFs on mesh normals", cl), ("true BRDFs on true normals", oracle)):
        print(f"    {name:32s} {_held_out_errors(p, r)}")

    def ang(a, b):
        return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))
    before, after = ang(lt.normal, true_n), ang(fit.normals, true_n)
    print(f"  normals vs truth: mean {before.mean():.2f} -> {after.mean():.2f} deg, "
          f"on bumps (> 5 deg) {before[before > 5].mean():.2f} -> {after[before > 5].mean():.2f} deg")
    if png:
        _normal_png(png, lt, true_n, fit.normals, views[0].camera)


def _held_out_errors(pred, r) -> str:
    """Pooled relative RMS, median / 90th percentile of the per-sample relative error, and the
    pooled RMS without the worst 1 % of samples (the pooled figure is a handful of highlights)."""
    sq = np.sum((pred - r) ** 2, axis=1)
    rel = np.sqrt(sq) / np.linalg.norm(r, axis=1)
    kept = np.sort(sq)[:int(0.99 * len(sq))].sum()
    return (f"{np.sqrt(sq.sum() / np.sum(r ** 2)):.3f} / {100 * np.median(rel):.2f} % / "
            f"{100 * np.percentile(rel, 90):.1f} % / {np.sqrt(kept / np.sum(r ** 2)):.4f}")


def _normal_png(path, lt, true_n, fitted, camera):
    """The relief the mesh lacks, for the texels made in view 0: each normal's tilt from the mesh
    normal (its x, y in the texel's local frame, x 4, as red / green), true and fitted, and the
    angular error left after fitting."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    sel = lt.best_view == 0
    px = np.round(lt.pixel[sel]).astype(int)
    frames = tangent_frames(lt.normal[sel])

    def relief(n):
        local = to_local(n[sel], frames)
        img = np.ones((camera.height, camera.width, 3))
        img[px[:, 1], px[:, 0]] = np.clip(np.stack([0.5 + 4 * local[:, 0], 0.5 + 4 * local[:, 1],
                                                    np.full(len(local), 0.5)], 1), 0, 1)
        return img
    err = np.full((camera.height, camera.width), np.nan)
    err[px[:, 1], px[:, 0]] = np.degrees(np.arccos(np.clip(np.sum(fitted[sel] * true_n[sel], 1), -1, 1)))
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8))
    axes[0].imshow(relief(true_n))
    axes[0].set_title("true relief (tilt from the mesh normal)")
    axes[1].imshow(relief(fitted))
    axes[1].set_title("fitted normals (Sec. 9)")
    im = axes[2].imshow(err, cmap="magma", vmin=0, vmax=8)
    axes[2].set_title("angle fitted vs true (deg)")
    fig.colorbar(im, ax=axes[2], fraction=0.04)
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"  normal maps: {path}")


def _random_samples(rng, n_texels, per_texel):
    """Texel ids (S,) and random upper-hemisphere wi, wo (S, 3) for ``per_texel`` samples each."""
    texel = np.repeat(np.arange(n_texels), per_texel)
    v = rng.normal(size=(2, len(texel), 3))
    v[..., 2] = np.abs(v[..., 2]) + 0.2
    v /= np.linalg.norm(v, axis=2, keepdims=True)
    return texel, v[0], v[1]


def speed(n_proj: int, n_normals: int):
    rng = np.random.default_rng(0)
    mats = np.stack([params_of(m) for m in BUMPY_MATERIALS])
    basis, size = make_bases(mats, np.array([1, 2, 0]))
    print(f"\n== speed (basis of {basis.shape[1]} BRDFs per cluster, 6 samples per texel) ==")
    # projection of n_proj texels, in chunks of 200,000 texels (pure chunk function)
    texel, wi, wo = _random_samples(rng, n_proj, 6)
    labels = rng.integers(0, 3, n_proj)
    truth_w = rng.random((n_proj, 4))
    t, z = lobe_geometry(wi, wo)
    t0 = time.perf_counter()
    weights = np.zeros((n_proj, 4))
    chunk = 200_000
    for a in range(0, n_proj, chunk):
        s = slice(a * 6, (a + chunk) * 6)
        A = basis_values(t[s], z[s], wi[s, 2], texel[s] - a, labels[a:a + chunk], basis, size)
        r = np.einsum("sbc,sb->sc", A, truth_w[texel[s]]) * (1 + 0.02 * rng.normal(size=(len(A), 3)))
        weights[a:a + chunk] = project_chunk(texel[s] - a, t[s], z[s], wi[s, 2], r, np.ones(len(r)),
                                             labels[a:a + chunk], basis, size)[0]
    t_proj = time.perf_counter() - t0
    print(f"projection: {n_proj} texels in {t_proj:.1f} s (includes making the noisy samples; "
          f"target < 60 s; paper: ~1.5 h for clustering + projection)")
    # the same by a per-texel loop (evaluate its basis, scipy.optimize.nnls) on a subset
    m = 2000
    s = slice(0, m * 6)
    r = np.einsum("sbc,sb->sc", basis_values(t[s], z[s], wi[s, 2], texel[s], labels[:m], basis, size),
                  truth_w[texel[s]])
    t0 = time.perf_counter()
    for k in range(m):
        sk = slice(k * 6, (k + 1) * 6)
        Ak = np.stack([model_and_jacobian(basis[labels[k], b], t[sk], z[sk], wi[sk, 2], want_jac=False)[0]
                       for b in range(4)], axis=-1).reshape(-1, 4)
        nnls(Ak, r[sk].T.ravel())
    t_loop = (time.perf_counter() - t0) / m
    print(f"  per texel: batched {1e6 * t_proj / n_proj:.1f} us, per-texel loop (basis + scipy nnls) "
          f"{1e6 * t_loop:.1f} us (x{t_loop / (t_proj / n_proj):.1f})")

    # normal fitting of n_normals texels tilted 5 deg from their true normals
    texel, wi, wo = _random_samples(rng, n_normals, 6)
    labels = rng.integers(0, 3, n_normals)
    w0 = np.zeros((n_normals, 4))
    w0[:, 0] = 1
    tilt = np.radians(5.0)
    phi = rng.uniform(0, 2 * np.pi, n_normals)
    n_true = np.stack([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi),
                       np.full(n_normals, np.cos(tilt))], 1)
    fr = tangent_frames(n_true)[texel]
    wi_t, wo_t = to_local(wi, fr), to_local(wo, fr)
    ok = (wi_t[:, 2] > 0.05) & (wo_t[:, 2] > 0.05)
    tt, zz = lobe_geometry(wi_t, wo_t)
    A = np.zeros((len(texel), 4, 3))
    A[:] = basis_values(tt, zz, np.where(ok, wi_t[:, 2], 0), texel, labels, basis, size)
    r = A[:, 0] * (1 + 0.01 * rng.normal(size=(len(texel), 3)))
    t0 = time.perf_counter()
    nl, _, fitted, conv = fit_normals_chunk(texel, wi, wo, r, np.ones(len(r)), labels, w0, basis, size)
    t_nf = time.perf_counter() - t0
    err = np.degrees(np.arccos(np.clip(np.sum(nl * n_true, axis=1), -1, 1)))
    print(f"normal fitting: {n_normals} texels in {t_nf:.1f} s (target < 60 s; paper: 3-4 h per model); "
          f"error 5 deg -> median {np.median(err):.2f} deg, {100 * conv.mean():.0f} % converged")
    m = 200
    t0 = time.perf_counter()
    for k in range(m):
        s = slice(k * 6, (k + 1) * 6)
        least_squares(lambda x: _residual(x, wi[s], wo[s], r[s], basis[labels[k]])[0],
                      np.r_[0.0, 0.0, w0[k]], method="lm",
                      jac=lambda x: _residual(x, wi[s], wo[s], r[s], basis[labels[k]])[1])
    t_loop = (time.perf_counter() - t0) / m
    print(f"  per texel: batched {1e6 * t_nf / n_normals:.0f} us, scipy least_squares loop "
          f"{1e6 * t_loop:.0f} us (x{t_loop / (t_nf / n_normals):.0f})")


def _residual(x, wi, wo, r, basis_k):
    """One texel's residuals and analytic Jacobian (the batched model with a batch of one)."""
    res, jac = _mixture(x[None], wi[None], wo[None], r[None], np.ones((1, len(wi))), basis_k[None])
    return res[0], jac[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--object-width", type=int, default=160, help="camera width in pixels (object run)")
    ap.add_argument("--png", default="lensch_normals.png", help="normal-map figure ('' for none)")
    ap.add_argument("--projection-texels", type=int, default=1_000_000)
    ap.add_argument("--normal-texels", type=int, default=100_000)
    ap.add_argument("--seeds", default="0,1,2,3,4", help="seeds of the paper's experiment")
    ap.add_argument("--count-sets", type=int, default=12, help="random material sets to count")
    ap.add_argument("--skip", nargs="*", default=(), choices=("paper", "count", "object", "speed"))
    a = ap.parse_args()
    if "paper" not in a.skip:
        paper_experiment([int(x) for x in a.seeds.split(",")])
    if "count" not in a.skip:
        material_count(a.count_sets)
    if "object" not in a.skip:
        bumpy_object(a.object_width, a.png or None)
    if "speed" not in a.skip:
        speed(a.projection_texels, a.normal_texels)


if __name__ == "__main__":
    main()
