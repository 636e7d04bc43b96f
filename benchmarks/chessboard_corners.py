"""Chessboard corner accuracy of ``calibration.targets.detect_chessboard``'s methods.

    python benchmarks/chessboard_corners.py [--views N]

Independent renders: boards drawn in their own plane and resampled through a known camera with
lens distortion, blur and noise (the calibration tests' ``calib_synth``, other seeds and noise
levels than the tests use); the error is each corner's distance from the true projection of the
board point. Real: OpenCV's 13 ``left*.jpg`` photos (``../shared/data/chessboard-opencv``), where
the calibration RMS and K are compared with OpenCV's own test values.
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
sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "calibration")]

from calib_synth import DIST_TRUE, K_TRUE, board_poses, chessboard_texture, render_plane  # noqa: E402

from calibration.intrinsics import calibrate_intrinsics, detect_all  # noqa: E402
from calibration.targets import chessboard_object_points, detect_chessboard  # noqa: E402

METHODS = ("classic", "sb", "sb_accuracy")
DATA = ROOT.parent / "shared" / "data" / "chessboard-opencv"


def synthetic(n_views: int, seed: int, noise: float) -> None:
    rng = np.random.default_rng(seed)
    tex, to_tex = chessboard_texture(12, 9)
    poses = board_poses(n_views, rng)
    imgs = [render_plane(tex, to_tex, K_TRUE, DIST_TRUE, r, t, rng=rng, noise=noise) for r, t in poses]
    obj = chessboard_object_points((11, 8), 1.0)
    truth = [cv2.projectPoints(obj, r, t, K_TRUE, DIST_TRUE)[0].reshape(-1, 2) for r, t in poses]
    for method in METHODS:
        t0 = time.perf_counter()
        dets, missing = detect_all(imgs, functools.partial(detect_chessboard, pattern_size=(11, 8), method=method),
                                   names=[str(i) for i in range(len(imgs))])
        dt = (time.perf_counter() - t0) / len(imgs)
        rms = [np.sqrt(np.mean(np.sum((_ordered(d.image_points, truth[int(d.frame)]) - truth[int(d.frame)]) ** 2,
                                      axis=1))) for d in dets]
        print(f"renders seed {seed} noise {noise}: {method:11s} corner RMS {np.sqrt(np.mean(np.square(rms))):.4f} px "
              f"(views {len(dets)}/{len(imgs)}, worst view {max(rms):.4f}) {1e3 * dt:.0f} ms/view")


def _ordered(pts: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``pts`` in the corner order (of the two a chessboard allows) nearest ``truth``."""
    return pts if np.linalg.norm(pts - truth) <= np.linalg.norm(pts[::-1] - truth) else pts[::-1]


def real() -> None:
    files = sorted(DATA.glob("left*.jpg"))
    imgs = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    for method in METHODS:
        dets, missing = detect_all(imgs, functools.partial(detect_chessboard, pattern_size=(9, 6), method=method))
        res = calibrate_intrinsics(dets, reject_outliers=False)
        print(f"OpenCV left*.jpg {method:11s}: {len(dets)} views, RMS {res.rms_px:.4f} px (OpenCV's test: 0.19633), "
              f"fx {res.K[0, 0]:.2f} fy {res.K[1, 1]:.2f} cx {res.K[0, 2]:.2f} cy {res.K[1, 2]:.2f} "
              "(532.81 532.93 342.50 233.89)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=8)
    args = ap.parse_args()
    for seed, noise in ((101, 1.0), (202, 2.5)):
        synthetic(args.views, seed, noise)
    if DATA.is_dir():
        real()


if __name__ == "__main__":
    main()
