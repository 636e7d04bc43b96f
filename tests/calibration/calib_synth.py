"""Synthetic ground truth for the calibration tests (no dependency on sims/).

Boards are drawn in their own plane (coarser than the image, so a bilinear lookup never
aliases) and resampled into the camera with the true projection (distortion included), then
blurred and noised.
"""
from __future__ import annotations

import cv2
import numpy as np

K_TRUE = np.array([[1600.0, 0, 642.6], [0, 1610.0, 485.4], [0, 0, 1]])
DIST_TRUE = np.array([-0.12, 0.05, 0.0008, -0.0005, 0.0])
SIZE = (1280, 960)
_RAYS: dict = {}


def camera_rays(K, dist, size, s):
    """Undistorted viewing rays (z = 1) of a ``s``-times supersampled pixel grid (cached)."""
    key = (np.asarray(K, float).tobytes(), np.asarray(dist, float).tobytes(), tuple(size), s)
    if key not in _RAYS:
        w, h = size
        ys, xs = np.mgrid[0:h * s, 0:w * s].astype(np.float64)
        px = np.stack([(xs + 0.5) / s - 0.5, (ys + 0.5) / s - 0.5], -1).reshape(-1, 1, 2)
        norm = cv2.undistortPoints(px, np.asarray(K, float), np.asarray(dist, float),
                                   criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12))
        _RAYS[key] = np.concatenate([norm.reshape(-1, 2), np.ones((norm.shape[0], 1))], 1).astype(np.float32)
    return _RAYS[key]


def chessboard_texture(cols_sq: int, rows_sq: int, px_per_square: int = 32, margin_sq: float = 1.0):
    """Board image, with the board-frame mm -> texture px scale and offset (1 square = 1 unit)."""
    m = int(margin_sq * px_per_square)
    h, w = rows_sq * px_per_square + 2 * m, cols_sq * px_per_square + 2 * m
    tex = np.full((h, w), 230, np.uint8)
    yy, xx = np.mgrid[0:rows_sq, 0:cols_sq]
    for y, x in zip(yy.ravel(), xx.ravel()):
        if (x + y) % 2 == 0:
            tex[m + y * px_per_square:m + (y + 1) * px_per_square,
                m + x * px_per_square:m + (x + 1) * px_per_square] = 25
    # Texture pixel (centre at integer) of board point (u, v): first inner corner at (1, 1) squares.
    def to_tex(uv):
        return (np.asarray(uv) + 1.0) * px_per_square + m - 0.5
    return tex, to_tex


def render_plane(texture, board_to_tex, K, dist, rvec, tvec, size=SIZE, *, noise=2.0, blur=0.7,
                 rng=None, background=120):
    """Image of a planar texture at pose (rvec, tvec) (board -> camera, board units)."""
    rng = np.random.default_rng(0) if rng is None else rng
    w, h = size
    s = 1  # texture magnified, so a bilinear lookup is alias-free
    rays = camera_rays(K, dist, size, s)
    R = cv2.Rodrigues(np.asarray(rvec, float))[0]
    # Plane z_board = 0 seen through homography H = [r1 r2 t]: board (u, v, 1) ~ H^-1 ray.
    H_inv = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, float).ravel()]))
    # rays are (x, y, 1): three element-wise planes instead of an (N, 3) x (3, 3) BLAS product,
    # whose thread start-up dominates at this size
    Hi = H_inv.astype(np.float32)
    x, y = rays[:, 0], rays[:, 1]
    lam = Hi[2, 0] * x + Hi[2, 1] * y + Hi[2, 2]
    board = np.stack([(Hi[0, 0] * x + Hi[0, 1] * y + Hi[0, 2]) / lam,
                      (Hi[1, 0] * x + Hi[1, 1] * y + Hi[1, 2]) / lam], axis=1)
    tex_xy = board_to_tex(board).astype(np.float32)
    mapx = tex_xy[:, 0].reshape(h * s, w * s)
    mapy = tex_xy[:, 1].reshape(h * s, w * s)
    hi = cv2.remap(texture.astype(np.float32), mapx, mapy, cv2.INTER_LINEAR,
                   borderMode=cv2.BORDER_CONSTANT, borderValue=float(background))
    hi[(lam < 0).reshape(h * s, w * s)] = background
    img = hi
    if blur:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img = img + np.float32(noise) * rng.standard_normal(img.shape, dtype=np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def board_poses(n, rng, *, board_wh=(10, 7), dist_range=(19, 28), tilt_deg=45.0, offset=0.25,
                K=K_TRUE, dist=DIST_TRUE, size=SIZE, margin=(-1, -1, 1, 1)):
    """Varied poses (board -> camera, board units) whose board (inner extent ``board_wh`` plus
    ``margin`` squares) stays inside the image."""
    poses = []
    x0, y0, x1, y1 = margin
    outline = np.array([[x0, y0, 0], [board_wh[0] + x1, y0, 0], [x0, board_wh[1] + y1, 0],
                        [board_wh[0] + x1, board_wh[1] + y1, 0]], float)
    centre = np.array([board_wh[0] / 2, board_wh[1] / 2, 0])
    while len(poses) < n:
        ang = np.radians(rng.uniform(-tilt_deg, tilt_deg, 3)) * np.array([1, 1, 0.5])
        R = cv2.Rodrigues(ang)[0]
        z = rng.uniform(*dist_range)
        t = np.array([rng.uniform(-offset, offset) * z, rng.uniform(-offset, offset) * 0.75 * z, z]) - R @ centre
        rvec = cv2.Rodrigues(R)[0].ravel()
        pr = cv2.projectPoints(outline, rvec, t, K, dist)[0].reshape(-1, 2)
        if pr.min() < 5 or pr[:, 0].max() > size[0] - 6 or pr[:, 1].max() > size[1] - 6:
            continue
        poses.append((rvec, t))
    return poses


def rot_axis_angle(axis, angle_rad):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return cv2.Rodrigues(axis * angle_rad)[0]
