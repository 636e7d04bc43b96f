"""Light localisation from chrome / steel spheres.

Frames: pixels x right, y down (pixel centres at integers); camera frame OpenCV (x right,
y down, z forward), millimetres. Light *directions* point from the object towards the light
(unit vectors, camera frame). Positioner kinematics live in the world (turntable) frame:
azimuth from +x towards +y, elevation above the platter plane, degrees.

References: Lensch et al. 2003, Sec. 4.1 (collinear steel spheres, Eqs. 1-5; light at the
least-squares intersection of the reflected rays).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from . import _fit, _validate
from .errors import DegenerateFit, InvalidInput, TargetNotFound, TooFewViews

__all__ = [
    "SphereImage", "Highlight", "PointLight", "PositionerModel",
    "detect_sphere", "find_highlight", "light_direction_orthographic", "sphere_center_from_silhouette",
    "reflect_highlight", "closest_point_to_lines", "triangulate_point_light", "locate_collinear_spheres",
    "fit_positioner_model",
]


@dataclass(frozen=True)
class SphereImage:
    """A sphere's silhouette in an image.

    Attributes
    ----------
    center_px : ndarray of shape (2,)
        Centre of the sphere's image (x, y), pixels (:func:`detect_sphere`: of its outline's
        ellipse).
    radius_px : float
        Radius, pixels (:func:`detect_sphere`: of the circle with the ellipse's area).
    ellipse : tuple or None
        ``cv2.fitEllipse`` result ``((cx, cy), (d1, d2), angle_deg)`` of the outline; None when
        the geometry was given rather than detected.
    edge_px : ndarray of shape (N, 2)
        Outline points (boundary-pixel centres pushed half a pixel outward), pixels; empty when
        the geometry was given.
    """

    center_px: np.ndarray
    radius_px: float
    ellipse: tuple | None = None
    edge_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def __post_init__(self) -> None:
        object.__setattr__(self, "center_px", _validate.array(self.center_px, "center_px", shape=(2,)))
        object.__setattr__(self, "radius_px", _validate.positive(self.radius_px, "radius_px"))
        edge = np.zeros((0, 2)) if self.edge_px is None else self.edge_px
        object.__setattr__(self, "edge_px", _validate.array(edge, "edge_px", shape=(-1, 2)))


@dataclass(frozen=True)
class Highlight:
    """A specular highlight: sub-pixel position, saturated-pixel count, peak value."""

    xy_px: np.ndarray
    n_saturated: int
    peak: float


@dataclass(frozen=True)
class PointLight:
    """Triangulated point light (camera frame, mm).

    Attributes
    ----------
    position_mm : ndarray of shape (3,)
    covariance_mm2 : ndarray of shape (3, 3)
        From the Jacobian of the position w.r.t. the highlight pixels, times the stated
        highlight noise ``sigma_px**2``.
    std_mm : ndarray of shape (3,)
    residuals_mm : ndarray of shape (M,)
        Distance of each reflected ray from the solution, mm.
    surface_points_mm, directions : ndarray of shape (M, 3)
        Where each ray reflects, and the reflected unit direction.
    """

    position_mm: np.ndarray
    covariance_mm2: np.ndarray
    std_mm: np.ndarray
    residuals_mm: np.ndarray
    surface_points_mm: np.ndarray
    directions: np.ndarray


#: a sphere's outline is a circle, or an ellipse of at most this eccentricity under perspective
#: (minor / major axis; 0.75 is a sphere 40 deg off a wide lens' axis)
MIN_SPHERE_AXIS_RATIO = 0.75
#: outline points may stray from the fitted ellipse by this fraction of the radius (rms)
MAX_SPHERE_OUTLINE_RMS = 0.03
#: the filled outline must cover this fraction of its ellipse (a convex, unbroken silhouette)
MIN_SPHERE_FILL = 0.9


def detect_sphere(mask, *, threshold: float | None = None, frame: str | None = None) -> SphereImage:
    """Find a sphere's silhouette (the largest blob) in a mask or an image, from its outline.

    The centre and radius come from an ellipse fitted to the blob's *outer* outline, not from
    its pixel moments: a mirror sphere reflects dark parts of the room as holes in the blob,
    which bias moments but leave the outline intact.

    Parameters
    ----------
    mask : ndarray of shape (H, W) or (H, W, 3)
        Boolean mask, or an image where the sphere is brighter than the background (its
        colour channels are averaged).
    threshold : float, optional
        Level separating sphere from background. Default: Otsu's threshold of the image (of
        its logarithm for a float or 16-bit image, so a dim ball under a bright highlight still
        separates); 0.5 for a boolean mask.
    frame : str, optional
        Frame name for the error messages.

    Returns
    -------
    SphereImage
        ``center_px`` and ``ellipse`` from the outline's ellipse fit; ``radius_px`` the radius
        of the circle of the ellipse's area, pixels; ``edge_px`` the outline points.

    Raises
    ------
    TargetNotFound
        No blob of at least 50 pixels, or the largest blob is not a credible sphere: it
        touches the image border, its outline is not an ellipse of axis ratio >=
        :data:`MIN_SPHERE_AXIS_RATIO` within :data:`MAX_SPHERE_OUTLINE_RMS` of its radius, or it
        fills less than :data:`MIN_SPHERE_FILL` of that ellipse. The message says which.
    """
    img = _validate.gray(mask, "mask")
    if threshold is not None and not np.isfinite(threshold):
        raise InvalidInput(f"threshold must be finite, got {threshold!r}", argument="threshold")
    level = _sphere_threshold(img, np.asarray(mask).dtype) if threshold is None else float(threshold)
    binary = (img > level).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    if n < 2 or stats[1:, cv2.CC_STAT_AREA].max() < 50:
        raise TargetNotFound(f"no sphere silhouette (blob of >= 50 px above the threshold {level:.4g})",
                             frame=frame)
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x, y, bw, bh = stats[k, :4]
    h, w = img.shape
    if x == 0 or y == 0 or x + bw >= w or y + bh >= h:
        raise TargetNotFound(f"the largest blob above the threshold {level:.4g} touches the image border: "
                             "not a whole sphere (mask it, or give a threshold)", frame=frame)
    contours, _ = cv2.findContours((labels == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outline = max(contours, key=len)
    pts = outline.reshape(-1, 2).astype(np.float64)
    # boundary-pixel centres lie half a pixel inside the edge: push them out
    inner = pts.mean(axis=0)
    outward = pts - inner
    pts = pts + 0.5 * outward / np.maximum(np.linalg.norm(outward, axis=1, keepdims=True), 1e-9)
    ellipse = cv2.fitEllipse(pts.astype(np.float32))
    (cx, cy), (d1, d2), angle = ellipse
    a, b = max(d1, d2) / 2, min(d1, d2) / 2
    radius = float(np.sqrt(a * b))
    ratio = b / a if a > 0 else 0.0
    # outline scatter about the ellipse: normalised radius in the ellipse's own axes
    t = np.radians(angle)
    rel = pts - [cx, cy]
    u = rel @ np.array([np.cos(t), np.sin(t)]) / max(d1 / 2, 1e-9)
    v = rel @ np.array([-np.sin(t), np.cos(t)]) / max(d2 / 2, 1e-9)
    rms = float(np.sqrt(np.mean((np.hypot(u, v) - 1) ** 2))) * radius
    fill = cv2.contourArea(outline) / max(np.pi * a * b, 1e-9)
    why = []
    if ratio < MIN_SPHERE_AXIS_RATIO:
        why.append(f"its outline's axis ratio is {ratio:.2f} (< {MIN_SPHERE_AXIS_RATIO})")
    if rms > max(MAX_SPHERE_OUTLINE_RMS * radius, 1.0):
        why.append(f"its outline strays {rms:.1f} px rms from an ellipse (> {100 * MAX_SPHERE_OUTLINE_RMS:.0f}% "
                   f"of the {radius:.1f} px radius)")
    if fill < MIN_SPHERE_FILL:
        why.append(f"it fills {100 * fill:.0f}% of its ellipse (< {100 * MIN_SPHERE_FILL:.0f}%)")
    if why:
        raise TargetNotFound(f"the largest blob above the threshold {level:.4g} is not a credible sphere: "
                             + "; ".join(why) + " (mask the sphere, or give a threshold)", frame=frame)
    return SphereImage(np.array([cx, cy], float), radius, ellipse, pts)


def _sphere_threshold(img: np.ndarray, dtype) -> float:
    """Default sphere / background level: 0.5 for masks, Otsu's for 8-bit images, Otsu's on
    the logarithm for float or 16-bit ones (a highlight thousands of times brighter than the
    ball would otherwise take the whole upper class)."""
    if dtype == bool:
        return 0.5
    lo, hi = float(img.min()), float(img.max())
    if hi <= lo:
        return hi
    if dtype == np.uint8:
        return float(cv2.threshold(img.astype(np.uint8), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)[0])
    floor = max(float(np.percentile(img, 1)), lo) if lo < 0 else lo
    span = np.log1p(np.maximum(img - floor, 0) / max(hi - floor, 1e-30) * 1e4)
    u8 = np.round(span / span.max() * 255).astype(np.uint8)
    t = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)[0]
    return float(floor + np.expm1(t / 255 * span.max()) / 1e4 * (hi - floor))


def find_highlight(image, sphere: SphereImage | None = None, *, saturation: float | None = None,
                   rel_threshold: float = 0.2, frame: str | None = None) -> Highlight:
    """Sub-pixel position of the brightest highlight (on the sphere, if given).

    The blob is the connected region above ``rel_threshold * reference`` that holds the peak
    (reference: the saturation level when the peak reaches it, else the peak). Its centroid is
    weighted by ``min(I, reference) - threshold``, so a clipped (saturated) core counts as a flat
    top and the unclipped rim refines it.

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, 3)
        Linear (or monotonic) intensities.
    sphere : SphereImage, optional
        Restrict the search to the sphere's disc (shrunk by 1 px).
    saturation : float, optional
        Clipping level of the sensor (default: treat the peak value as the level if at least
        two pixels share it).
    rel_threshold : float
        Fraction of the reference level that bounds the blob. 0.2 takes in the highlight's
        flanks, which a high threshold cuts asymmetrically where the sphere compresses the
        reflection: on the tests' chrome spheres 0.2 instead of 0.5 brings distant-light errors
        from 0.05-0.07° to 0.01-0.02°, and on the simulated steel-ball row (pixel-integrated
        renders) the point light from 0.8-1.4 % to 0.4 % of its distance.
    frame : str, optional
        Frame name for error messages.

    Returns
    -------
    Highlight

    Raises
    ------
    TargetNotFound
        No pixel above the background inside the search region.
    """
    img = _validate.gray(image, "image")
    if sphere is not None:
        _sphere(sphere)
    if saturation is not None:
        saturation = _validate.positive(saturation, "saturation")
    if not 0 < rel_threshold < 1:
        raise InvalidInput(f"rel_threshold must be in (0, 1), got {rel_threshold}")
    offset = np.zeros(2)
    region = np.ones(img.shape, bool)
    if sphere is not None:  # work in the sphere's bounding box only (frames may be 24 MP)
        c, r = sphere.center_px, sphere.radius_px
        x0, y0 = np.maximum(np.floor(c - r).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(c + r).astype(int) + 1, [img.shape[1], img.shape[0]])
        if x1 <= x0 or y1 <= y0:
            raise TargetNotFound("the sphere's disc lies outside the image", frame=frame)
        img = img[y0:y1, x0:x1]
        offset = np.array([x0, y0], float)
        yy, xx = np.indices(img.shape)
        region = (xx + x0 - c[0]) ** 2 + (yy + y0 - c[1]) ** 2 < (r - 1) ** 2
    vals = np.where(region, img, -np.inf)
    peak_idx = np.unravel_index(np.argmax(vals), img.shape)
    peak = float(img[peak_idx])
    if not peak > 0:
        raise TargetNotFound("no highlight (nothing brighter than zero in the search region)", frame=frame)
    sat = saturation
    if sat is None and np.count_nonzero(vals >= peak) >= 2:
        sat = peak
    ref = min(peak, sat) if sat is not None else peak
    thr = rel_threshold * ref
    n, labels = cv2.connectedComponents((vals > thr).astype(np.uint8), connectivity=8)
    blob = labels == labels[peak_idx]
    w = np.where(blob, np.minimum(img, ref) - thr, 0.0)
    ys, xs = np.nonzero(w)
    ww = w[ys, xs]
    xy = np.array([np.sum(ww * xs), np.sum(ww * ys)]) / np.sum(ww) + offset
    n_sat = int(np.count_nonzero(blob & (img >= sat))) if sat is not None else 0
    return Highlight(xy, n_sat, peak)


def light_direction_orthographic(highlight_xy, sphere: SphereImage) -> np.ndarray:
    """Distant-light direction from a highlight on a mirror sphere seen by a distant camera.

    Parameters
    ----------
    highlight_xy : array_like of shape (2,) or (M, 2)
        Highlight pixels (x, y).
    sphere : SphereImage
        The sphere's image centre and radius.

    Returns
    -------
    ndarray of shape (3,) or (M, 3)
        Unit directions towards the light in the camera frame (x right, y down, z forward;
        the viewer is at -z).
    """
    h = _validate.array(highlight_xy, "highlight_xy", ndim=(1, 2))
    if h.shape[-1] != 2:
        raise InvalidInput(f"highlight_xy must have shape (2,) or (M, 2), got {h.shape}", argument="highlight_xy")
    _sphere(sphere)
    nx, ny = ((h[..., 0] - sphere.center_px[0]) / sphere.radius_px,
              (h[..., 1] - sphere.center_px[1]) / sphere.radius_px)
    rho2 = nx ** 2 + ny ** 2
    if np.any(rho2 >= 1):
        raise InvalidInput("highlight_xy lies outside the sphere's disc")
    n = np.stack([nx, ny, -np.sqrt(1 - rho2)], axis=-1)
    v = np.array([0.0, 0.0, -1.0])  # towards the viewer
    return 2 * np.sum(n * v, axis=-1, keepdims=True) * n - v


def _sphere(sphere) -> None:
    if not isinstance(sphere, SphereImage):
        raise InvalidInput(f"sphere must be a SphereImage, got {type(sphere).__name__}", argument="sphere")
    _validate.array(sphere.center_px, "sphere.center_px", shape=(2,))
    _validate.positive(sphere.radius_px, "sphere.radius_px")


def _rays(pixels, K, dist, name: str) -> np.ndarray:
    px = _validate.array(pixels, name, ndim=(1, 2))
    if px.shape[-1] != 2:
        raise InvalidInput(f"{name} must have shape (M, 2), got {px.shape}", argument=name)
    K, dist = _validate.camera(K, dist)
    xy = cv2.undistortPoints(px.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def sphere_center_from_silhouette(sphere: SphereImage, K, dist=None, radius_mm: float = 1.0) -> np.ndarray:
    """Camera-frame centre of a sphere of known radius from its outline (perspective).

    The outline's viewing rays form a cone tangent to the sphere: unit rays ``u`` satisfy
    ``u . c = cos(beta)`` for the cone axis ``c``; ``w = c / cos(beta)`` solves the linear system
    ``U w = 1``; the distance is ``radius_mm / sin(beta)``.

    Returns
    -------
    ndarray of shape (3,)
        Centre, mm (scale set by ``radius_mm``).
    """
    radius_mm = _validate.positive(radius_mm, "radius_mm")
    _sphere(sphere)
    if len(sphere.edge_px) < 5:
        raise TooFewViews("sphere outline points (sphere.edge_px)", have=len(sphere.edge_px), need=5)
    U = _rays(sphere.edge_px, K, dist, "sphere.edge_px")
    w = np.linalg.lstsq(U, np.ones(len(U)), rcond=None)[0]
    cos_b = 1.0 / np.linalg.norm(w)
    if not 0 < cos_b < 1:
        raise DegenerateFit("sphere outline does not form a cone (check K and the mask)")
    return (w * cos_b) * radius_mm / np.sqrt(1 - cos_b ** 2)


def reflect_highlight(highlight_xy, center_mm, radius_mm, K, dist=None) -> tuple[np.ndarray, np.ndarray]:
    """Reflect the viewing rays through highlights off spheres.

    Parameters
    ----------
    highlight_xy : array_like of shape (M, 2)
        Highlight pixels.
    center_mm : array_like of shape (M, 3)
        Sphere centres, camera frame, mm.
    radius_mm : float or array_like of shape (M,)
        Sphere radii, mm.
    K, dist : camera matrix (3, 3) and OpenCV distortion.

    Returns
    -------
    points_mm : ndarray of shape (M, 3)
        Reflection points on the spheres (camera frame, mm).
    directions : ndarray of shape (M, 3)
        Unit reflected directions (towards the light).

    Raises
    ------
    InvalidInput
        A ray misses its sphere (names the index).
    """
    C = _validate.array(center_mm, "center_mm", ndim=(1, 2))
    if C.shape[-1] != 3:
        raise InvalidInput(f"center_mm must have shape (M, 3), got {C.shape}", argument="center_mm")
    C = C.reshape(-1, 3)
    R = _validate.array(radius_mm, "radius_mm")
    if R.ndim > 1 or R.size not in (1, len(C)) or np.any(R <= 0):
        raise InvalidInput(f"radius_mm must be one positive radius or one per sphere ({len(C)}), got {R}",
                           argument="radius_mm")
    R = np.broadcast_to(R, (len(C),))
    if np.any(np.linalg.norm(C, axis=1) <= R):
        raise InvalidInput("center_mm: the camera lies inside a sphere (|center| <= radius)", argument="center_mm")
    d = _rays(highlight_xy, K, dist, "highlight_xy")
    if len(d) != len(C):
        raise InvalidInput(f"highlight_xy has {len(d)} points for {len(C)} sphere centres")
    b = np.sum(d * C, axis=1)
    disc = b ** 2 - (np.sum(C * C, axis=1) - R ** 2)
    if np.any(disc < 0):
        raise InvalidInput(f"highlight_xy[{int(np.argmin(disc))}]: the viewing ray misses its sphere")
    X = d * (b - np.sqrt(disc))[:, None]
    n = (X - C) / R[:, None]
    v = -d
    return X, 2 * np.sum(n * v, axis=1, keepdims=True) * n - v


def closest_point_to_lines(P, L) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares point nearest to the lines ``P + s L``, for one or a batch of line sets.

    Parameters
    ----------
    P : ndarray of shape (..., M, 3)
        A point on each line.
    L : ndarray of shape (..., M, 3)
        Unit direction of each line.

    Returns
    -------
    X : ndarray of shape (..., 3)
        The point minimising the summed squared distances to the M lines.
    A : ndarray of shape (..., 3, 3)
        The normal matrix ``sum(I - L L^T)`` (singular when the lines are parallel).
    """
    proj = np.eye(3) - L[..., :, None] * L[..., None, :]
    A = proj.sum(axis=-3)
    return np.linalg.solve(A, np.einsum("...mij,...mj->...i", proj, P)[..., None])[..., 0], A


def triangulate_point_light(highlights_xy, centers_mm, radius_mm, K, dist=None, *,
                            sigma_px: float = 0.25, sigma_center_mm: float = 0.0) -> PointLight:
    """Point-light position from its highlights on several spheres of known position/radius.

    Reflected rays are intersected in the least-squares sense (Lensch 2003 Sec. 4.1). The
    covariance propagates an isotropic highlight noise ``sigma_px`` (and sphere-centre noise
    ``sigma_center_mm``) through the numerical Jacobians d(position)/d(highlight pixels) and
    d(position)/d(centres).

    The position is far more sensitive to the centres than their size suggests: a 1-inch ball's
    normal turns by ``delta / radius`` for a centre error ``delta``, and the reflected ray by
    twice that (the simulated lab's row of six 12.7 mm balls at 750 mm: 0.03 mm of random centre
    error per axis moves a light 470 mm away by 1.4 % median).

    Parameters
    ----------
    highlights_xy : array_like of shape (M, 2)
        Highlight pixel of each sphere, M >= 2.
    centers_mm : array_like of shape (M, 3)
        Sphere centres, camera frame, mm.
    radius_mm : float or array_like of shape (M,)
    K, dist : camera matrix and OpenCV distortion.
    sigma_px : float
        1-sigma highlight localisation noise, pixels.
    sigma_center_mm : float
        1-sigma error of each centre coordinate, mm (0: centres exact, e.g. measured on the
        fixture; Lensch's flash-derived centres are typically good to a few tenths of a mm).

    Returns
    -------
    PointLight

    Raises
    ------
    TooFewViews
        Fewer than 2 spheres.
    DegenerateFit
        The reflected rays are (nearly) parallel: the light is at infinity for this layout.
    """
    h = _validate.array(highlights_xy, "highlights_xy", shape=(-1, 2))
    sigma_px = _validate.positive(sigma_px, "sigma_px")
    sigma_center_mm = _validate.positive(sigma_center_mm, "sigma_center_mm", allow_zero=True)
    if len(h) < 2:
        raise TooFewViews("point-light triangulation (spheres)", have=len(h), need=2)
    P, L = reflect_highlight(h, centers_mm, radius_mm, K, dist)
    A = np.sum(np.eye(3) - L[:, :, None] * L[:, None, :], axis=0)
    if np.linalg.eigvalsh(A)[0] < 1e-6 * len(h):
        raise DegenerateFit("the reflected rays are nearly parallel: spread the spheres further apart "
                            "or move the light closer")
    pos = closest_point_to_lines(P, L)[0]
    J = np.empty((3, h.size))
    eps = 1e-3
    for k in range(h.size):  # 2M tiny solves; each re-reflects all rays
        hp = h.copy().ravel()
        hp[k] += eps
        Pk, Lk = reflect_highlight(hp.reshape(-1, 2), centers_mm, radius_mm, K, dist)
        J[:, k] = (closest_point_to_lines(Pk, Lk)[0] - pos) / eps
    cov = sigma_px ** 2 * J @ J.T
    if sigma_center_mm > 0:
        C = np.asarray(centers_mm, float).reshape(-1, 3)
        Jc = np.empty((3, C.size))
        for k in range(C.size):  # 3M more tiny solves
            Ck = C.copy().ravel()
            Ck[k] += eps
            Pk, Lk = reflect_highlight(h, Ck.reshape(-1, 3), radius_mm, K, dist)
            Jc[:, k] = (closest_point_to_lines(Pk, Lk)[0] - pos) / eps
        cov = cov + sigma_center_mm ** 2 * Jc @ Jc.T
    diff = pos - P
    resid = np.linalg.norm(diff - np.sum(diff * L, axis=1, keepdims=True) * L, axis=1)
    return PointLight(pos, cov, np.sqrt(np.diag(cov)), resid, P, L)


def locate_collinear_spheres(flash_highlights_xy, spacing_mm: float, K, dist=None) -> np.ndarray:
    """Centres of equally spaced collinear spheres from on-axis (ring-flash) highlights.

    Lensch 2003 Eqs. 1-5: sphere ``i`` lies on the ray ``f_i`` through its flash highlight,
    ``p_i = p_0 + i d``, so ``f_i x p_0 + i (f_i x d) = 0``; the 6-vector ``(p_0, d)`` is the
    null vector of the stacked system (SVD), scaled so ``|d| = spacing_mm`` and ``p_0`` lies in
    front of the camera.

    Parameters
    ----------
    flash_highlights_xy : array_like of shape (M, 2)
        Flash highlight of sphere ``i`` (in order along the fixture), pixels; M >= 3.
    spacing_mm : float
        Centre-to-centre distance of neighbouring spheres, mm.
    K, dist : camera matrix and OpenCV distortion.

    Returns
    -------
    ndarray of shape (M, 3)
        Sphere centres, camera frame, mm.
    """
    f = _rays(flash_highlights_xy, K, dist, "flash_highlights_xy")
    if len(f) < 3:
        raise TooFewViews("collinear sphere location (spheres)", have=len(f), need=3)
    spacing_mm = _validate.positive(spacing_mm, "spacing_mm")
    skew = np.zeros((len(f), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -f[:, 2], f[:, 1], -f[:, 0]
    skew -= skew.transpose(0, 2, 1)
    i = np.arange(len(f), dtype=float)[:, None, None]
    A = np.concatenate([skew, i * skew], axis=2).reshape(-1, 6)
    s = np.linalg.svd(A)
    if s[1][-2] < 1e-9 * s[1][0]:
        raise DegenerateFit("the flash highlights do not determine the sphere line (all on one ray?)")
    x = s[2][-1]
    p0, d = x[:3], x[3:]
    scale = spacing_mm / np.linalg.norm(d)
    if p0 @ f[0] < 0:
        scale = -scale
    return (p0 + i[:, :, 0] * d) * scale


@dataclass(frozen=True)
class PositionerModel:
    """Light-positioner kinematics fitted to measured light positions (world frame, mm, deg).

    ``position(az, el) = centre + radius * (cos e cos a, cos e sin a, sin e)`` with
    ``a = az + azimuth_offset_deg``, ``e = el + elevation_offset_deg``.

    Attributes
    ----------
    centre_mm : ndarray of shape (3,)
    radius_mm, azimuth_offset_deg, elevation_offset_deg : float
    param_std : ndarray of shape (6,)
        1-sigma of (cx, cy, cz, radius, az offset, el offset), mm / deg.
    residuals_mm : ndarray of shape (N,)
        Distance of each measured position from the model, mm.
    fit_status : int
        ``scipy.optimize.least_squares`` status (1-4: converged).
    fit_message : str
        The solver's termination message.
    """

    centre_mm: np.ndarray
    radius_mm: float
    azimuth_offset_deg: float
    elevation_offset_deg: float
    param_std: np.ndarray
    residuals_mm: np.ndarray
    fit_status: int = 1
    fit_message: str = ""
    #: with a fit to the reflected rays: their rms angle from the model's lights, deg (else nan)
    ray_rms_deg: float = float("nan")

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_mm ** 2)))

    def position(self, azimuth_deg, elevation_deg) -> np.ndarray:
        """Light position(s), world frame mm, shape (..., 3), for commanded angles (deg)."""
        return _arm(np.r_[self.centre_mm, self.radius_mm, self.azimuth_offset_deg, self.elevation_offset_deg],
                    np.asarray(azimuth_deg, float), np.asarray(elevation_deg, float))


#: scale of the ray fit's robust loss, as the sine of the angle past which a ray counts less
#: (highlights good to ~0.15 px on a 20 px ball give ~1 deg)
RAY_MISFIT_SCALE = float(np.sin(np.radians(1.0)))


def _arm(p, az, el):
    a, e = np.radians(az + p[4]), np.radians(el + p[5])
    return p[:3] + p[3] * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1)


def fit_positioner_model(azimuth_deg, elevation_deg, positions_mm, *, rays=None,
                         max_evaluations: int | None = None) -> PositionerModel:
    """Fit arm kinematics (centre, radius, azimuth/elevation offsets) to measured positions.

    With ``rays`` (the reflected rays each position was triangulated from) the fit goes on to
    minimise the angle between every ray and the direction from its reflection point to the
    model's light. A triangulated position is well determined across the rays but poorly along
    them (spheres 200 mm apart seeing a lamp 500 mm away: ~5x worse in depth); the arm model
    ties all poses together, and fitting it to the rays themselves weighs each direction by what
    it measures instead of trusting every triangulated depth alike (simulated lab, 9 poses at
    320 x 240: worst light 2.3 % -> see docs/measurements.md).

    Parameters
    ----------
    azimuth_deg, elevation_deg : array_like of shape (N,)
        Commanded positioner angles, deg (azimuth from world +x towards +y, elevation above
        the platter plane).
    positions_mm : array_like of shape (N, 3)
        Light positions measured for those poses (e.g. :func:`triangulate_point_light`,
        mapped to the world frame), mm.
    rays : tuple (points_mm, directions, pose[, weight]), optional
        Reflection points (R, 3) mm and unit directions (R, 3) of the rays towards the lamp
        (:func:`reflect_highlight`, same frame as ``positions_mm``), the index (R,) into the
        poses of the light each ray saw, and optionally each ray's weight (R,), inversely
        proportional to its angular uncertainty (a highlight towards a ball's limb, where the
        normal turns faster per pixel, gives a less certain ray: :func:`ray_weights`).
    max_evaluations : int, optional
        Residual evaluations the fit may use (scipy's default when None).

    Returns
    -------
    PositionerModel
        Gives every commanded pose a position, including poses with no sphere measurement.
        ``residuals_mm`` are the distances of ``positions_mm`` from the model either way.

    Raises
    ------
    TooFewViews
        Fewer than 3 poses (6 parameters, 3 coordinates each).
    DegenerateFit
        The poses do not span both angles (the offsets are then undetermined).
    NotConverged
        The fit stopped before converging.
    """
    az = _validate.array(azimuth_deg, "azimuth_deg").ravel()
    el = _validate.array(elevation_deg, "elevation_deg").ravel()
    X = _validate.array(positions_mm, "positions_mm")
    if az.shape != el.shape or X.shape != (len(az), 3):
        raise InvalidInput(f"azimuth_deg {az.shape}, elevation_deg {el.shape} and positions_mm {X.shape} "
                         "must be (N,), (N,), (N, 3)")
    if len(az) < 3:
        raise TooFewViews("positioner model (poses)", have=len(az), need=3)
    if np.ptp(az) < 5 and np.ptp(el) < 5:
        raise DegenerateFit("positioner poses span less than 5° in both azimuth and elevation")
    # Initial guess: algebraic sphere fit |X - c|^2 = r^2 (linear in c and r^2 - |c|^2); poses
    # on one circle leave it rank-deficient, and the mean of the positions is used instead.
    A = np.c_[2 * X, np.ones(len(X))]
    sol_c, _, rank, _ = np.linalg.lstsq(A, np.sum(X * X, axis=1), rcond=None)
    c0 = sol_c[:3] if rank == 4 else X.mean(axis=0)
    d0 = X - c0
    r0 = float(np.mean(np.linalg.norm(d0, axis=1)))
    a_off = np.degrees(np.angle(np.mean(np.exp(1j * (np.arctan2(d0[:, 1], d0[:, 0]) - np.radians(az))))))
    e_off = float(np.mean(np.degrees(np.arcsin(np.clip(d0[:, 2] / max(r0, 1e-9), -1, 1))) - el))
    sol = _fit.solve(lambda p: (_arm(p, az, el) - X).ravel(), np.r_[c0, r0, a_off, e_off],
                     what="positioner arm fit", max_evaluations=max_evaluations, method="lm")
    ray_rms = float("nan")
    if rays is not None:
        P, D, pose, weight = _rays_of_poses(rays, len(az))

        def misfit(p):  # sine of the angle between each ray and the direction to its model light
            w = _arm(p, az, el)[pose] - P
            return (weight[:, None] * np.cross(w / np.linalg.norm(w, axis=1, keepdims=True), D)).ravel()
        # robust: a highlight the lamp's spot picker got wrong turns its ray by degrees
        sol = _fit.solve(misfit, sol.x, what="positioner arm fit to the rays", max_evaluations=max_evaluations,
                         loss="soft_l1", f_scale=RAY_MISFIT_SCALE)
        ray_rms = float(np.degrees(np.arcsin(min(1.0, np.sqrt(3 * np.mean(sol.fun ** 2))))))
    J = sol.jac
    dof = max(sol.fun.size - 6, 1)
    try:
        cov = np.linalg.inv(J.T @ J) * (sol.fun @ sol.fun) / dof
    except np.linalg.LinAlgError:
        raise DegenerateFit("positioner model is undetermined by these poses") from None
    p = sol.x
    res = np.linalg.norm((_arm(p, az, el) - X), axis=1)
    return PositionerModel(p[:3], float(p[3]), float((p[4] + 180) % 360 - 180), float(p[5]),
                           np.sqrt(np.diag(cov)), res, int(sol.status), str(sol.message), ray_rms)


def ray_weights(points_mm, directions, camera_mm) -> np.ndarray:
    """Weights (R,) of reflected rays for :func:`fit_positioner_model`: ``n . v``, the cosine
    between the ball's normal at the reflection point and the direction to the camera. A
    highlight's pixel error turns the normal by ``delta / (r_px cos)`` across the limb (the
    sphere's foreshortening), so its ray's angular error grows as ``1 / (n . v)``.

    Parameters
    ----------
    points_mm, directions : ndarray of shape (R, 3)
        Reflection points and unit reflected directions (:func:`reflect_highlight`).
    camera_mm : array_like of shape (3,)
        The camera centre in the same frame (the origin in the camera frame).
    """
    P = _validate.array(points_mm, "points_mm", shape=(-1, 3))
    D = _validate.array(directions, "directions", shape=P.shape)
    v = np.asarray(camera_mm, float) - P
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    n = v + D / np.linalg.norm(D, axis=1, keepdims=True)   # the mirror normal bisects the two
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.sum(n * v, axis=1)


def _rays_of_poses(rays, poses: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Validated ``rays`` of :func:`fit_positioner_model`: points, unit directions, pose index,
    weight."""
    if len(rays) not in (3, 4):
        raise InvalidInput("rays must be (points_mm, directions, pose[, weight])", argument="rays")
    P = _validate.array(rays[0], "rays points_mm", shape=(-1, 3))
    D = _validate.array(rays[1], "rays directions", shape=(-1, 3))
    pose = np.asarray(rays[2])
    if D.shape != P.shape or pose.shape != (len(P),) or not np.issubdtype(pose.dtype, np.integer):
        raise InvalidInput(f"rays: points {P.shape}, directions {D.shape} and pose {pose.shape} must be "
                           "(R, 3), (R, 3) and (R,) integers", argument="rays")
    if len(pose) and (pose.min() < 0 or pose.max() >= poses):
        raise InvalidInput(f"rays pose index must lie in 0..{poses - 1}", argument="rays")
    weight = np.ones(len(P)) if len(rays) == 3 else _validate.array(rays[3], "rays weight", shape=(len(P),))
    if np.any(weight <= 0):
        raise InvalidInput("rays weight must be > 0", argument="rays")
    return P, D / np.linalg.norm(D, axis=1, keepdims=True), pose, weight
