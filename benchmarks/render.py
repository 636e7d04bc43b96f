"""Renderer timings: the full bunny at 1 megapixel with shadows, an environment-lit sphere, and
BRDF evaluations per second for every model in ``reconstruct.brdf``.

Run: ``python benchmarks/render.py [--size 1000] [--repeat 3] [--env-samples 64]``.

Figures are best-of-``repeat``; both wall time and process CPU time are printed (numpy and
Embree run single-threaded here, so CPU time equals wall time on an idle machine and stays
meaningful on a shared, loaded one). "cold" includes building the Embree BVH and the mesh's
cached arrays; "warm" re-renders the same scene (a simulated capture session renders many frames
of one mesh). Target: 1 MP bunny with shadows under a point light in < 1 s on 2 cores.
"""
from __future__ import annotations

import argparse
import dataclasses
import inspect
import os
import time
from pathlib import Path

import numpy as np
import trimesh

import reconstruct.brdf as brdf_pkg
from reconstruct.brdf import BRDF, CookTorrance, Lambertian
from reconstruct.camera import CameraModel
from reconstruct.envmap import EnvironmentMap
from reconstruct.raycast import Mesh, Plane, Sphere
from reconstruct.render import PointLight, Scene, render

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def timed(fn, repeat):
    """(best wall s, best CPU s, last result) over ``repeat`` calls."""
    wall, cpu, out = np.inf, np.inf, None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return wall, cpu, out


def bunny_scene():
    mesh = trimesh.load(SHARED / "meshes" / "bun_zipper.ply")
    T = np.eye(4)
    T[:3, :3] = 1000 * np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])  # m -> mm, y-up -> z-up
    T[:3, 3] = -T[:3, :3] @ np.array([mesh.bounds.mean(0)[0], mesh.bounds[0][1],
                                      mesh.bounds.mean(0)[2]])
    sc = Scene()
    sc.add(Mesh(mesh, T), CookTorrance(kd=0.6, f0=0.04, alpha=0.3), "bunny")
    sc.add(Plane((600, 600)), Lambertian(0.3), "floor")
    sc.add_light(PointLight((200.0, -300.0, 400.0), 1e5))
    return sc, len(mesh.faces)


def bench_bunny(size, repeat):
    if not (SHARED / "meshes" / "bun_zipper.ply").is_file():
        print(f"bunny: skipped ({SHARED / 'meshes' / 'bun_zipper.ply'} is absent)")
        return
    cam = CameraModel.look_at((0, -450, 250), (0, 0, 80), width=size, height=size, fov_deg=30)
    sc, n_faces = bunny_scene()
    wall_c, cpu_c, _ = timed(lambda: render(sc, cam, shadows=True), 1)
    wall, cpu, res = timed(lambda: render(sc, cam, shadows=True), repeat)
    print(f"bunny ({n_faces} faces) {size}x{size} = {size * size / 1e6:.2f} MP, point light, "
          f"shadows, Cook-Torrance + Lambertian floor ({res.mask.mean():.0%} of pixels hit):")
    print(f"  cold {wall_c:.3f} s wall / {cpu_c:.3f} s CPU;  warm {wall:.3f} s wall / "
          f"{cpu:.3f} s CPU  (target < 1 s)")
    for threads in (1, 2):
        w, c, _ = timed(lambda: render(sc, cam, shadows=True, threads=threads), repeat)
        print(f"  threads={threads}: {w:.3f} s wall / {c:.3f} s CPU")
    wall_ns, cpu_ns, _ = timed(lambda: render(sc, cam, shadows=False), repeat)
    print(f"  without shadows: {wall_ns:.3f} s wall / {cpu_ns:.3f} s CPU")


def bench_env_sphere(size, samples, repeat):
    probe = SHARED / "probes" / "grace.hdr"
    if probe.is_file():
        env, name = EnvironmentMap.load(probe).resized(64), "grace.hdr (64x128)"
    else:
        env = EnvironmentMap.from_function(lambda d: 0.2 + 5 * np.exp(30 * (d[:, :1] - 1))
                                           + 0 * d, 64)
        name = "synthetic sky (64x128)"
    sc = Scene(environment=env)
    sc.add(Sphere(40.0, center=(0, 0, 50)), CookTorrance(kd=0.5, f0=0.04, alpha=0.3))
    cam = CameraModel.look_at((0.0, -300.0, 50.0), (0.0, 0.0, 50.0), width=size, height=size,
                              fov_deg=18)
    wall, cpu, res = timed(lambda: render(sc, cam, env_samples=samples, shadows=False, rng=0),
                           repeat)
    n = int(res.mask.sum())
    print(f"environment-lit sphere {size}x{size}, {name}, {samples} MIS samples/pixel, "
          f"{n} sphere pixels: {wall:.3f} s wall / {cpu:.3f} s CPU "
          f"({n * samples / cpu / 1e6:.2f} M samples/s CPU)")


def _instantiate(cls):
    """A model with its defaults; required BRDF-typed fields get simple models; tabulated
    models are tabulated from a Cook-Torrance model with their ``from_brdf`` defaults."""
    if hasattr(cls, "from_brdf"):
        return cls.from_brdf(CookTorrance(kd=0.3, f0=0.5, alpha=0.25))
    kw = {}
    for f in dataclasses.fields(cls):
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            if "BRDF" in str(f.type):
                kw[f.name] = Lambertian(0.5) if "diffuse" in f.name else CookTorrance(kd=0.0)
            else:
                raise TypeError(f"needs {f.name!r}")
    return cls(**kw)


def bench_brdfs(samples, repeat):
    rng = np.random.default_rng(0)

    def hemisphere(n):
        v = rng.normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        v[:, 2] = np.abs(v[:, 2])
        return v
    wi, wo = hemisphere(samples), hemisphere(samples)
    print(f"BRDF evaluations per second ({samples:.0e} random direction pairs, best CPU time):")
    for name in sorted(getattr(brdf_pkg, "__all__", dir(brdf_pkg))):
        cls = getattr(brdf_pkg, name)
        if not (inspect.isclass(cls) and issubclass(cls, BRDF)) or inspect.isabstract(cls) \
                or cls is BRDF:
            continue
        try:
            model = _instantiate(cls)
        except (TypeError, ValueError) as e:
            print(f"  {name:20s} skipped (no default instance: {e})")
            continue
        _, cpu, _ = timed(lambda: model.evaluate(wi, wo), repeat)
        print(f"  {name:20s} {samples / cpu / 1e6:8.2f} M evals/s")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1000, help="bunny frame width = height, px")
    parser.add_argument("--env-size", type=int, default=256, help="env-lit sphere frame size")
    parser.add_argument("--env-samples", type=int, default=64)
    parser.add_argument("--brdf-samples", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    print(f"cpus available: {len(os.sched_getaffinity(0))}, load average: "
          f"{os.getloadavg()[0]:.1f}")
    bench_bunny(args.size, args.repeat)
    bench_env_sphere(args.env_size, args.env_samples, args.repeat)
    bench_brdfs(args.brdf_samples, args.repeat)


if __name__ == "__main__":
    main()
