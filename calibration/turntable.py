"""Turntable axis and object pose from a target imaged at several turntable angles.

Frames
------
camera : OpenCV (x right, y down, z forward), millimetres.
world : the turntable (object) frame, which turns with the platter. Origin on the rotation axis
    at the height of the target's origin, +z up the axis (the sign for which +z points up in the
    image, i.e. has a negative camera-y component), +x along the target's x axis (projected
    perpendicular to the axis) at the reference orientation, +y = z × x.

Turntable angles are degrees. The fitted model is: the platter turns by
``phi = scale * reading + offset`` (right-handed about +z; ``phi = 0`` is the reference
orientation, the target's pose in the first view), so the world-to-camera pose for any reading
is ``R(reading) = R_ref @ Rz(phi)``, ``t(reading) = t_ref``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import cv2
import numpy as np

from . import _fit, _validate
from .errors import DegenerateFit, InvalidInput, TooFewViews
from .targets import TargetDetection

__all__ = ["TurntableFit", "fit_turntable", "consistent_corner_order", "lab_frame"]


def _rot(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) about unit ``axis`` by ``angle`` (n,) radians (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.asarray(angle, float)[:, None, None]
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * (k @ k)


def _basis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to unit ``a`` and to each other."""
    helper = np.eye(3)[np.argmin(np.abs(a))]
    b1 = np.cross(a, helper)
    b1 /= np.linalg.norm(b1)
    return b1, np.cross(a, b1)


@dataclass(frozen=True)
class TurntableFit:
    """Result of :func:`fit_turntable`.

    Attributes
    ----------
    axis_camera : ndarray of shape (3,)
        Unit direction of the rotation axis (world +z) in the camera frame.
    origin_camera : ndarray of shape (3,)
        World origin (on the axis, at the target origin's height) in the camera frame, mm.
    R_ref : ndarray of shape (3, 3)
        World-to-camera rotation at platter angle ``phi = 0``.
    angle_scale : float
        ``phi = angle_scale * reading + angle_offset_deg``; +1 for a turntable whose reading
        grows counter-clockwise seen from +z, -1 for clockwise. Fitted when asked, else ±1.
    angle_offset_deg : float
        Platter angle (deg) at reading 0.
    view_angles_deg : ndarray of shape (V,)
        Fitted platter angle ``phi`` of each view, deg (view 0 is 0).
    target_in_world : tuple of ndarray
        ``(R, t)`` target-to-world pose (mm), constant since the target turns with the platter.
    per_view_rms_px : ndarray of shape (V,)
        Reprojection RMS per view, pixels.
    rms_px : float
        Overall reprojection RMS, pixels.
    axis_std_deg : float
        1-sigma angular uncertainty of the axis direction, deg.
    angles_known : bool
        Whether turntable readings were given (else ``view_angles_deg`` are free fits).
    fit_status : int
        ``scipy.optimize.least_squares`` status of the bundle adjustment (1-4: converged).
    fit_message : str
        The solver's termination message.
    """

    axis_camera: np.ndarray
    origin_camera: np.ndarray
    R_ref: np.ndarray
    angle_scale: float
    angle_offset_deg: float
    view_angles_deg: np.ndarray
    target_in_world: tuple[np.ndarray, np.ndarray]
    per_view_rms_px: np.ndarray
    rms_px: float
    axis_std_deg: float
    angles_known: bool
    fit_status: int = 1
    fit_message: str = ""

    def platter_angle_deg(self, reading_deg) -> np.ndarray:
        """Platter angle ``phi`` (deg) for turntable readings (deg)."""
        return self.angle_scale * np.asarray(reading_deg, float) + self.angle_offset_deg

    def world_to_camera(self, reading_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """World-to-camera pose ``(R (3, 3), t (3,) mm)`` at turntable reading ``reading_deg``:
        ``X_cam = R @ X_world + t``."""
        phi = np.radians(float(self.platter_angle_deg(reading_deg)))
        return self.R_ref @ _rot(np.array([0.0, 0.0, 1.0]), np.array([phi]))[0], self.origin_camera.copy()

    def world_to_camera_at_phi(self, phi_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """World-to-camera pose at platter angle ``phi_deg`` (deg) directly."""
        phi = np.radians(float(phi_deg))
        return self.R_ref @ _rot(np.array([0.0, 0.0, 1.0]), np.array([phi]))[0], self.origin_camera.copy()


def fit_turntable(detections: Sequence[TargetDetection], K, dist=None, angles_deg=None, *,
                  fit_scale: bool = False, max_evaluations: int | None = None) -> TurntableFit:
    """Fit the turntable axis, the angle model and the object pose from target views.

    Each view is solved with ``cv2.solvePnP``; the relative rotations give an initial axis
    (principal direction of the Rodrigues vectors) and a point on it (linear least squares);
    then one bundle adjustment over all corners of all views (``scipy.optimize.least_squares``,
    residuals in pixels) refines the axis (2 dof), the point (2 dof), the reference target pose
    (6) and either the angle model (scale when ``fit_scale``) or one free angle per view.

    Parameters
    ----------
    detections : sequence of TargetDetection
        The same target (rigidly on the platter) in every view; corners must be consistently
        identified across views (use ChArUco: a plain chessboard's numbering may flip).
    K : array_like of shape (3, 3)
        Camera matrix, pixels.
    dist : array_like, optional
        OpenCV distortion coefficients (default none).
    angles_deg : array_like of shape (V,), optional
        Turntable readings of the views, deg. Without them each view's angle is fitted.
    fit_scale : bool
        Also fit the reading-to-angle scale (needs ``angles_deg``).
    max_evaluations : int, optional
        Residual evaluations the bundle adjustment may use (scipy's default when None).

    Returns
    -------
    TurntableFit

    Raises
    ------
    NotConverged
        The bundle adjustment stopped before converging.
    TooFewViews
        Fewer than 3 views (2 with known angles).
    DegenerateFit
        The views span less than 10° of rotation, or the rotations share no common axis.
    """
    dets = list(detections)
    K, dist = _validate.camera(K, dist)
    for i, d in enumerate(dets):
        if not isinstance(d, TargetDetection):
            raise InvalidInput(f"detections[{i}] must be a TargetDetection, got {type(d).__name__}",
                               argument="detections")
        _validate.array(d.image_points, f"detections[{i}].image_points", shape=(-1, 2))
        _validate.array(d.object_points, f"detections[{i}].object_points", shape=(len(d.image_points), 3))
        if len(d.image_points) < 4:
            raise TooFewViews(f"detections[{i}] ({d.frame}) corners for a pose", have=len(d.image_points), need=4)
    known = angles_deg is not None
    if known:
        readings = _validate.array(angles_deg, "angles_deg").ravel()
        if readings.shape != (len(dets),):
            raise InvalidInput(f"angles_deg must have one reading per detection ({len(dets)}), "
                             f"got shape {readings.shape}")
    elif fit_scale:
        raise InvalidInput("fit_scale=True needs angles_deg (the turntable readings)")
    need = 2 if known and not fit_scale else 3
    if len(dets) < need:
        raise TooFewViews("turntable fit", have=len(dets), need=need)

    obj = [d.object_points.astype(float) for d in dets]
    norm = [cv2.undistortPoints(d.image_points.reshape(-1, 1, 2).astype(float), K, dist).reshape(-1, 2)
            for d in dets]
    Rs, ts = [], []
    for i, d in enumerate(dets):
        ok, rvec, tvec = cv2.solvePnP(obj[i], d.image_points.astype(float), K, dist,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise DegenerateFit(f"solvePnP failed for view {i} ({d.frame})")
        Rs.append(cv2.Rodrigues(rvec)[0])
        ts.append(tvec.ravel())
    Rs, ts = np.array(Rs), np.array(ts)

    # Initial axis: relative rotations R_i R_0^T are all about the same axis.
    omegas = np.array([cv2.Rodrigues(R @ Rs[0].T)[0].ravel() for R in Rs[1:]])
    if np.linalg.norm(omegas, axis=1).max() < np.radians(10):
        raise DegenerateFit("the views span less than 10° of turntable rotation; the axis is undetermined")
    a = np.linalg.svd(omegas)[2][0]
    if a[1] > 0:  # +z up in the image: negative camera-y component
        a = -a
    phi0 = omegas @ a
    if np.linalg.norm(omegas - np.outer(phi0, a), axis=1).max() > np.radians(5):
        raise DegenerateFit("the target's pose changes are not rotations about one axis "
                            "(did the target move on the platter, or corner numbering flip?)")
    phis = np.r_[0.0, phi0]
    Rrel = _rot(a, phis)
    A = (np.eye(3) - Rrel[1:]).reshape(-1, 3)
    b = (ts[1:] - Rrel[1:] @ ts[0]).ravel()
    c = np.linalg.lstsq(A, b, rcond=None)[0]

    b1, b2 = _basis(a)
    fx = K[0, 0]
    n_views = len(dets)
    if known:
        dr = readings - readings[0]
        # Rotation sense: compare angles on the circle (Rodrigues angles wrap at 180°).
        s0 = 1.0 if np.sum(np.cos(phis - np.radians(dr))) >= np.sum(np.cos(phis + np.radians(dr))) else -1.0
    x0 = np.r_[0.0, 0.0, 0.0, 0.0, cv2.Rodrigues(Rs[0])[0].ravel(), ts[0],
               [s0] if (known and fit_scale) else [], [] if known else phis[1:]]

    def unpack(x):
        ax = a + x[0] * b1 + x[1] * b2
        ax = ax / np.linalg.norm(ax)
        cc = c + x[2] * b1 + x[3] * b2
        R0 = cv2.Rodrigues(x[4:7])[0]
        t0 = x[7:10]
        if known:
            ph = (x[10] if fit_scale else s0) * np.radians(dr)
        else:
            ph = np.r_[0.0, x[10:]]
        return ax, cc, R0, t0, ph

    def residuals(x):
        ax, cc, R0, t0, ph = unpack(x)
        Rr = _rot(ax, ph)
        out = []
        for i in range(n_views):  # loop over views only; corners are vectorised
            X = (obj[i] @ R0.T + t0 - cc) @ Rr[i].T + cc
            out.append(fx * (X[:, :2] / X[:, 2:3] - norm[i]))
        return np.concatenate(out).ravel()

    sol = _fit.solve(residuals, x0, what="turntable bundle adjustment", max_evaluations=max_evaluations,
                     method="lm", x_scale="jac")
    ax, cc, R0, t0, ph = unpack(sol.x)
    res = sol.fun.reshape(-1, 2)
    counts = np.array([len(o) for o in obj])
    per_view = np.array([np.sqrt(np.mean(np.sum(r ** 2, 1))) for r in np.split(res, np.cumsum(counts)[:-1])])
    # residual variance per coordinate (pixels^2) scales the inverse normal matrix
    sigma2 = np.sum(res ** 2) / max(res.size - sol.x.size, 1)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * sigma2
    except np.linalg.LinAlgError:
        raise DegenerateFit("the turntable fit's normal matrix is singular") from None
    axis_std = float(np.degrees(np.sqrt(max(cov[0, 0], cov[1, 1]))))

    # World frame: origin = foot of the target origin (reference view) on the axis.
    origin = cc + ax * np.dot(t0 - cc, ax)
    xw = R0[:, 0] - ax * np.dot(R0[:, 0], ax)
    if np.linalg.norm(xw) < 1e-6:
        raise DegenerateFit("the target's x axis is parallel to the turntable axis; cannot fix world +x")
    xw /= np.linalg.norm(xw)
    R_ref = np.column_stack([xw, np.cross(ax, xw), ax])
    # target-to-world: X_w = R_ref^T (R0 X + t0 - origin)
    target_in_world = (R_ref.T @ R0, R_ref.T @ (t0 - origin))
    if known:
        scale = float(sol.x[10]) if fit_scale else s0
        offset = -scale * readings[0]
    else:
        scale, offset = 1.0, 0.0
    return TurntableFit(axis_camera=ax, origin_camera=origin, R_ref=R_ref, angle_scale=scale,
                        angle_offset_deg=float(offset), view_angles_deg=np.degrees(ph),
                        target_in_world=target_in_world, per_view_rms_px=per_view,
                        rms_px=float(np.sqrt(np.mean(np.sum(res ** 2, 1)))), axis_std_deg=axis_std,
                        angles_known=known, fit_status=int(sol.status), fit_message=str(sol.message))


def consistent_corner_order(detections: Sequence[TargetDetection], K, dist=None) -> list[TargetDetection]:
    """Chessboard views renumbered to one corner order (for :func:`fit_turntable`).

    A chessboard's corner order is ambiguous by a half turn in its plane (OpenCV may start at
    either end), so each view takes the order whose board x axis (``cv2.solvePnP``) agrees with
    the first view's. Views with corner ids (ChArUco) are returned as they are.

    Parameters
    ----------
    detections : sequence of TargetDetection
        Views of one board.
    K, dist : camera matrix (3, 3) and OpenCV distortion.

    Returns
    -------
    list of TargetDetection
    """
    K, dist = _validate.camera(K, dist)
    out, ref = [], None
    for k, d in enumerate(detections):  # a few views; one solvePnP each
        if not isinstance(d, TargetDetection):
            raise InvalidInput(f"detections[{k}] must be a TargetDetection, got {type(d).__name__}",
                               argument=f"detections[{k}]")
        if d.ids is None:
            ok, rvec, _ = cv2.solvePnP(d.object_points, d.image_points, K, dist)
            if not ok:
                raise DegenerateFit(f"{d.frame or f'detections[{k}]'}: no board pose (solvePnP failed)")
            x_axis = cv2.Rodrigues(rvec)[0][:, 0]
            if ref is None:
                ref = x_axis
            elif float(x_axis @ ref) < 0:
                d = replace(d, image_points=d.image_points[::-1].copy())
        out.append(d)
    return out


def lab_frame(fit: TurntableFit, grid_centre_mm, centre_height_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The lab frame from a turntable fit: fixed in the room, origin on the axis at the platter
    surface, +z up the axis, +x horizontal from the axis towards the camera, +y = z x x.

    Parameters
    ----------
    fit : TurntableFit
    grid_centre_mm : array_like of shape (3,)
        A point of the board, board frame, mm (e.g. the centre of its corner grid).
    centre_height_mm : float
        That point's height above the platter, mm (what the images cannot tell).

    Returns
    -------
    R : ndarray of shape (3, 3)
        Lab-to-camera rotation.
    t : ndarray of shape (3,)
        Lab origin in the camera frame, mm (``X_cam = R @ X_lab + t``).
    """
    if not isinstance(fit, TurntableFit):
        raise InvalidInput(f"fit must be a TurntableFit, got {type(fit).__name__}", argument="fit")
    g = _validate.array(grid_centre_mm, "grid_centre_mm", shape=(3,))
    height = float(_validate.array(centre_height_mm, "centre_height_mm", shape=()))
    R_tw, t_tw = fit.target_in_world
    centre_z = float((R_tw @ g + t_tw)[2])
    # +x towards the camera: the camera centre's azimuth in the fit's frame
    cam = -fit.R_ref.T @ fit.origin_camera
    psi = np.arctan2(cam[1], cam[0])
    Rz = np.array([[np.cos(psi), -np.sin(psi), 0.0], [np.sin(psi), np.cos(psi), 0.0], [0.0, 0.0, 1.0]])
    return fit.R_ref @ Rz, fit.origin_camera + (centre_z - height) * fit.axis_camera
