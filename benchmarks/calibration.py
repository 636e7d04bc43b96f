"""Calibration accuracy against ground truth, timings, and our HDR merge versus OpenCV's.

    python benchmarks/calibration.py [--quick] [--sim]

Synthetic scenes come from the calibration test helpers (``tests/calibration``): boards drawn
in their own plane and resampled through a known camera, analytic chrome spheres, raw brackets
with Poisson + read noise, polarizer stacks. Real data (``../shared/data``) is used when
present: OpenCV's chessboard photos and the UW chrome-sphere photos. Times are wall-clock,
best of 3 where cheap.
"""
from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# this file is itself named calibration.py: drop its folder so `import calibration` finds the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "calibration")]  # the package; synthetic-scene helpers

from calib_synth import (DIST_TRUE, K_TRUE, board_poses, chessboard_texture, render_plane,  # noqa: E402
                         rot_axis_angle)
from test_lights import render_spheres  # noqa: E402
from test_radiometry import BLACK, GAIN, READ, WHITE, patch_radiance, simulate_raw  # noqa: E402

from calibration.hdr import merge_ldr, merge_raw_brackets  # noqa: E402
from calibration.intrinsics import calibrate_intrinsics, detect_all  # noqa: E402
from calibration.lights import (detect_sphere, find_highlight, light_direction_orthographic,  # noqa: E402
                                reflect_highlight, triangulate_point_light)
from calibration.polarization import fit_polarization, separate_parallel_crossed  # noqa: E402
from calibration.targets import detect_charuco, detect_chessboard, make_charuco_board  # noqa: E402
from calibration.turntable import fit_turntable  # noqa: E402

DATA = ROOT.parent / "shared" / "data"


def timed(fn, repeat=1):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def angle_deg(u, v):
    u, v = np.asarray(u, float), np.asarray(v, float)
    c = np.sum(u * v, -1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def bench_intrinsics(n_views):
    rng = np.random.default_rng(42)
    tex, to_tex = chessboard_texture(12, 9)
    imgs = [render_plane(tex, to_tex, K_TRUE, DIST_TRUE, r, t, rng=rng, noise=1.5)
            for r, t in board_poses(n_views, rng)]
    for method in ("classic", "sb"):
        det = functools.partial(detect_chessboard, pattern_size=(11, 8), method=method)
        (dets, _), t_det = timed(lambda: detect_all(imgs, det))
        res, t_cal = timed(lambda: calibrate_intrinsics(dets))
        f_err = 100 * np.abs(np.diag(res.K)[:2] / np.diag(K_TRUE)[:2] - 1).max()
        c_err = 100 * np.abs(res.K[:2, 2] / K_TRUE[:2, 2] - 1).max()
        print(f"intrinsics ({method:7s}, {len(dets)} views 1280x960): focal err {f_err:.3f}%  principal point "
              f"err {c_err:.3f}%  RMS {res.rms_px:.3f} px   [bar: 0.2%, 0.2%, 0.15 px]  "
              f"detect {1e3 * t_det / len(imgs):.0f} ms/view, calibrate {1e3 * t_cal:.0f} ms")
    if (DATA / "chessboard-opencv").is_dir():
        files = sorted((DATA / "chessboard-opencv").glob("left*.jpg"))
        imgs = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
        for method in ("classic", "sb"):
            dets, _ = detect_all(imgs, functools.partial(detect_chessboard, pattern_size=(9, 6), method=method))
            res = calibrate_intrinsics(dets, reject_outliers=False)
            print(f"intrinsics real OpenCV left*.jpg ({method:7s}): RMS {res.rms_px:.4f} px (ref 0.19633), "
                  f"fx {res.K[0, 0]:.2f} fy {res.K[1, 1]:.2f} cx {res.K[0, 2]:.2f} cy {res.K[1, 2]:.2f} "
                  "(ref 532.81 532.93 342.50 233.89)")


def bench_turntable():
    sq = 12.0
    board = make_charuco_board((8, 6), sq, 0.75 * sq, "DICT_4X4_50")
    tex = np.pad(board.generateImage((320, 240), marginSize=0), 40, constant_values=255)
    to_tex = lambda uv: np.asarray(uv) / sq * 40 + 39.5  # noqa: E731
    e = np.radians(50.0)
    eye = 330 * np.array([np.cos(e), 0, np.sin(e)])
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    R_cw = np.stack([right, np.cross(fwd, right), fwd])
    t_cw = -R_cw @ eye
    R_b0 = np.diag([1.0, -1, -1])
    t_b0 = np.array([10.0, 5, 0]) - R_b0 @ [4 * sq, 3 * sq, 0]
    readings = np.arange(0, 360, 45.0)
    rng = np.random.default_rng(11)
    imgs = []
    for r in readings:
        Rz = rot_axis_angle([0, 0, 1], np.radians(r + 7.0))
        imgs.append(render_plane(tex, to_tex, K_TRUE, DIST_TRUE, cv2.Rodrigues(R_cw @ Rz @ R_b0)[0].ravel(),
                                 R_cw @ Rz @ t_b0 + t_cw, rng=rng, noise=1.5))
    dets, _ = detect_all(imgs, functools.partial(detect_charuco, board=board))
    for kw, name in ((dict(angles_deg=readings), "known angles"),
                     (dict(angles_deg=readings, fit_scale=True), "fit scale"),
                     ({}, "free angles")):
        fit, t = timed(lambda: fit_turntable(dets, K_TRUE, DIST_TRUE, **kw), 3)
        print(f"turntable ({name:12s}, 8 views): axis err {angle_deg(fit.axis_camera, R_cw[:, 2]):.4f}° "
              f"(1σ {fit.axis_std_deg:.4f}°) [bar 0.1°], "
              f"origin err {np.linalg.norm(fit.origin_camera - t_cw):.3f} mm, "
              f"RMS {fit.rms_px:.3f} px, {1e3 * t:.0f} ms")


def bench_lights():
    K = np.array([[3000.0, 0, 959.5], [0, 3000.0, 719.5], [0, 0, 1]])
    errs, t_all = [], 0.0
    rng = np.random.default_rng(0)
    for _ in range(6):
        L = rng.normal(size=3)
        L[2] = -abs(L[2]) - 0.3
        L /= np.linalg.norm(L)
        C = np.array([0.0, 0.0, 600.0])
        img, mask = render_spheres(C, 40.0, light_dir=L, K=K)
        t0 = time.perf_counter()
        sph = detect_sphere(mask)
        hl = find_highlight(img, sph, saturation=1.0)
        _, Lf = reflect_highlight(hl.xy_px[None], C[None], 40.0, K)
        t_all += time.perf_counter() - t0
        errs.append(angle_deg(Lf[0], L))
    print(f"distant light (6 random directions): err mean {np.mean(errs):.3f}° max {np.max(errs):.3f}° "
          f"[bar 0.25°], {1e3 * t_all / 6:.0f} ms/sphere")
    R = 25.0
    centres = np.array([[-150.0, -80, 700], [150, -90, 720], [-140, 100, 690], [160, 90, 710], [0, 0, 650]])
    light = np.array([120.0, -600.0, 250.0])
    img, mask = render_spheres(centres, R, light_pos=light, lobe_deg=3.0, K=K)
    _, labels = cv2.connectedComponents(mask.astype(np.uint8))
    t0 = time.perf_counter()
    hls = []
    for C in centres:
        uv = (K @ C)[:2] / C[2]
        blob = labels == labels[int(round(uv[1])), int(round(uv[0]))]
        hls.append(find_highlight(np.where(blob, img, 0), detect_sphere(blob), saturation=1.0).xy_px)
    pl = triangulate_point_light(np.array(hls), centres, R, K, sigma_px=0.1)
    t = time.perf_counter() - t0
    dist = np.linalg.norm(light - centres.mean(0))
    print(f"point light (5 spheres): err {np.linalg.norm(pl.position_mm - light):.2f} mm = "
          f"{100 * np.linalg.norm(pl.position_mm - light) / dist:.3f}% of {dist:.0f} mm [bar 0.5%], "
          f"stated 1σ {np.sqrt(np.trace(pl.covariance_mm2)):.2f} mm, {1e3 * t:.0f} ms")
    uw = DATA / "uw-photometric-stereo"
    if uw.is_dir():
        from PIL import Image
        sph = detect_sphere(np.asarray(Image.open(uw / "chrome" / "chrome.mask.tga")))
        ref = np.loadtxt(uw / "lights.txt", skiprows=1)
        photos = [np.asarray(Image.open(uw / "chrome" / f"chrome.{i}.tga")) for i in range(12)]
        ours = np.array([light_direction_orthographic(find_highlight(p, sph).xy_px, sph) for p in photos])
        ang = angle_deg(ours * [1, -1, -1], ref)
        print(f"real UW chrome sphere vs lights.txt (a course reference): mean {ang.mean():.2f}° "
              f"max {ang.max():.2f}° "
              "(an independent re-derivation: 3° mean, 8° worst)")


def bench_sim_sphere_row():
    """The simulated lab's row of six steel balls (sims/world.py), rendered 3 x 3 supersampled:
    Lensch's flash-highlight centres and the lamp's triangulated position against ground truth."""
    import sims.world as sw
    from calibration.lights import SphereImage, locate_collinear_spheres

    world = sw.SimWorld.for_capture("spheres", None, supersample=3)
    cam, row = world.camera, world.targets[0]
    centres_w = row.points_world(0.0)
    radius = row.spec.radius_mm
    centres = centres_w @ cam.R.T + cam.t
    discs = [SphereImage(uv, float(cam.K[0, 0] * radius / np.sqrt(c @ c - radius ** 2)))
             for uv, c in zip(cam.project(centres_w), centres)]
    (flash, t_render) = timed(lambda: world.radiance({"ring_flash": True}).mean(axis=2))
    flash_hl = np.array([find_highlight(flash, d).xy_px for d in discs])
    est = locate_collinear_spheres(flash_hl, row.spec.spacing_mm, cam.K, cam.dist)
    print(f"sim steel-ball row (6 x 12.7 mm balls, frames rendered 3x3 supersampled, {t_render:.0f} s each): "
          f"flash-derived centres within {np.linalg.norm(est - centres, axis=1).max():.2f} mm")
    rng = np.random.default_rng(0)
    for az, el in ((60.0, 40.0), (-30.0, 25.0)):
        light = cam.R @ sw.light_position(az, el) + cam.t
        lamp = world.radiance({"light_position_mm": sw.light_position(az, el)}).mean(axis=2)
        hl = np.array([find_highlight(lamp, d).xy_px for d in discs])
        dist = np.linalg.norm(light - centres.mean(axis=0))
        pl = triangulate_point_light(hl, centres, radius, cam.K, cam.dist, sigma_px=0.1)
        err = np.linalg.norm(pl.position_mm - light)
        print(f"  light az {az:.0f} el {el:.0f} (true centres ): err {err:.1f} mm = {100 * err / dist:.2f}% of "
              f"{dist:.0f} mm [bar 0.5%], stated 1σ {np.sqrt(np.trace(pl.covariance_mm2)):.1f} mm (0.1 px highlights)")
        pl = triangulate_point_light(hl, est, radius, cam.K, cam.dist, sigma_px=0.1)
        err = np.linalg.norm(pl.position_mm - light)
        # flash-derived centres share one fitted line, so their errors are correlated: the 1σ comes
        # from Monte Carlo over 0.1 px noise on the flash and lamp highlights through both fits
        mc = [triangulate_point_light(hl + rng.normal(0, 0.1, hl.shape),
                                      locate_collinear_spheres(flash_hl + rng.normal(0, 0.1, flash_hl.shape),
                                                               row.spec.spacing_mm, cam.K, cam.dist),
                                      radius, cam.K, cam.dist).position_mm for _ in range(200)]
        mc_sigma = np.sqrt(np.trace(np.cov(np.array(mc).T)))
        print(f"  light az {az:.0f} el {el:.0f} (flash centres): err {err:.1f} mm = {100 * err / dist:.2f}% of "
              f"{dist:.0f} mm [bar 0.5%; Lensch ~2%], Monte Carlo 1σ {mc_sigma:.1f} mm")


def bench_polarization(size):
    rng = np.random.default_rng(1)
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w]
    D = ((0.3 + 0.2 * np.sin(xx / 13.0) ** 2)[..., None] * np.array([1.0, 0.7, 0.4])).astype(np.float32)
    lobe = np.exp(-((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (2 * (w / 6) ** 2))
    S = (lobe[..., None] * np.ones(3)).astype(np.float32)
    def obs(th):
        return D / 2 + S * np.cos(np.radians(th - 12.0)) ** 2 + rng.normal(0, 0.002, D.shape).astype(np.float32)

    rel = lambda e, t: np.sqrt(np.mean((e - t) ** 2)) / np.sqrt(np.mean(t ** 2))  # noqa: E731
    p, c = obs(12.0), obs(102.0)
    sep, t2 = timed(lambda: separate_parallel_crossed(p, c, read_sigma=0.002), 3)
    angles = [0, 45, 90, 135]
    stack = np.stack([obs(a) for a in angles])
    fit, tn = timed(lambda: fit_polarization(stack, angles), 3)
    print(f"polarization {w}x{h}x3: two-image diffuse {100 * rel(sep.diffuse, D):.2f}% specular "
          f"{100 * rel(sep.specular, S):.2f}% ({1e3 * t2:.0f} ms); "
          f"4-angle fit diffuse {100 * rel(fit.diffuse, D):.2f}% "
          f"specular {100 * rel(fit.specular, S):.2f}% ({1e3 * tn:.0f} ms) [bar 2%]")


def bench_hdr(size):
    rng = np.random.default_rng(0)
    times = np.array([1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4])
    levels = np.geomspace(400.0, 1.5e7, 40)
    X = patch_radiance(levels)
    frames = [simulate_raw(X, t, rng) for t in times]
    hdr = merge_raw_brackets(frames, times, black_level=BLACK, white_level=WHITE, gain_e_per_dn=GAIN,
                             read_noise_dn=READ)
    clip = (WHITE - BLACK) * 0.97 / times.min()
    worst = max(abs(hdr.radiance[X == v].mean() / v - 1) for v in levels[levels < 0.95 * clip])
    print(f"raw HDR merge (5 exposures, 4.5 decades): worst patch-mean error {100 * worst:.3f}% "
          "over the unsaturated "
          f"range [bar 1%]")
    h, w = size
    big = np.tile(X, (h // X.shape[0] + 1, w // X.shape[1] + 1))[:h, :w]
    frames = [simulate_raw(big, t, rng) for t in times]
    _, t = timed(lambda: merge_raw_brackets(frames, times, black_level=BLACK, white_level=WHITE,
                                            gain_e_per_dn=GAIN, read_noise_dn=READ))
    print(f"raw HDR merge {w}x{h} mosaic x 5 exposures: {t:.2f} s ({1e9 * t / (h * w * 5):.1f} ns per sample)")

    # 8-bit brackets through a known response: our weighted merge vs cv2.MergeDebevec
    h8, w8 = h // 4, w // 4
    E = np.geomspace(0.05, 400.0, w8)[None, :, None] * np.array([1.0, 0.8, 0.6]) * np.ones((h8, 1, 1))
    E = E.astype(np.float32)
    t8 = np.array([1 / 256, 1 / 64, 1 / 16, 1 / 4, 1.0, 4.0], np.float32)
    imgs = [np.clip(np.round(255 * np.clip(E * t, 0, 1) ** (1 / 2.2) + rng.normal(0, 0.5, E.shape)), 0, 255)
            .astype(np.uint8) for t in t8]
    resp = np.maximum(np.arange(256) / 255.0, 0.5 / 255) ** 2.2
    resp3 = np.stack([resp] * 3, 1).astype(np.float32)
    ours, t_ours = timed(lambda: merge_ldr(imgs, t8, resp3), 3)
    merge_cv = cv2.createMergeDebevec()
    theirs, t_cv = timed(lambda: merge_cv.process(imgs, t8, resp3.reshape(256, 1, 3)), 3)
    ok = (E * t8.min() < 0.98) & (E * t8.max() > 0.02)
    log_err = lambda a: np.sqrt(np.mean((np.log(np.maximum(a, 1e-12)) - np.log(E))[ok] ** 2))  # noqa: E731
    e_ours, e_cv = log_err(ours.radiance), log_err(theirs)
    print(f"8-bit HDR merge {w8}x{h8}x3, 6 exposures, true response: log-RMS error ours {e_ours:.4f} vs "
          f"MergeDebevec {e_cv:.4f} (error ratio {e_cv / e_ours:.1f}x better); time ours {1e3 * t_ours:.0f} ms vs "
          f"{1e3 * t_cv:.0f} ms (time ratio {t_ours / t_cv:.2f})")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer views and smaller images")
    ap.add_argument("--sim", action="store_true",
                    help="also the simulated lab's steel-ball row (renders 3 frames, minutes on 2 cores)")
    args = ap.parse_args()
    bench_intrinsics(10 if args.quick else 16)
    bench_turntable()
    bench_lights()
    if args.sim:
        bench_sim_sphere_row()
    bench_polarization((512, 512) if args.quick else (1536, 2048))
    bench_hdr((1000, 1500) if args.quick else (3000, 4000))


if __name__ == "__main__":
    main()
