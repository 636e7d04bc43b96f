"""Mirror spheres in images: finding them, their lamp highlights, and light directions.

The one-call entry point is :func:`light_directions_from_sphere` (images of a mirror sphere ->
light directions, orthographic or perspective). The pieces the session calibration chains for
rows of spheres are public too: :func:`sphere_silhouettes` (dark balls against a lit backdrop),
:func:`project_spheres` (spheres of known position), :func:`lamp_spots` (bright spots on a
ball that may be the lamp) and :func:`pick_lamp_highlights` (the spot per ball whose reflected
rays meet best), and :func:`find_mirror_sphere` (a sphere under an environment, for probes).

Frames: pixels x right, y down; camera frame OpenCV (x right, y down, z forward), mm. Light
directions point from the sphere towards the light (unit vectors, camera frame).
"""
from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from . import _validate
from .errors import InvalidInput, TargetNotFound, TooFewViews
from .lights import (SphereImage, closest_point_to_lines, detect_sphere, find_highlight,
                     light_direction_orthographic, reflect_highlight, sphere_center_from_silhouette)

__all__ = ["SphereLights", "LampSpot", "light_directions_from_sphere", "find_mirror_sphere",
           "sphere_silhouettes", "project_spheres", "lamp_spots", "pick_lamp_highlights"]

#: most spot combinations :func:`pick_lamp_highlights` tries (a ball row shows 1-2 spots per ball)
MAX_SPOT_COMBINATIONS = 4096


@dataclass(frozen=True)
class SphereLights:
    """Light directions measured on one mirror sphere (:func:`light_directions_from_sphere`).

    Attributes
    ----------
    directions : ndarray of shape (N, 3)
        Unit direction towards each image's light, camera frame (OpenCV).
    highlights_px : ndarray of shape (N, 2)
        The highlight in each image (x, y), pixels.
    sphere : SphereImage
        The sphere's image geometry used.
    center_mm : ndarray of shape (3,) or None
        Camera-frame sphere centre, mm (perspective model only).
    points_mm : ndarray of shape (N, 3) or None
        Where each highlight's ray reflects off the sphere, camera frame, mm (perspective only):
        with ``directions`` the ray towards a near light.
    model : {'orthographic', 'perspective'}
    """

    directions: np.ndarray
    highlights_px: np.ndarray
    sphere: SphereImage
    center_mm: np.ndarray | None
    points_mm: np.ndarray | None
    model: str


def light_directions_from_sphere(images, sphere=None, *, K=None, dist=None, radius_mm: float | None = None,
                                 saturation: float | None = None, names=None) -> SphereLights:
    """Light directions from images of one mirror sphere, one light per image.

    Orthographic (no ``K``): the sphere's image centre and radius give each highlight's normal
    (a distant camera). Perspective (``K`` and ``radius_mm``): the sphere's centre comes from its
    outline (:func:`~calibration.lights.sphere_center_from_silhouette`) and each highlight's
    viewing ray is reflected off it (:func:`~calibration.lights.reflect_highlight`), which is
    exact for any camera distance.

    Parameters
    ----------
    images : sequence of ndarray of shape (H, W) or (H, W, 3)
        Linear (or monotonic) images, one per light.
    sphere : SphereImage or ndarray of shape (H, W), optional
        The sphere: its geometry (``SphereImage(center_px, radius_px)`` when known; the
        perspective model needs its outline, i.e. a detected one), or a mask of it. Default:
        detected in the per-pixel maximum of the images (:func:`~calibration.lights.detect_sphere`).
    K : array_like of shape (3, 3), optional
        Camera matrix (pixels); selects the perspective model.
    dist : array_like, optional
        OpenCV distortion coefficients (perspective model).
    radius_mm : float, optional
        Sphere radius, mm (perspective model; sets the scale of ``center_mm`` / ``points_mm``).
    saturation : float, optional
        Sensor clipping level (:func:`~calibration.lights.find_highlight`).
    names : sequence of str, optional
        Frame names for the error messages (default ``image 0``, ``image 1``, ...).

    Returns
    -------
    SphereLights

    Raises
    ------
    TargetNotFound
        No credible sphere, or no highlight in an image (names it).
    InvalidInput
        ``K`` without ``radius_mm`` (or the reverse), or a bad argument.
    """
    imgs = [_validate.gray(im, f"images[{k}]") for k, im in enumerate(images)]
    if not imgs:
        raise TooFewViews("light directions (images)", have=0, need=1)
    if len({im.shape for im in imgs}) > 1:
        raise InvalidInput(f"images must share one shape, got {sorted({im.shape for im in imgs})}",
                           argument="images")
    names = [f"image {k}" for k in range(len(imgs))] if names is None else list(names)
    if len(names) != len(imgs):
        raise InvalidInput(f"names must hold one name per image ({len(imgs)}), got {len(names)}", argument="names")
    if (K is None) != (radius_mm is None):
        raise InvalidInput("the perspective model needs both K and radius_mm; give neither for the "
                           "orthographic model", argument="K" if K is None else "radius_mm")
    if sphere is None:
        sphere = detect_sphere(np.max(np.stack(imgs), axis=0), frame="the images' maximum")
    elif not isinstance(sphere, SphereImage):
        sphere = detect_sphere(sphere, frame="sphere mask")
    hl = np.array([find_highlight(im, sphere, saturation=saturation, frame=n).xy_px for im, n in zip(imgs, names)])
    if K is None:
        return SphereLights(light_direction_orthographic(hl, sphere), hl, sphere, None, None, "orthographic")
    centre = sphere_center_from_silhouette(sphere, K, dist, radius_mm)
    points, directions = reflect_highlight(hl, np.broadcast_to(centre, (len(hl), 3)), radius_mm, K, dist)
    return SphereLights(directions, hl, sphere, centre, points, "perspective")


def _tone(image) -> np.ndarray:
    """Grey view scaled so its 99.5th percentile is 1, clipped (hot pixels and highlights do not
    crush the contrast)."""
    g = _validate.gray(image, "image", dtype=np.float32)
    top = float(np.percentile(g, 99.5))
    return np.clip(g / top, 0.0, 1.0) if top > 0 else np.zeros_like(g)


def find_mirror_sphere(image, *, reflectance: float = 0.6, frame: str | None = None) -> SphereImage:
    """A mirror sphere under an environment (a light probe capture), to a fraction of a pixel.

    The strongest circle of OpenCV's gradient Hough transform on the tone-mapped image (the
    sphere's compressed reflection of the room differs from the background all round its limb)
    is only a start: on a ball 20 px in radius it locks onto the strong edges of the reflection
    inside the limb (12 % small on the quick demo's probe, which moves every direction near the
    rim by tens of degrees). :func:`_limb_circle` then finds the limb itself on rays from that
    centre and fits a circle to it.

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, 3)
        Linear radiance.
    reflectance : float
        The ball's mirror reflectance, in (0, 1) (chrome ~0.65, bearing steel ~0.55): its limb
        reflects the background right behind it at this fraction, so the outline is where the
        image crosses halfway between the two.
    frame : str, optional
        Frame name for the error message.

    Returns
    -------
    SphereImage
        Centre and radius, pixels (no outline).

    Raises
    ------
    TargetNotFound
        No circle in the image, or no limb around the circle found.
    """
    if not 0 < reflectance < 1:
        raise InvalidInput(f"reflectance must be in (0, 1), got {reflectance!r}", argument="reflectance")
    g = _validate.gray(image, "image", dtype=np.float32)
    g8 = (np.sqrt(_tone(g)) * 255).astype(np.uint8)
    h, w = g8.shape
    circles = cv2.HoughCircles(g8, cv2.HOUGH_GRADIENT_ALT, dp=1.0, minDist=min(h, w) / 4, param1=100,
                               param2=0.75, minRadius=5, maxRadius=min(h, w) // 2)
    if circles is None:
        raise TargetNotFound("no mirror sphere (no circle in the image)", frame=frame)
    x, y, r = (float(v) for v in circles.reshape(-1, 3)[0])
    centre, radius = _limb_circle(g, np.array([x, y]), r, level=(1 + reflectance) / 2, frame=frame)
    return SphereImage(centre, radius)


#: the limb search: rays from the start centre sample the image every LIMB_STEP_PX from
#: LIMB_SEARCH[0] to LIMB_SEARCH[1] start radii; the background level is their median beyond
#: LIMB_OUTSIDE start radii (the Hough start is within ~15 % of the limb)
LIMB_SEARCH, LIMB_OUTSIDE, LIMB_STEP_PX = (0.6, 1.6), 1.3, 0.05
#: searches from the last fit's circle (the second puts the background band outside the limb)
LIMB_PASSES = 2


def _limb_circle(gray: np.ndarray, centre: np.ndarray, radius: float, *, level: float,
                 frame: str | None) -> tuple[np.ndarray, float]:
    """A mirror ball's limb, fitted as a circle (centre (2,), radius; pixels).

    On each of ~one ray per pixel of circumference the limb is the outermost point, scanning in
    from the background, where the profile (bilinear) falls below ``level`` times the ray's
    background level; a pixel the limb cuts holds the area-weighted mix of background and limb,
    so that crossing is near the outline (on the quick demo's 20 px probe ball +0.2 px, as the
    reflection just inside the limb is darker than the background's; Hough: -2.4 px). A circle
    is fitted to those points
    (algebraic least squares), rays more than 3 robust sigmas off dropped (where the limb
    reflects something brighter than the background it hides, there is no crossing)."""
    for _ in range(LIMB_PASSES):
        n = max(64, int(2 * np.pi * radius))
        a = np.arange(n) * (2 * np.pi / n)
        s = np.arange(LIMB_SEARCH[0] * radius, LIMB_SEARCH[1] * radius, LIMB_STEP_PX)
        X = (centre[0] + np.cos(a)[:, None] * s).astype(np.float32)
        Y = (centre[1] + np.sin(a)[:, None] * s).astype(np.float32)
        P = cv2.remap(gray, X, Y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
        outside = s >= LIMB_OUTSIDE * radius
        with warnings.catch_warnings():  # a ray wholly outside the image has no background
            warnings.simplefilter("ignore", RuntimeWarning)
            background = np.nanmedian(P[:, outside], axis=1)
        below = (P < level * background[:, None]) & ~outside
        last = below.shape[1] - 1 - np.argmax(below[:, ::-1], axis=1)  # the outermost sample below
        ok = below.any(axis=1) & (last < len(s) - 1) & np.isfinite(background) & (background > 0)
        i = np.minimum(last, len(s) - 2)
        p0, p1 = P[np.arange(n), i], P[np.arange(n), i + 1]
        step = np.where(p1 != p0, p1 - p0, 1.0)
        edge = s[i] + np.clip((level * background - p0) / step, 0, 1) * LIMB_STEP_PX
        pts = centre + np.stack([np.cos(a), np.sin(a)], axis=1) * edge[:, None]
        keep = ok & np.isfinite(edge)
        for _ in range(3):
            if keep.sum() < n // 3:
                raise TargetNotFound(f"no mirror sphere limb around the circle at ({centre[0]:.0f}, {centre[1]:.0f}) "
                                     f"px: {int(keep.sum())} of {n} rays cross it", frame=frame)
            # x^2 + y^2 + D x + E y + F = 0
            A = np.column_stack([pts[keep], np.ones(keep.sum())])
            D, E, F = np.linalg.lstsq(A, -np.sum(pts[keep] ** 2, axis=1), rcond=None)[0]
            centre = np.array([-D / 2, -E / 2])
            radius = float(np.sqrt(max(centre @ centre - F, 1e-12)))
            res = np.linalg.norm(pts - centre, axis=1) - radius
            sigma = 1.4826 * np.median(np.abs(res[keep])) + 0.05
            keep = ok & (np.abs(res) < 3 * sigma)
    return centre, radius


def _round_blobs(mask: np.ndarray, min_area: int) -> list[tuple[int, np.ndarray]]:
    """Compact, round connected components of ``mask`` not touching the border, as
    (diameter px, boolean mask)."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=4)
    h, w = mask.shape
    out = []
    for k in range(1, n):  # a few blobs
        x, y, bw, bh, area = stats[k]
        if area < min_area or x == 0 or y == 0 or x + bw >= w or y + bh >= h:
            continue  # too small, or open to the border: background, not a sphere
        if not 0.7 < bw / bh < 1.4 or area < 0.6 * np.pi * (max(bw, bh) / 2) ** 2:
            continue  # not round
        out.append((int(max(bw, bh)), labels == k))
    return out


def sphere_silhouettes(images, reflectance: float, *, min_area: int = 30) -> list[np.ndarray]:
    """Silhouettes of mirror spheres in front of a lit backdrop, left to right.

    The per-pixel median over the frames removes each frame's moving highlight and shadows;
    dark round blobs in it are the candidate spheres. A mirror's limb reflects the backdrop
    right behind it times the mirror's ``reflectance``, so each outline is then redrawn halfway
    between the backdrop level *around that sphere* (median of an annulus) and that limb level,
    not at a global dark threshold, which would shrink the silhouette by the bright limb ring
    and bias the sphere's depth.

    Parameters
    ----------
    images : sequence of ndarray of shape (H, W) or (H, W, 3)
        Linear images of the same view (e.g. one per light).
    reflectance : float
        The spheres' mirror reflectance, in (0, 1) (chrome ~0.65, bearing steel ~0.55).
    min_area : int
        Smallest silhouette, pixels.

    Returns
    -------
    list of ndarray of shape (H, W), bool
        One mask per sphere, ordered by image x.
    """
    frames = [_validate.gray(im, f"images[{k}]", dtype=np.float32) for k, im in enumerate(images)]
    if not frames:
        raise TooFewViews("sphere silhouettes (images)", have=0, need=1)
    if not 0 < reflectance < 1:
        raise InvalidInput(f"reflectance must be in (0, 1), got {reflectance!r}", argument="reflectance")
    med = np.median(np.stack(frames), axis=0).astype(np.float32)
    h, w = med.shape
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    out = []
    for diam, coarse in _round_blobs(med < 0.3 * float(np.percentile(med, 95)), min_area):
        cy, cx = (float(v.mean()) for v in np.nonzero(coarse))
        # work in a window around the sphere (1.6 radii: the annulus' outer edge)
        y0, y1 = max(int(cy - 0.8 * diam), 0), min(int(cy + 0.8 * diam) + 2, h)
        x0, x1 = max(int(cx - 0.8 * diam), 0), min(int(cx + 0.8 * diam) + 2, w)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        win = med[y0:y1, x0:x1]
        r = np.hypot(yy - cy, xx - cx) / (diam / 2)
        level = 0.5 * (1 + reflectance) * float(np.median(win[(r > 1.2) & (r < 1.6)]))
        local = cv2.morphologyEx(((win < level) & (r < 1.3)).astype(np.uint8), cv2.MORPH_OPEN, disc)
        _, labels = cv2.connectedComponents(local, connectivity=4)
        k = labels[int(round(cy)) - y0, int(round(cx)) - x0]
        if k:
            mask = np.zeros(med.shape, bool)
            mask[y0:y1, x0:x1] = labels == k
            out.append((cx, mask))
    return [b for _, b in sorted(out, key=lambda t: t[0])]


def project_spheres(centers_mm, radius_mm: float, K, dist, image_size: tuple[int, int]
                    ) -> tuple[list[SphereImage], np.ndarray]:
    """Image discs of spheres of known camera-frame position, those wholly inside the image.

    Parameters
    ----------
    centers_mm : array_like of shape (M, 3)
        Sphere centres, camera frame, mm.
    radius_mm : float
        Sphere radius, mm.
    K, dist : camera matrix (3, 3) and OpenCV distortion.
    image_size : (int, int)
        Image (width, height), pixels.

    Returns
    -------
    spheres : list of SphereImage
        Projected centre and apparent radius (the outline cone's half-angle times the focal
        length) of each sphere inside the image.
    inside : ndarray of shape (K,), int
        Their indices in ``centers_mm``.

    Raises
    ------
    InvalidInput
        A sphere lies behind (or around) the camera.
    """
    C = _validate.array(centers_mm, "centers_mm", shape=(-1, 3))
    radius_mm = _validate.positive(radius_mm, "radius_mm")
    K, dist = _validate.camera(K, dist)
    if np.any(C[:, 2] <= radius_mm):
        raise InvalidInput(f"centers_mm: sphere(s) {np.nonzero(C[:, 2] <= radius_mm)[0].tolist()} lie behind "
                           "the camera (z <= radius)", argument="centers_mm")
    px = cv2.projectPoints(C, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    r_px = np.sqrt(K[0, 0] * K[1, 1]) * np.tan(np.arcsin(radius_mm / np.linalg.norm(C, axis=1)))
    w, h = image_size
    inside = (px[:, 0] - r_px >= 0) & (px[:, 1] - r_px >= 0) & (px[:, 0] + r_px < w) & (px[:, 1] + r_px < h)
    return [SphereImage(p, float(r)) for p, r in zip(px[inside], r_px[inside])], np.nonzero(inside)[0]


@dataclass(frozen=True)
class LampSpot:
    """A bright spot on a sphere that may be the lamp's image.

    Attributes
    ----------
    xy_px : ndarray of shape (2,)
        Sub-pixel position (:func:`~calibration.lights.find_highlight` on the spot), pixels.
    flux : float
        Summed image value over the spot (image units x pixels).
    """

    xy_px: np.ndarray
    flux: float


def lamp_spots(image, sphere: SphereImage, level: float, *, frame: str | None = None) -> list[LampSpot]:
    """Bright spots above ``level`` on one sphere's disc, largest flux first.

    Besides the lamp's own image, a ball in a row shows the lamp once more through its
    neighbour (a smaller, dimmer spot near the limb facing it); once the HDR merge clips both,
    only their size and where their reflected rays go tell them apart
    (:func:`pick_lamp_highlights`).

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, 3)
        Linear image.
    sphere : SphereImage
        The sphere's disc (shrunk by 1 px for the search).
    level : float
        Spot threshold, image units.
    frame : str, optional
        Frame name for error messages.

    Returns
    -------
    list of LampSpot
    """
    lum = _validate.gray(image, "image")
    if not isinstance(sphere, SphereImage):
        raise InvalidInput(f"sphere must be a SphereImage, got {type(sphere).__name__}", argument="sphere")
    c, r = sphere.center_px, sphere.radius_px
    x0, y0 = np.maximum(np.floor(c - r).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(c + r).astype(int) + 1, [lum.shape[1], lum.shape[0]])
    win = lum[y0:y1, x0:x1]
    yy, xx = np.mgrid[y0:y1, x0:x1]
    disc = (xx - c[0]) ** 2 + (yy - c[1]) ** 2 < (r - 1) ** 2
    n, labels = cv2.connectedComponents(((win > level) & disc).astype(np.uint8), connectivity=8)
    local = SphereImage(c - [x0, y0], r)
    out = []
    for k in range(1, n):  # a few spots per ball
        blob = labels == k
        hl = find_highlight(np.where(blob, win, 0.0), local, frame=frame)
        out.append(LampSpot(hl.xy_px + [x0, y0], float(win[blob].sum())))
    return sorted(out, key=lambda s: -s.flux)


def pick_lamp_highlights(spots, centers_mm, radius_mm: float, K, dist=None) -> tuple[np.ndarray, np.ndarray]:
    """One lamp highlight per sphere: of every combination of the spheres' spots, the one whose
    reflected rays meet best.

    "Best": the least-squares light of the combination sees the smallest RMS angle between each
    reflected ray and the direction from its reflection point to the light (an angle, not a
    distance: rays all pass near the balls they leave). A sphere whose ray then misses by more
    than 3x the median angle (and 1 deg) sits the light out when 2 others remain.

    Parameters
    ----------
    spots : sequence of sequence of LampSpot
        The candidate spots of each sphere (:func:`lamp_spots`), each non-empty.
    centers_mm : array_like of shape (M, 3)
        The spheres' centres, camera frame, mm.
    radius_mm : float
        Sphere radius, mm.
    K, dist : camera matrix (3, 3) and OpenCV distortion.

    Returns
    -------
    highlights_px : ndarray of shape (K, 2)
        The chosen spot of each sphere kept, pixels.
    kept : ndarray of shape (K,), int
        Their spheres' indices in ``spots``.
    """
    if len(spots) < 2 or any(len(s) == 0 for s in spots):
        raise TooFewViews("lamp highlights (spheres with a spot)", have=sum(len(s) > 0 for s in spots), need=2)
    C = _validate.array(centers_mm, "centers_mm", shape=(len(spots), 3))
    xy = np.array([s.xy_px for ss in spots for s in ss])
    owner = np.repeat(np.arange(len(spots)), [len(ss) for ss in spots])
    P, L = reflect_highlight(xy, C[owner], radius_mm, K, dist)
    first = np.r_[0, np.cumsum([len(ss) for ss in spots])[:-1]]
    combos = np.array(list(itertools.islice(itertools.product(*[range(len(ss)) for ss in spots]),
                                            MAX_SPOT_COMBINATIONS))) + first     # (C, M) spot rows
    Pc, Lc = P[combos], L[combos]                                                # (C, M, 3)
    X = closest_point_to_lines(Pc, Lc)[0]                                        # (C, 3)
    to = X[:, None] - Pc
    cos = np.sum(to * Lc, axis=2) / np.maximum(np.linalg.norm(to, axis=2), 1e-9)
    ang = np.degrees(np.arccos(np.clip(cos, -1, 1)))                             # (C, M)
    best = int(np.argmin(np.sqrt(np.mean(ang ** 2, axis=1))))
    keep = np.arange(len(spots))
    a = ang[best]
    if len(spots) > 2:
        keep = keep[(a <= max(3 * float(np.median(a)), 1.0)) | (np.argsort(np.argsort(a)) < 2)]
    return xy[combos[best][keep]], keep
