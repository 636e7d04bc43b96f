"""Passive reflectometry (Romeiro et al. 2008) on the simulated problem: speed and accuracy.

Prints, in one run:

1. the time to build the lighting matrix for 8,000 normals of a sphere against the Grace
   Cathedral probe at its own resolution (32,768 texels, ~16,000 per visible hemisphere) and
   against the probe resampled to 64,082 directions (~32,000 per visible hemisphere, the
   paper's count), and the time of the two-prior solve;
2. the error table: each material from one image of a sphere under Grace, the relative RMS
   BRDF error of Eq. 1 of the recovered BRDF next to that of the truth's own bivariate
   reduction (the paper's Figs. 3 and 6), and the relative RMS error of a sphere rendered with
   the recovered BRDF under a different probe (Uffizi);
3. environment dependence (Fig. 7): one material recovered under Grace and under Uffizi, with
   both adequacy reports, and a PNG of incident-plane slices against the truth (Fig. 6 style).

Images are rendered by exact quadrature over the probe's texels (``reconstruct.distant``), the
sphere seen orthographically in the OpenCV camera frame with the probe's up along -y.

Usage: ``python benchmarks/passive.py [--out DIR] [--env-height 64] [--size 100]``
(needs ``../shared/data/probes``).
"""
from __future__ import annotations

import os

# One BLAS thread: on this project's shared 2-core machines a threaded 1024 x 1024 Cholesky
# took 3-6 s (threads spin-waiting on each other) against 0.07 s single-threaded.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402
import warnings
from pathlib import Path

import numpy as np  # noqa: E402

from reconstruct.brdf import Bivariate, CookTorrance, Lafortune, Lambertian, OrenNayar, Ward
from reconstruct.distant import shade_distant, sphere_normals
from reconstruct.envmap import EnvironmentMap
from reconstruct.frames import tangent_frames
from reconstruct.passive import PassiveWarning, bivariate_error, passive_reflectometry
from reconstruct.passive_lighting import lighting_matrix
from reconstruct.passive_prior import default_prior

PROBES = Path(__file__).resolve().parents[2] / "shared" / "data" / "probes"
CAMERA_TO_PROBE = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])

MATERIALS = {
    "Lambertian": Lambertian([0.7, 0.5, 0.3]),
    "Oren-Nayar s=0.4": OrenNayar([0.6, 0.55, 0.4], 0.4),
    "Cook-Torrance a=0.3": CookTorrance([0.4, 0.3, 0.2], 0.04, 0.3),
    "Cook-Torrance a=0.1": CookTorrance([0.3, 0.2, 0.1], 0.04, 0.1),
    "Ward a=0.08 (bounded)": Ward([0.2, 0.2, 0.25], 0.15, 0.08, variant="bounded"),
    "strong Fresnel": CookTorrance([0.05, 0.05, 0.06], 0.02, 0.3, "beckmann"),
    "retro-reflective": Lafortune([0.2, 0.15, 0.1], 1.04, 1.04, 10.0),
}


def probe(name: str, height: int | None = None) -> EnvironmentMap:
    env = EnvironmentMap.load(PROBES / f"{name}.hdr", rotation=CAMERA_TO_PROBE)
    return env if height is None else env.resized(height)


def sphere_image(brdf, env, size):
    normals, mask = sphere_normals(size)
    image = np.zeros(normals.shape)
    image[mask] = shade_distant(brdf, normals[mask], *env.sources())
    return image, normals, mask


def render_error(estimate, truth, env, size=64) -> float:
    """Relative RMS image error of a sphere rendered with ``estimate`` against ``truth``."""
    a, _, mask = sphere_image(estimate, env, size)
    b = sphere_image(truth, env, size)[0]
    return float(np.linalg.norm(a[mask] - b[mask]) / np.linalg.norm(b[mask]))


def timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t, time.process_time() - c


def naive_lighting_rows(normals, d, E, omega, grid=(32, 32)):
    """The baseline: lighting-matrix rows (3, N, n_t n_s) one normal at a time over all its
    visible sources, through local frames, ``Bivariate.interpolation_weights`` and one
    ``bincount`` per colour (orthographic camera looking along +z)."""
    table = Bivariate(np.zeros((*grid, 3)))
    rows = np.zeros((3, len(normals), grid[0] * grid[1]))
    for r, frame in enumerate(tangent_frames(normals)):
        wi = d @ frame.T
        vis = wi[:, 2] > 0
        wo = np.broadcast_to(frame @ [0.0, 0.0, -1.0], (int(vis.sum()), 3))
        index, weight = table.interpolation_weights(wi[vis], wo)
        weight = weight * wi[vis, 2:3]
        for c in range(3):
            rows[c, r] = np.bincount(index.ravel(), (weight * (E[vis, c] * omega[vis])[:, None])
                                     .ravel(), minlength=rows.shape[2])
    return rows


def timing_section():
    normals, mask = sphere_normals(112)
    n = normals[mask]
    n = n[-n[:, 2] >= np.cos(np.radians(80))]
    n = n[np.random.default_rng(0).choice(len(n), 8000, replace=False)]
    grace = probe("grace")
    fine = EnvironmentMap.from_function(lambda d: grace.lookup(d), 179, 358)
    for label, env in (("probe texels", grace), ("resampled", fine)):
        d, E, om = env.sources()
        L, wall, cpu = timed(lambda: lighting_matrix(n, d, E, om))
        print(f"lighting matrix, 8000 normals x {len(d)} directions ({label}, ~{len(d) // 2} "
              f"per visible hemisphere): {wall:.1f} s wall, {cpu:.1f} s CPU  (target < 10 s)")
        if label == "probe texels":  # the baseline on a subset, scaled to 8000 normals
            sub = slice(None, None, 40)
            rows, _, cpu_naive = timed(lambda: naive_lighting_rows(n[sub], d, E, om))
            cpu_naive *= len(n) / len(rows[0])
            diff = np.abs(L[:, sub] - rows).max() / np.abs(rows).max()
            print(f"  naive baseline (one normal at a time, local frames, bincount; "
                  f"{len(rows[0])} normals scaled to {len(n)}): {cpu_naive:.1f} s CPU, "
                  f"{cpu_naive / cpu:.1f}x the lighting matrix's; largest difference "
                  f"{diff:.1e} of the largest entry")
    default_prior("diffuse"), default_prior("glossy")  # learned once, cached
    env = probe("grace")
    image, normals, mask = sphere_image(Lambertian(0.5), probe("grace", 16), 112)
    stamps = []
    start = time.perf_counter()
    fit = passive_reflectometry(image, normals, mask, env, progress=lambda done, total:
                                stamps.append((done, time.perf_counter())))
    end = time.perf_counter()
    n_obs = fit.adequacy.n_observations
    t_matrix = next(t for done, t in stamps if done >= n_obs)
    print(f"whole fit, {n_obs} normals x {len(env.sources()[0])} texels: {end - start:.1f} s "
          f"wall; after the lighting matrix, the two-prior solve (3 channels) and the adequacy "
          f"report: {end - t_matrix:.1f} s  (target < 5 s)")


def error_table(env_height, size):
    grace, uffizi = probe("grace", env_height), probe("uffizi", env_height)
    print(f"\nerror table: one {size} x {size} sphere image under Grace ({env_height} x "
          f"{2 * env_height} texels); Eq. 1 errors on the MERL grid, all samples / leaving out "
          f"10 deg at the horizon; render error: sphere under Uffizi")
    print(f"{'material':24s} {'recovered':>17s} {'reduction':>17s} {'render':>7s} "
          f"{'prior':>8s} {'resid':>6s} {'time':>6s}")
    fits = {}
    for name, truth in MATERIALS.items():
        image, normals, mask = sphere_image(truth, grace, size)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PassiveWarning)
            fit, wall, _ = timed(lambda: passive_reflectometry(image, normals, mask, grace))
        fits[name] = fit
        reduction = Bivariate.from_brdf(truth)
        e = [bivariate_error(fit.brdf, truth, exclude_grazing_deg=x) for x in (0, 10)]
        r = [bivariate_error(reduction, truth, exclude_grazing_deg=x) for x in (0, 10)]
        print(f"{name:24s} {e[0]:8.1%} {e[1]:8.1%} {r[0]:8.1%} {r[1]:8.1%} "
              f"{render_error(fit.brdf, truth, uffizi):7.2%} {fit.prior:>8s} "
              f"{fit.residual.mean():6.2%} {wall:5.1f}s")
    return fits


def environment_section(env_height, size, out: Path):
    name = "Cook-Torrance a=0.3"
    truth = MATERIALS[name]
    print(f"\nenvironment dependence (Fig. 7): {name}")
    fits = {}
    for probe_name in ("grace", "uffizi"):
        env = probe(probe_name, env_height)
        image, normals, mask = sphere_image(truth, env, size)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PassiveWarning)
            fit = passive_reflectometry(image, normals, mask, env)
        fits[probe_name] = fit
        print(f"-- input under {probe_name}: Eq. 1 error {bivariate_error(fit.brdf, truth):.1%}"
              f" (leaving out 10 deg: "
              f"{bivariate_error(fit.brdf, truth, exclude_grazing_deg=10):.1%})")
        print("   " + fit.adequacy.report().replace("\n", "\n   "))
    plot_slices(truth, fits, out / "passive_slices.png")


def plot_slices(truth, fits, path: Path):
    """Incident-plane slices, red channel: f(theta_o) for theta_i = 20, 45, 70 deg."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    theta_o = np.radians(np.linspace(-89, 89, 357))
    reduction = Bivariate.from_brdf(truth)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for ax, ti in zip(axes, (20, 45, 70)):
        wi = np.tile([np.sin(np.radians(ti)), 0, np.cos(np.radians(ti))], (len(theta_o), 1))
        wo = np.stack([-np.sin(theta_o), np.zeros_like(theta_o), np.cos(theta_o)], axis=1)
        x = np.degrees(theta_o)
        ax.semilogy(x, truth.evaluate(wi, wo)[:, 0], "b.", ms=3, label="true (3-D)")
        ax.semilogy(x, reduction.evaluate(wi, wo)[:, 0], "g-", label="true bivariate")
        for (probe_name, fit), style in zip(fits.items(), ("r-", "k--")):
            ax.semilogy(x, fit.brdf.evaluate(wi, wo)[:, 0], style,
                        label=f"recovered ({probe_name})")
        ax.set_title(f"incident plane, theta_i = {ti} deg (red)")
        ax.set_xlabel("theta_o (deg, + = mirror side)")
    axes[0].set_ylabel("f_r (1/sr)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"\nwrote {path}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("passive-out"))
    ap.add_argument("--env-height", type=int, default=64)
    ap.add_argument("--size", type=int, default=100)
    ap.add_argument("--skip-timing", action="store_true")
    args = ap.parse_args()
    if not PROBES.is_dir():
        raise SystemExit(f"needs the light probes in {PROBES}")
    if not args.skip_timing:
        timing_section()
    error_table(args.env_height, args.size)
    environment_section(args.env_height, args.size, args.out)


if __name__ == "__main__":
    main()
