"""Calibrated pinhole camera with OpenCV distortion, placed in the world (turntable) frame.

Frames: world = turntable frame (origin on the axis at the platter surface, +z up the axis,
millimetres); camera frame = OpenCV (x right, y down, z forward). ``R, t`` map world to camera:
``X_cam = R @ X_world + t``.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .frames import linear_rows

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)


@functools.lru_cache(maxsize=4)
def _undistorted_grid(K: tuple, dist: tuple, width: int, height: int) -> np.ndarray:
    """Normalised undistorted coordinates (x, y) of every pixel centre, row-major, (H*W, 2),
    read-only. Cached: the iterative undistortion costs ~0.4 s per megapixel, and a simulated
    session renders many frames through one fixed lens."""
    ys, xs = np.mgrid[0:height, 0:width]
    px = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(px, np.asarray(K).reshape(3, 3), np.asarray(dist), None, None,
                             criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)
    xy.flags.writeable = False
    return xy


#: the most pixels whose world directions :func:`_world_directions` keeps (24 bytes each)
_KEPT_DIRECTIONS_MAX = 1 << 21


@functools.lru_cache(maxsize=4)
def _world_directions(K: tuple, dist: tuple, R: tuple, width: int, height: int) -> np.ndarray:
    """Unit world directions of every pixel centre's ray, row-major, (H*W, 3), read-only: what
    :meth:`CameraModel.row_rays` returns, computed once per lens, orientation and image size
    (a simulated session renders many frames through one fixed camera)."""
    camera = CameraModel(np.asarray(K).reshape(3, 3), width, height, dist=np.asarray(dist),
                         R=np.asarray(R).reshape(3, 3))
    d = camera._directions(_undistorted_grid(K, dist, width, height))
    d.flags.writeable = False
    return d


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics, distortion and pose of one view.

    Attributes
    ----------
    K : ndarray of shape (3, 3)
        Intrinsic matrix, pixels.
    width, height : int
        Image size, pixels.
    dist : ndarray of shape (5,) or (k,)
        OpenCV distortion coefficients (k1, k2, p1, p2, k3, ...); zeros for an ideal lens.
    R : ndarray of shape (3, 3)
        Rotation world -> camera.
    t : ndarray of shape (3,)
        Translation world -> camera, millimetres.
    """

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=float).reshape(3, 3))
        object.__setattr__(self, "dist", np.asarray(self.dist, dtype=float).ravel())
        object.__setattr__(self, "R", np.asarray(self.R, dtype=float).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=float).reshape(3))

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def look_at(cls, eye_mm, target_mm=(0.0, 0.0, 0.0), *, up=(0.0, 0.0, 1.0), width: int = 640,
                height: int = 480, fov_deg: float | None = None, focal_px: float | None = None,
                dist=None) -> "CameraModel":
        """A camera at ``eye_mm`` looking at ``target_mm`` (world frame, mm), world ``up`` pointing
        up in the image. Give the horizontal field of view ``fov_deg`` or ``focal_px``."""
        eye = np.asarray(eye_mm, float)
        fwd = np.asarray(target_mm, float) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(up, float))
        if np.linalg.norm(right) < 1e-9:
            raise ValueError("look_at: 'up' is parallel to the viewing direction")
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])
        if focal_px is None:
            focal_px = 0.5 * width / np.tan(np.radians(fov_deg if fov_deg is not None else 40.0) / 2)
        K = np.array([[focal_px, 0, (width - 1) / 2], [0, focal_px, (height - 1) / 2], [0, 0, 1]])
        return cls(K=K, width=width, height=height, dist=np.zeros(5) if dist is None else dist,
                   R=R, t=-R @ eye)

    def with_pose(self, R, t) -> "CameraModel":
        return replace(self, R=np.asarray(R, float), t=np.asarray(t, float))

    # -- geometry -----------------------------------------------------------------------------
    @property
    def center(self) -> np.ndarray:
        """Camera centre in the world frame, mm, shape (3,)."""
        return -self.R.T @ self.t

    @property
    def rvec(self) -> np.ndarray:
        return cv2.Rodrigues(self.R)[0].ravel()

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """Pixel coordinates (x right, y down; pixel centres at integers) of world points (N, 3)
        -> (N, 2), distortion applied."""
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        uv, _ = cv2.projectPoints(pts, self.rvec, self.t, self.K, self.dist)
        return uv.reshape(-1, 2)

    def depth(self, points_world: np.ndarray) -> np.ndarray:
        """z in the camera frame (mm) of world points (N, 3) -> (N,)."""
        return np.asarray(points_world, float).reshape(-1, 3) @ self.R[2] + self.t[2]

    def pixel_rays(self, pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """World-frame rays through pixels.

        Parameters
        ----------
        pixels : ndarray of shape (N, 2), optional
            Pixel coordinates (x, y); default: every pixel centre, row-major (N = H*W).

        Returns
        -------
        origins : ndarray of shape (N, 3)
            The camera centre, mm.
        directions : ndarray of shape (N, 3)
            Unit directions in the world frame (lens distortion removed).
        """
        if pixels is None:
            ys, xs = np.mgrid[0:self.height, 0:self.width]
            pixels = np.stack([xs.ravel(), ys.ravel()], axis=1)
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if np.any(self.dist):
            xy = cv2.undistortPoints(px, self.K, self.dist, None, None,
                                     criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)
        else:
            Kinv = np.linalg.inv(self.K)
            xy = px.reshape(-1, 2) @ Kinv[:2, :2].T + Kinv[:2, 2]
        return np.broadcast_to(self.center, (len(xy), 3)).copy(), self._directions(xy)

    def row_rays(self, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
        """World-frame rays through the pixel centres of image rows ``[r0, r1)``, row-major:
        origins (N, 3), a read-only broadcast of the camera centre (mm), and unit directions
        (N, 3), N = (r1 - r0) * width. Same rays as :meth:`pixel_rays`; the undistortion of
        the whole grid is computed once per lens and image size and cached."""
        if not 0 <= r0 <= r1 <= self.height:
            raise ValueError(f"rows [{r0}, {r1}) must lie within [0, {self.height}]")
        W = self.width
        if np.any(self.dist) and W * self.height <= _KEPT_DIRECTIONS_MAX:
            d = _world_directions(tuple(self.K.ravel()), tuple(self.dist), tuple(self.R.ravel()), W,
                                  self.height)[r0 * W:r1 * W]
        elif np.any(self.dist):
            grid = _undistorted_grid(tuple(self.K.ravel()), tuple(self.dist), W, self.height)
            d = self._directions(grid[r0 * W:r1 * W])
        else:  # d = R^T K^-1 (x, y, 1) = x a + y b + c: an outer sum, no per-pixel product
            a, b, c = (self.R.T @ np.linalg.inv(self.K)).T
            d = (np.arange(W, dtype=np.float64)[None, :, None] * a
                 + (np.arange(r0, r1, dtype=np.float64)[:, None, None] * b + c)).reshape(-1, 3)
            d /= np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
        return np.broadcast_to(self.center, d.shape), d

    def _directions(self, xy: np.ndarray) -> np.ndarray:
        """Unit world directions (N, 3) of normalised camera coordinates ``xy`` (N, 2)."""
        d_cam = np.empty((len(xy), 3))
        d_cam[:, :2] = xy
        d_cam[:, 2] = 1.0
        d = linear_rows(self.R.T, d_cam)  # R^T (x, y, 1)
        d /= np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
        return d
