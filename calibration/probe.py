"""Light probes: mirror-sphere photographs to latitude-longitude environment maps.

Lat-long convention (world frame, +z up the turntable axis): an ``(H, 2H)`` map; row ``i``
holds polar angle ``theta = (i + 0.5) * pi / H`` from +z (row 0 looks straight up), column
``j`` holds azimuth ``phi = (j + 0.5) * 2 pi / (2H)`` measured from +x towards +y. A map pixel
stores the radiance arriving *from* that direction.

:func:`mirror_sphere_to_latlong` treats the camera as distant (orthographic: a sphere small in
the field of view); :func:`mirror_sphere_to_latlong_perspective` solves each reflection point
for a calibrated camera at a finite distance (a 25 mm ball at 500 mm subtends ±3°, which the
orthographic model turns into up to ~6° of direction error near the rim). Directions within
``blind_cone_deg`` of straight behind the sphere are not seen (they map to the silhouette, where
the image is also most compressed); their weight fades to 0 and a second view from another side
fills them (:func:`merge_probes`).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import _validate
from .errors import InvalidInput, TooFewViews

__all__ = ["Probe", "latlong_directions", "mirror_sphere_to_latlong", "mirror_sphere_to_latlong_perspective",
           "merge_probes"]


@dataclass(frozen=True)
class Probe:
    """An environment map with a per-direction confidence.

    Attributes
    ----------
    env : ndarray of shape (H, 2H) or (H, 2H, C), float32
        Radiance from each direction (0 where ``weight`` is 0).
    weight : ndarray of shape (H, 2H), float32
        0 (not observed: the blind spot) to 1 (well observed).
    """

    env: np.ndarray
    weight: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """Directions with any data, (H, 2H) bool."""
        return self.weight > 0


def latlong_directions(height: int) -> np.ndarray:
    """Unit world directions of every lat-long pixel centre, shape (height, 2*height, 3)."""
    h = _validate.integer(height, "height", minimum=2)
    theta = (np.arange(h) + 0.5) * np.pi / h
    phi = (np.arange(2 * h) + 0.5) * np.pi / h
    st = np.sin(theta)[:, None]
    return np.stack([st * np.cos(phi)[None], st * np.sin(phi)[None],
                     np.broadcast_to(np.cos(theta)[:, None], (h, 2 * h))], axis=-1)


def mirror_sphere_to_latlong(image, center_px, radius_px: float, R_world_to_camera, *, height: int = 128,
                             blind_cone_deg: float = 15.0, fade_deg: float = 20.0) -> Probe:
    """Resample a mirror-sphere photo into a world-frame lat-long map.

    For a world direction ``w`` the camera sees it reflected at the sphere normal
    ``n = normalize(R w + v)`` (``v = (0, 0, -1)``: towards the camera in the OpenCV camera frame),
    i.e. at pixel ``center + radius * (n_x, n_y)``; the image is sampled there bilinearly.

    Parameters
    ----------
    image : ndarray of shape (H_img, W_img) or (H_img, W_img, C)
        Linear radiance (HDR) of the sphere.
    center_px : array_like of shape (2,)
        Sphere centre in the image (x, y), pixels (e.g. ``lights.detect_sphere``).
    radius_px : float
        Sphere radius in the image, pixels.
    R_world_to_camera : array_like of shape (3, 3)
        Rotation world -> camera of this view (``X_cam = R @ X_world + t``).
    height : int
        Lat-long map height (width is ``2 * height``).
    blind_cone_deg : float
        Half-angle of the unseen cone straight behind the sphere, deg (weight 0).
    fade_deg : float
        Width of the smooth weight ramp beyond the blind cone, deg.

    Returns
    -------
    Probe
    """
    img = _validate.image(image, "image", dtype=np.float32)
    R = _rotation(R_world_to_camera)
    c = _validate.array(center_px, "center_px", shape=(2,))
    radius_px = _validate.positive(radius_px, "radius_px")
    if not 0 <= blind_cone_deg < 90 or fade_deg < 0:
        raise InvalidInput("blind_cone_deg must be in [0, 90) and fade_deg >= 0")
    w_cam = latlong_directions(height) @ R.T
    n = w_cam + np.array([0.0, 0.0, -1.0])
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = n / np.maximum(norm, 1e-12)
    mapx = (c[0] + radius_px * n[..., 0]).astype(np.float32)
    mapy = (c[1] + radius_px * n[..., 1]).astype(np.float32)
    env = cv2.remap(img, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    # angle from "straight behind the sphere" (camera +z)
    weight = _blind_weight(np.degrees(np.arccos(np.clip(w_cam[..., 2], -1, 1))), blind_cone_deg, fade_deg)
    inside = (mapx >= 0) & (mapy >= 0) & (mapx <= img.shape[1] - 1) & (mapy <= img.shape[0] - 1)
    weight = np.where(inside, weight, 0.0).astype(np.float32)
    env = env * (weight > 0)[..., None] if env.ndim == 3 else env * (weight > 0)
    return Probe(env.astype(np.float32), weight)


def _rotation(R) -> np.ndarray:
    R = _validate.array(R, "R_world_to_camera", shape=(3, 3))
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InvalidInput("R_world_to_camera must be a 3x3 rotation matrix", argument="R_world_to_camera")
    return R


def _blind_weight(behind_deg, blind_cone_deg, fade_deg):
    ramp = np.clip((behind_deg - blind_cone_deg) / max(fade_deg, 1e-9), 0, 1)
    return (ramp * ramp * (3 - 2 * ramp)).astype(np.float32)  # smoothstep


def mirror_sphere_to_latlong_perspective(image, K, dist, center_mm, radius_mm: float, R_world_to_camera, *,
                                         height: int = 128, blind_cone_deg: float = 15.0,
                                         fade_deg: float = 20.0, iterations: int = 30) -> Probe:
    """Resample a mirror-sphere photo from a calibrated pinhole camera into a lat-long map.

    For a world direction ``w`` (``R w`` in the camera frame) the reflection point ``X`` on the
    sphere has a normal bisecting ``R w`` and the direction back to the camera:
    ``n = normalize(R w - X / |X|)``, ``X = C + r n``, solved by fixed-point iteration for all
    directions at once, then projected with ``cv2.projectPoints`` (distortion included).

    Parameters
    ----------
    image : ndarray of shape (H_img, W_img) or (H_img, W_img, C)
        Linear radiance (HDR).
    K : array_like of shape (3, 3)
        Camera matrix, pixels.
    dist : array_like or None
        OpenCV distortion coefficients.
    center_mm : array_like of shape (3,)
        Sphere centre in the camera frame, mm (e.g. ``lights.sphere_center_from_silhouette``).
    radius_mm : float
        Sphere radius, mm.
    R_world_to_camera : array_like of shape (3, 3)
        Rotation world -> camera.
    height, blind_cone_deg, fade_deg : see :func:`mirror_sphere_to_latlong`
        The blind cone is centred on the direction from the camera through the sphere centre.
    iterations : int
        Fixed-point iterations (each halves the error or better away from the blind cone).

    Returns
    -------
    Probe
    """
    img = _validate.image(image, "image", dtype=np.float32)
    R = _rotation(R_world_to_camera)
    K, dist = _validate.camera(K, dist)
    C = _validate.array(center_mm, "center_mm", shape=(3,))
    radius_mm = _validate.positive(radius_mm, "radius_mm")
    height = _validate.integer(height, "height", minimum=2)
    if not np.linalg.norm(C) > radius_mm:
        raise InvalidInput("center_mm: the camera must lie outside the sphere "
                           f"(|center_mm| = {np.linalg.norm(C):.1f}, radius_mm = {radius_mm})", argument="center_mm")
    w_cam = (latlong_directions(height) @ R.T).reshape(-1, 3)
    n = w_cam - C / np.linalg.norm(C)  # start: the orthographic solution
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    for _ in range(int(iterations)):
        X = C + radius_mm * n
        n = w_cam - X / np.linalg.norm(X, axis=1, keepdims=True)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    X = C + radius_mm * n
    uv = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    shape = (height, 2 * height)
    mapx = uv[:, 0].reshape(shape).astype(np.float32)
    mapy = uv[:, 1].reshape(shape).astype(np.float32)
    env = cv2.remap(img, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    axis = C / np.linalg.norm(C)
    behind = np.degrees(np.arccos(np.clip(w_cam @ axis, -1, 1))).reshape(shape)
    # the reflection point must face the camera (a converged solution always does)
    facing = (np.sum(n * -X, axis=1) > 0).reshape(shape)
    inside = (mapx >= 0) & (mapy >= 0) & (mapx <= img.shape[1] - 1) & (mapy <= img.shape[0] - 1)
    weight = np.where(inside & facing, _blind_weight(behind, blind_cone_deg, fade_deg), 0.0).astype(np.float32)
    env = env * (weight > 0)[..., None] if env.ndim == 3 else env * (weight > 0)
    return Probe(env.astype(np.float32), weight)


def merge_probes(probes) -> Probe:
    """Weighted average of lat-long probes of one size (fills each view's blind spot).

    Returns
    -------
    Probe
        ``env`` is 0 and ``weight`` 0 where no view saw the direction.
    """
    probes = list(probes)
    if not probes:
        raise TooFewViews("probe merge", have=0, need=1)
    for i, p in enumerate(probes):
        if not isinstance(p, Probe):
            raise InvalidInput(f"probes[{i}] must be a Probe, got {type(p).__name__}", argument="probes")
    shapes = {p.env.shape for p in probes}
    if len(shapes) != 1:
        raise InvalidInput(f"probes must share one lat-long shape, got {sorted(shapes)}")
    W = np.stack([p.weight for p in probes])
    E = np.stack([p.env for p in probes])
    Wb = W[..., None] if E.ndim == 4 else W
    sw = W.sum(axis=0)
    swb = sw[..., None] if E.ndim == 4 else sw
    env = np.sum(Wb * E, axis=0) / np.maximum(swb, 1e-12)
    return Probe(np.where(swb > 0, env, 0).astype(np.float32), np.minimum(sw, 1).astype(np.float32))
