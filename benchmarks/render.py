"""Renderer timings: the full bunny at 1 megapixel with shadows, an environment-lit sphere, and
BRDF evaluations per second for every model in ``reconstruct.brdf``.

Run: ``python benchmarks/render.py [--size 1000] [--repeat 3] [--env-samples 64]``.

Figures are best-of-``repeat``: wall time, process CPU time (all threads) and the calling
thread's CPU time. On a machine shared with other jobs the wall time is inflated by waiting for a
core; the CPU times are what the render itself costs (``threads=1``: CPU = the wall time it would
take on an idle core; ``threads=2``: CPU / wall shows how much of it ran in parallel). The load
average is printed before and after so the figures can be read against it. "cold" includes
building the Embree BVH and the mesh's per-pose tables; "warm" re-renders the same scene (a
simulated capture session renders many frames of one mesh). Target: 1 MP bunny with shadows
under a point light in < 1 s on 2 cores. The simulated camera's frame (render + sensor + DNG at
the default 1200 x 800 distorted camera) is timed too: every simulated capture makes one.
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
    """(best wall s, best process CPU s, best calling-thread CPU s, last result) over
    ``repeat`` calls."""
    wall, cpu, thread, out = np.inf, np.inf, np.inf, None
    for _ in range(repeat):
        t0, c0, h0 = time.perf_counter(), time.process_time(), time.thread_time()
        out = fn()
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
        thread = min(thread, time.thread_time() - h0)
    return wall, cpu, thread, out


def fmt(wall, cpu, thread):
    return f"{wall:.3f} s wall / {cpu:.3f} s CPU ({thread:.3f} s on the calling thread)"


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
    *cold, _ = timed(lambda: render(sc, cam, shadows=True), 1)
    *warm, res = timed(lambda: render(sc, cam, shadows=True), repeat)
    print(f"bunny ({n_faces} faces) {size}x{size} = {size * size / 1e6:.2f} MP, point light, "
          f"shadows, Cook-Torrance + Lambertian floor ({res.mask.mean():.0%} of pixels hit), "
          f"target < 1 s:")
    print(f"  cold (BVH build) {fmt(*cold)}")
    print(f"  warm, default threads {fmt(*warm)}")
    for threads in (1, 2):
        *t, _ = timed(lambda: render(sc, cam, shadows=True, threads=threads), repeat)
        print(f"  warm, threads={threads}: {fmt(*t)}")
    *t, _ = timed(lambda: render(sc, cam, shadows=False, threads=1), repeat)
    print(f"  without shadows, threads=1: {fmt(*t)}")


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
    *t, res = timed(lambda: render(sc, cam, env_samples=samples, shadows=False, rng=0), repeat)
    n = int(res.mask.sum())
    print(f"environment-lit sphere {size}x{size}, {name}, {samples} MIS samples/pixel, "
          f"{n} sphere pixels: {fmt(*t)} ({n * samples / t[1] / 1e6:.2f} M samples/s CPU)")


def bench_sim_frame(repeat, objects=("sphere", "bunny")):
    """The simulated camera's frame at its default 1200 x 800 distorted camera: rig state ->
    render -> sensor -> DNG bytes."""
    from sims.world import SimWorld
    for name in objects:
        world = SimWorld(name)
        *cold, dng = timed(lambda: world.frame_source({}), 1)
        *warm, _ = timed(lambda: world.frame_source({}), repeat)
        print(f"sim camera frame, {name}, {world.camera.width}x{world.camera.height} DNG "
              f"({len(dng) / 1e6:.1f} MB): first {fmt(*cold)}; then {fmt(*warm)}")


def _instantiate(cls, table_shape):
    """A model with its defaults; required BRDF-typed fields get simple models; tabulated
    models are tabulated from a Cook-Torrance model (the 3-D table at ``table_shape``, the
    bivariate one at its ``from_brdf`` defaults)."""
    if hasattr(cls, "from_brdf"):
        source = CookTorrance(kd=0.3, f0=0.5, alpha=0.25)
        if cls is brdf_pkg.TabulatedIsotropic:
            return cls.from_brdf(source, table_shape)
        return cls.from_brdf(source)
    kw = {}
    for f in dataclasses.fields(cls):
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            if "BRDF" in str(f.type):
                kw[f.name] = Lambertian(0.5) if "diffuse" in f.name else CookTorrance(kd=0.0)
            else:
                raise TypeError(f"needs {f.name!r}")
    return cls(**kw)


def bench_brdfs(samples, repeat, table_shape=(90, 90, 180)):
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
            model = _instantiate(cls, table_shape)
        except (TypeError, ValueError) as e:
            print(f"  {name:20s} skipped (no default instance: {e})")
            continue
        _, cpu, _, _ = timed(lambda: model.evaluate(wi, wo), repeat)
        print(f"  {name:20s} {samples / cpu / 1e6:8.2f} M evals/s")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1000, help="bunny frame width = height, px")
    parser.add_argument("--env-size", type=int, default=256, help="env-lit sphere frame size")
    parser.add_argument("--env-samples", type=int, default=64)
    parser.add_argument("--brdf-samples", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--table-shape", default="90,90,180",
                        help="node counts of the TabulatedIsotropic table (MERL's by default)")
    parser.add_argument("--sim-objects", default="sphere,bunny",
                        help="objects of the simulated camera frame benchmark ('' to skip)")
    args = parser.parse_args(argv)
    print(f"cpus available: {len(os.sched_getaffinity(0))}, load average (1 min) at start: "
          f"{os.getloadavg()[0]:.1f}")
    bench_bunny(args.size, args.repeat)
    bench_env_sphere(args.env_size, args.env_samples, args.repeat)
    if args.sim_objects:
        bench_sim_frame(args.repeat, tuple(args.sim_objects.split(",")))
    bench_brdfs(args.brdf_samples, args.repeat,
                tuple(int(n) for n in args.table_shape.split(",")))
    print(f"load average (1 min) at end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
