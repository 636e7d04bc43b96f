"""Sharing and passive over blocks (issue 21): what the block routes hold and cost.

Prints, in one run:

1. passive's lighting matrix for ``--normals`` normals of a sphere under the Grace probe (32 x 64)
   on a 32 x 32 grid: the whole build the fit used before (L, its float64 copy per channel, the
   Gram matrices) against ``lighting_sums`` over blocks: peak traced memory (tracemalloc), CPU
   seconds, and the largest relative difference of the Gram matrices;
2. sharing's RBF subsample: synthetic separated lumitexels (Lensch Sec. 11's Phong materials, each
   a band of the surface parameter; mesh normals tilted 8 deg) fitted with ``fit_spatial_blocks`` on ``fit_texels`` of them drawn at
   random: peak traced memory, CPU seconds and the held-out relative RMS for each size.

Usage: ``python benchmarks/sharing_passive_blocks.py [--normals 8000] [--texels 2000]``
(needs ``../shared/data/probes``).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")   # threaded BLAS spin-waits on a loaded 2-core box

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from reconstruct.distant import sphere_normals  # noqa: E402
from reconstruct.envmap import EnvironmentMap  # noqa: E402
from reconstruct.lensch import ArrayBlocks  # noqa: E402
from reconstruct.metrics import relative_rms  # noqa: E402
from reconstruct.passive_lighting import lighting_matrix, lighting_sums  # noqa: E402
from reconstruct.sharing import fit_spatial_blocks, reframe  # noqa: E402
from sims.objects import shared_data_dir  # noqa: E402
from sims.reflectance_samples import paper_phong_materials, synthetic_samples  # noqa: E402


def measured(fn):
    """(result, peak traced MiB, CPU s) of ``fn()``."""
    tracemalloc.start()
    t = time.process_time()
    out = fn()
    cpu = time.process_time() - t
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return out, peak, cpu


def passive_part(n_normals: int) -> None:
    env = EnvironmentMap.load(shared_data_dir() / "probes" / "grace.hdr").resized(32)
    d, E, omega = env.sources()
    normals, mask = sphere_normals(160)
    n = normals[mask][:: max(1, int(mask.sum()) // n_normals)][:n_normals]
    values = np.random.default_rng(0).uniform(0, 1, (len(n), 3))

    def whole():   # what passive_reflectometry held before: L, a float64 copy per channel, the Grams
        L = lighting_matrix(n, d, E, omega, grid=(32, 32))
        A = [L[c].astype(np.float64) for c in range(3)]
        return np.stack([a.T @ a for a in A])

    g_whole, peak_w, cpu_w = measured(whole)
    s, peak_b, cpu_b = measured(lambda: lighting_sums(n, values, d, E, omega, grid=(32, 32)))
    diff = float(np.abs(s.gram - g_whole).max() / np.abs(g_whole).max())
    print(f"passive, {len(n)} normals, Grace 32 x 64, 32 x 32 grid:")
    print(f"  whole build   peak {peak_w:7.1f} MiB  CPU {cpu_w:5.2f} s")
    print(f"  over blocks   peak {peak_b:7.1f} MiB  CPU {cpu_b:5.2f} s   Gram max rel. difference {diff:.1e}")


def sharing_part(n_texels: int) -> None:
    s = synthetic_samples(paper_phong_materials(exponents=(10.0, 40.0, 80.0)), n_texels, rng=3)
    g = np.random.default_rng(7)
    phi = g.uniform(0, 2 * np.pi, n_texels)
    tilt = np.radians(8.0)
    mesh = np.stack([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), np.full(n_texels, np.cos(tilt))], 1)
    wi, wo = reframe(s.texel, mesh, s.wi, s.wo)
    diffuse = np.asarray([0.15, 0.3, 0.1]) / np.pi * s.wi[:, 2:3] * (1 + g.uniform(-0.05, 0.05, (len(s.texel), 3)))
    specular = np.maximum(s.reflectance - diffuse, 0.0)
    held = g.random(len(s.texel)) < 0.2
    train = ~held
    blocks = ArrayBlocks(s.texel[train], wi[train], wo[train], s.reflectance[train], np.ones(int(train.sum())),
                         n_texels=n_texels, block_texels=1000, diffuse=diffuse[train], specular=specular[train])
    # each material a band of the surface (the RBF shares reflectance between neighbours)
    xy = np.stack([(s.material + g.uniform(0.05, 0.95, n_texels)) / 3, g.uniform(0, 1, n_texels)], 1)
    print(f"sharing, {n_texels} texels, {int(train.sum())} training / {int(held.sum())} held-out samples, 300 centres:")
    for fit_texels in sorted({n_texels // 8, n_texels // 4, n_texels // 2, n_texels}):
        fit, peak, cpu = measured(lambda: fit_spatial_blocks(blocks, xy, fit_texels=fit_texels, max_centers=300,
                                                             fit_normals=True, m_xy=1.0, rng=0))
        err = relative_rms(fit.predict(s.texel[held], wi[held], wo[held]), s.clean[held])
        centres = "+".join(str(f.model.n_centers) for f in fit.fits.values())
        print(f"  RBFs on {fit.fit_texels:6d} texels ({centres} centres)  peak {peak:6.1f} MiB  CPU {cpu:6.2f} s  held-out rel. RMS {err:.4f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--normals", type=int, default=8000)
    ap.add_argument("--texels", type=int, default=2000)
    args = ap.parse_args()
    passive_part(args.normals)
    sharing_part(args.texels)


if __name__ == "__main__":
    main()
