"""Camera intrinsics from planar-target views (Zhang's method via OpenCV).

Frames: image pixels x right, y down (pixel centres at integers); camera frame OpenCV
(x right, y down, z forward); board frame z = 0 on the board, millimetres.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import cv2
import numpy as np

from . import _validate
from .errors import DegenerateFit, InvalidInput, TargetNotFound, TooFewViews
from .targets import TargetDetection

__all__ = [
    "RejectedView", "IntrinsicsResult", "detect_all", "corner_coverage", "calibrate_intrinsics",
]

_MIN_VIEWS = 3
# Views whose board normals all lie within this cone cannot separate focal length from depth.
_MIN_TILT_SPREAD_DEG = 5.0
#: k3 counts as determined when its 1-sigma moves the farthest image corner by at most this
#: (pixels) and the fitted k3 exceeds twice its sigma; else it is fixed at 0 (a 5-parameter fit
#: of 15 views can put corners pixels off the true distortion while its RMS looks fine)
K3_MAX_CORNER_STD_PX = 0.5


@dataclass(frozen=True)
class RejectedView:
    """A view left out of the calibration, and why."""

    frame: str
    rms_px: float | None
    reason: str


@dataclass(frozen=True)
class IntrinsicsResult:
    """Result of :func:`calibrate_intrinsics`.

    Attributes
    ----------
    K : ndarray of shape (3, 3)
        Intrinsic matrix, pixels.
    dist : ndarray of shape (5,) or (k,)
        OpenCV distortion coefficients (k1, k2, p1, p2, k3[, ...]).
    image_size : (int, int)
        ``(width, height)``, pixels.
    rms_px : float
        RMS reprojection error over all corners of the kept views, pixels.
    per_view_rms_px : ndarray of shape (V,)
        RMS reprojection error of each kept view, pixels.
    K_std : ndarray of shape (4,)
        Standard deviations of ``(fx, fy, cx, cy)``, pixels.
    dist_std : ndarray, same shape as ``dist``
        Standard deviations of the distortion coefficients.
    rvecs, tvecs : ndarray of shape (V, 3)
        Board-to-camera pose of each kept view (Rodrigues vector, rad; translation, mm).
    frames : list of str
        Names of the kept views, in order.
    rejected : list of RejectedView
        Views removed as outliers or unusable, with the reason.
    coverage : ndarray of shape (gy, gx), int
        Corners that fell in each cell of a grid over the image (kept views).
    model_note : str
        How the distortion model was chosen: empty when used as asked, else why k3 was fixed
        at 0 (with the free fit's k3, its sigma and their effect at the image corner).
    """

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    rms_px: float
    per_view_rms_px: np.ndarray
    K_std: np.ndarray
    dist_std: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    frames: list[str]
    rejected: list[RejectedView] = field(default_factory=list)
    coverage: np.ndarray | None = None
    model_note: str = ""

    @property
    def coverage_fraction(self) -> float:
        """Fraction of coverage-grid cells that hold at least one corner."""
        return float(np.mean(self.coverage > 0)) if self.coverage is not None else 0.0

    def report(self) -> str:
        """A human-readable summary (parameters with 1-sigma, per-view errors, rejections)."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        s = self.K_std
        lines = [
            f"intrinsics from {len(self.frames)} views, RMS {self.rms_px:.4f} px",
            f"  fx = {fx:.3f} ± {s[0]:.3f}  fy = {fy:.3f} ± {s[1]:.3f} px",
            f"  cx = {cx:.3f} ± {s[2]:.3f}  cy = {cy:.3f} ± {s[3]:.3f} px",
            "  dist = " + ", ".join(f"{d:.5f}±{e:.5f}" for d, e in zip(self.dist, self.dist_std)),
            f"  corner coverage: {100 * self.coverage_fraction:.0f}% of grid cells",
        ]
        lines += [f"  view {f}: {e:.4f} px" for f, e in zip(self.frames, self.per_view_rms_px)]
        lines += [f"  rejected {r.frame}: {r.reason}" for r in self.rejected]
        lines += [f"  {self.model_note}"] if self.model_note else []
        return "\n".join(lines)


def detect_all(images: Sequence, detector: Callable[..., TargetDetection], *,
               names: Sequence[str] | None = None, on_missing: str = "skip"
               ) -> tuple[list[TargetDetection], list[RejectedView]]:
    """Run ``detector(image, frame=name)`` over frames.

    Parameters
    ----------
    images : sequence of ndarray
        The photos.
    detector : callable
        E.g. ``functools.partial(detect_chessboard, pattern_size=(9, 6), square_size=25.0)``.
    names : sequence of str, optional
        Frame names (default ``'frame 0'``, ...), used in errors and reports.
    on_missing : {'skip', 'raise'}
        ``'skip'`` (default: a folder of photos usually holds a few without the whole board):
        a frame without a target is listed in ``missing`` with the detector's reason.
        ``'raise'``: it raises :class:`TargetNotFound` naming it.

    Returns
    -------
    detections : list of TargetDetection
        The frames where the target was found, in order.
    missing : list of RejectedView
        The frames skipped, each with the reason (the report of what was left out).
    """
    if on_missing not in ("raise", "skip"):
        raise InvalidInput(f"on_missing must be 'raise' or 'skip', got {on_missing!r}")
    names = [f"frame {i}" for i in range(len(images))] if names is None else list(names)
    if len(names) != len(images):
        raise InvalidInput(f"names has {len(names)} entries for {len(images)} images")
    found, missing = [], []
    for img, name in zip(images, names):
        try:
            found.append(detector(img, frame=name))
        except TargetNotFound as err:
            if on_missing == "raise":
                raise
            missing.append(RejectedView(name, None, str(err)))
    return found, missing


def corner_coverage(image_points: Sequence[np.ndarray], image_size: tuple[int, int],
                    grid: tuple[int, int] = (8, 6)) -> np.ndarray:
    """Count corners per cell of a ``grid = (gx, gy)`` laid over the image.

    Parameters
    ----------
    image_points : sequence of ndarray of shape (N_i, 2)
        Corner pixels of each view.
    image_size : (int, int)
        ``(width, height)``, pixels.
    grid : (int, int)
        Cells across and down.

    Returns
    -------
    ndarray of shape (gy, gx), int64
        Row 0 is the top of the image. Empty cells show where more views are needed
        (distortion is poorly constrained there).
    """
    w, h = (_validate.integer(v, "image_size", minimum=1) for v in image_size)
    gx, gy = (_validate.integer(v, "grid", minimum=1) for v in grid)
    pts = np.concatenate([_validate.array(p, f"image_points[{i}]", shape=(-1, 2))
                          for i, p in enumerate(image_points)]) if len(image_points) else np.zeros((0, 2))
    counts, _, _ = np.histogram2d(pts[:, 1], pts[:, 0], bins=(gy, gx), range=((-0.5, h - 0.5), (-0.5, w - 0.5)))
    return counts.astype(np.int64)


def _calibrate(dets, image_size, flags):
    obj = [d.object_points.astype(np.float32) for d in dets]
    img = [d.image_points.astype(np.float32) for d in dets]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    try:
        out = cv2.calibrateCameraExtended(obj, img, image_size, None, None, flags=flags, criteria=crit)
    except cv2.error as err:
        raise DegenerateFit(f"calibrateCamera failed on {len(dets)} views: {err.msg or err}") from None
    rms, K, dist, rvecs, tvecs, std_in, _std_ex, per_view = out
    return dict(rms=float(rms), K=K, dist=dist.ravel(), rvecs=np.asarray(rvecs).reshape(-1, 3),
                tvecs=np.asarray(tvecs).reshape(-1, 3), std=std_in.ravel(),
                per_view=np.asarray(per_view).ravel())


def calibrate_intrinsics(detections: Sequence[TargetDetection], image_size: tuple[int, int] | None = None,
                         *, flags: int = 0, reject_outliers: bool = True, outlier_sigma: float = 4.0,
                         min_view_rms_px: float = 0.3, min_views: int = _MIN_VIEWS,
                         coverage_grid: tuple[int, int] = (8, 6), choose_k3: bool = True) -> IntrinsicsResult:
    """Calibrate K and lens distortion from planar-target detections.

    Runs ``cv2.calibrateCameraExtended`` (Zhang), then removes outlier views one at a time —
    the worst view while its RMS exceeds ``max(median + outlier_sigma * 1.4826 * MAD,
    min_view_rms_px)`` — re-calibrating after each removal, down to ``min_views``.

    The distortion model is chosen by evidence (``choose_k3``): when ``flags`` leave k3 free,
    a k3 the views do not determine (its 1-sigma moves the farthest image corner by more than
    :data:`K3_MAX_CORNER_STD_PX`, or it is within 2 sigma of 0) is fixed at 0 and the fit
    repeated; ``model_note`` says so.

    Parameters
    ----------
    detections : sequence of TargetDetection
        One per view (see :func:`~calibration.targets.detect_chessboard`,
        :func:`~calibration.targets.detect_charuco`, :func:`detect_all`).
    image_size : (int, int), optional
        ``(width, height)`` in pixels; default: from the detections (must agree).
    flags : int
        ``cv2.CALIB_*`` flags (e.g. ``cv2.CALIB_RATIONAL_MODEL``, ``cv2.CALIB_FIX_K3``).
    reject_outliers : bool
        Remove outlier views as above.
    outlier_sigma : float
        Robust z-score above which a view is an outlier.
    min_view_rms_px : float
        Views with RMS below this (pixels) are never rejected.
    min_views : int
        Fewest views accepted (>= 3).
    coverage_grid : (int, int)
        Grid ``(gx, gy)`` for the corner coverage map.
    choose_k3 : bool
        Fix an undetermined k3 at 0 (above); False keeps the model ``flags`` ask for.

    Returns
    -------
    IntrinsicsResult

    Raises
    ------
    TooFewViews
        Fewer than ``min_views`` detections.
    DegenerateFit
        All board orientations are (nearly) parallel, or OpenCV could not solve.
    """
    dets = list(detections)
    if min_views < _MIN_VIEWS:
        raise InvalidInput(f"min_views must be >= {_MIN_VIEWS}, got {min_views}")
    if len(dets) < min_views:
        raise TooFewViews("intrinsics calibration", have=len(dets), need=min_views)
    for i, d in enumerate(dets):
        if not isinstance(d, TargetDetection):
            raise InvalidInput(f"detections[{i}] must be a TargetDetection, got {type(d).__name__}")
        _validate.array(d.image_points, f"detections[{i}].image_points", shape=(-1, 2))
        _validate.array(d.object_points, f"detections[{i}].object_points", shape=(len(d.image_points), 3))
        if len(d.image_points) < 6:
            raise TooFewViews(f"detections[{i}] ({d.frame}) corners", have=len(d.image_points), need=6)
    sizes = {d.image_size for d in dets}
    if image_size is None:
        if len(sizes) != 1:
            raise InvalidInput(f"detections come from images of different sizes {sorted(sizes)}; "
                             "calibrate each camera/resolution separately")
        image_size = sizes.pop()
    image_size = tuple(_validate.integer(v, "image_size", minimum=1) for v in image_size)
    if len(image_size) != 2:
        raise InvalidInput(f"image_size must be (width, height), got {image_size}", argument="image_size")
    names = [d.frame or f"view {i}" for i, d in enumerate(dets)]

    rejected: list[RejectedView] = []
    sol = _calibrate(dets, image_size, flags)
    while reject_outliers and len(dets) > min_views:
        e = sol["per_view"]
        med = np.median(e)
        limit = max(med + outlier_sigma * 1.4826 * np.median(np.abs(e - med)), min_view_rms_px)
        worst = int(np.argmax(e))
        if e[worst] <= limit:
            break
        rejected.append(RejectedView(names[worst], float(e[worst]),
                                     f"reprojection RMS {e[worst]:.3f} px > limit {limit:.3f} px"))
        del dets[worst], names[worst]
        sol = _calibrate(dets, image_size, flags)

    note = ""
    if choose_k3 and not flags & (cv2.CALIB_FIX_K3 | cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL
                                  | cv2.CALIB_TILTED_MODEL):
        undetermined = _k3_undetermined(sol, image_size)
        if undetermined:
            note = f"k3 fixed at 0: {undetermined}"
            sol = _calibrate(dets, image_size, flags | cv2.CALIB_FIX_K3)

    # Board normals in the camera frame: third column of each rotation.
    normals = np.array([cv2.Rodrigues(r)[0][:, 2] for r in sol["rvecs"]])
    spread = np.degrees(np.arccos(np.clip(normals @ normals.T, -1, 1))).max()
    if spread < _MIN_TILT_SPREAD_DEG:
        raise DegenerateFit(f"all {len(dets)} board orientations lie within {spread:.1f}° of each other "
                            f"(need > {_MIN_TILT_SPREAD_DEG}°): tilt the board differently between views")
    std = sol["std"]
    n_dist = sol["dist"].size
    return IntrinsicsResult(
        K=sol["K"], dist=sol["dist"], image_size=image_size, rms_px=sol["rms"],
        per_view_rms_px=sol["per_view"], K_std=std[:4].copy(), dist_std=std[4:4 + n_dist].copy(),
        rvecs=sol["rvecs"], tvecs=sol["tvecs"], frames=names, rejected=rejected,
        coverage=corner_coverage([d.image_points for d in dets], image_size, coverage_grid), model_note=note)


def _k3_undetermined(sol: dict, image_size: tuple[int, int]) -> str:
    """Why the free fit's k3 is not determined (empty when it is): its sigma's effect at the
    farthest image corner (radial displacement ``f k3 r^7``), or k3 within 2 sigma of 0."""
    K, k3, s3 = sol["K"], float(sol["dist"][4]), float(sol["std"][4 + 4])
    w, h = image_size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    r = np.max(np.hypot((corners[:, 0] - K[0, 2]) / K[0, 0], (corners[:, 1] - K[1, 2]) / K[1, 1]))
    corner_std_px = s3 * r ** 7 * float(np.sqrt(K[0, 0] * K[1, 1]))
    if corner_std_px > K3_MAX_CORNER_STD_PX:
        return (f"the views leave it uncertain by {corner_std_px:.2f} px at the image corner "
                f"(k3 = {k3:.4g} ± {s3:.2g}; > {K3_MAX_CORNER_STD_PX} px): add views that put the board "
                "into the image corners")
    if abs(k3) < 2 * s3:
        return f"k3 = {k3:.4g} ± {s3:.2g} is not distinguishable from 0"
    return ""
