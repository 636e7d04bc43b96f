"""Geometry benchmarks: photometric stereo, surface integration and lumitexel assembly.

Prints timings on this machine and, as ratios measured in the same run, against the obvious
baseline (a per-pixel ``np.linalg.lstsq`` loop, timed on a subset and scaled).

    python benchmarks/geometry.py
"""
from __future__ import annotations

import time

import numpy as np

from reconstruct.integrate import frankot_chellappa, poisson_integrate
from reconstruct.photometric_stereo import photometric_stereo


def _sphere_stack(H, W, K, seed=0):
    rng = np.random.default_rng(seed)
    Y, X = np.mgrid[:H, :W]
    r = 0.45 * min(H, W)
    nx, ny = (X - W / 2) / r, (Y - H / 2) / r
    inside = nx ** 2 + ny ** 2 < 0.97 ** 2
    n = np.stack([nx, ny, -np.sqrt(np.clip(1 - nx ** 2 - ny ** 2, 0, None))], -1) * inside[..., None]
    az = rng.uniform(0, 2 * np.pi, K)
    el = rng.uniform(np.radians(30), np.radians(75), K)
    L = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)], 1)
    imgs = (0.6 * np.clip(np.einsum("hwc,kc->khw", n, L), 0, None)
            + rng.normal(0, 0.002, (K, H, W))).astype(np.float32)
    return imgs, L, inside, n


def bench_photometric_stereo(H=1000, W=1000, K=12):
    imgs, L, inside, _ = _sphere_stack(H, W, K)
    t0 = time.perf_counter()
    photometric_stereo(imgs, L, inside)
    t_ls = time.perf_counter() - t0
    t0 = time.perf_counter()
    photometric_stereo(imgs, L, inside, robust=True, shadow_threshold=0.01)
    t_robust = time.perf_counter() - t0
    # baseline: per-pixel lstsq loop on 2000 pixels, scaled to the mask size
    ys, xs = np.nonzero(inside)
    sub = slice(0, 2000)
    t0 = time.perf_counter()
    for y, x in zip(ys[sub], xs[sub]):
        np.linalg.lstsq(L, imgs[:, y, x], rcond=None)
    t_base = (time.perf_counter() - t0) / 2000 * inside.sum()
    print(f"photometric stereo {H}x{W}, {K} lights ({inside.sum()} masked px):")
    print(f"  least squares      {t_ls:7.3f} s   (per-pixel lstsq loop ~{t_base:6.1f} s: "
          f"{t_base / t_ls:5.0f}x faster)")
    print(f"  robust (re-weighted) {t_robust:5.3f} s")


def bench_integration(H=512, W=512):
    _, _, inside, n = _sphere_stack(H, W, 3)
    t0 = time.perf_counter()
    poisson_integrate(n, inside)
    t_p = time.perf_counter() - t0
    t0 = time.perf_counter()
    frankot_chellappa(n, inside)
    t_fc = time.perf_counter() - t0
    print(f"integration {H}x{W}: Poisson (masked, sparse) {t_p:.3f} s, Frankot-Chellappa {t_fc:.3f} s")




def bench_lumitexels(n_views=24, size=(640, 480)):
    """Lumitexel assembly from rendered views of the full bunny (or an icosphere without data)."""
    import trimesh

    from reconstruct.brdf import BlinnPhong
    from reconstruct.camera import CameraModel
    from reconstruct.lumitexels import View, assemble_lumitexels
    from reconstruct.raycast import Mesh
    from reconstruct.render import PointLight, Scene, render
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "shared/data/meshes/bun_zipper.ply"
    if path.is_file():
        mesh = trimesh.load(path, process=False)
        mesh.apply_scale(120.0 / np.ptp(mesh.vertices[:, 1]))
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        mesh.apply_translation(-mesh.bounds.mean(0) + [0, 0, 60])
        name = f"bunny ({len(mesh.faces)} faces)"
    else:
        mesh = trimesh.creation.icosphere(subdivisions=6, radius=50.0)
        mesh.apply_translation([0, 0, 60])
        name = f"icosphere ({len(mesh.faces)} faces; bunny not found)"
    cam = CameraModel.look_at((450, 0, 160), (0, 0, 60), width=size[0], height=size[1], fov_deg=24)
    mat = BlinnPhong(kd=[0.5, 0.4, 0.3], ks=0.3, exponent=40.0)
    views = []
    t0 = time.perf_counter()
    for k in range(n_views):
        a = 2 * np.pi * k / n_views
        T = np.eye(4)
        T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
        light = np.array([300 * np.cos(0.7 * k), 300 * np.sin(0.7 * k), 250.0])
        scene = Scene()
        scene.add(Mesh(mesh, T), mat)
        scene.add_light(PointLight(light, intensity=1e5))
        views.append(View(cam, render(scene, cam).radiance, light, 1e5, T))
    t_render = time.perf_counter() - t0
    t0 = time.perf_counter()
    lt = assemble_lumitexels(mesh, views)
    t = time.perf_counter() - t0
    print(f"lumitexels: {name}, {n_views} views {size[0]}x{size[1]} (rendering them took {t_render:.1f} s)")
    print(f"  {lt.n_texels} texels, {lt.n_samples} samples in {t:.2f} s = "
          f"{lt.n_samples / t / 1e6:.2f} M samples/s (target: 1 M samples in < 10 s)")


if __name__ == "__main__":
    bench_photometric_stereo()
    bench_integration()
    bench_lumitexels()
