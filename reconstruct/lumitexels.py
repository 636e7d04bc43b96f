"""Lumitexels: per surface point, its position, normal and reflectance samples (Lensch 2003, Sec. 5).

All three reconstruction methods start here. A lumitexel is made for every surface point seen
at the image sampling density; each of its reflectance samples holds the light and view
directions in the point's local frame and the measured reflectance

    r = L * d^2 / I  =  f_r(wi, wo) * cos(theta_i)          (the paper's Eq. 6 convention)

where ``L`` is the pixel's radiance, ``d`` the distance to the point light (mm) and ``I`` its
radiant intensity (same units as the renderer: radiance = f_r * I / d^2 * cos). The cosine stays
in the sample, as in the paper, so a fitted BRDF is compared as ``f(wi, wo) * wi_z`` against
``r``; :meth:`Lumitexels.brdf_values` divides it out when a method wants f_r itself.

Frames: everything is computed in the object frame (the frame of the mesh's vertices, mm). For a
turntable capture, each :class:`View` gives ``object_to_world`` (the object's pose at that
turntable angle); cameras and lights are taken into the object frame with its inverse. Local
frames are :func:`reconstruct.frames.tangent_frames` of the interpolated normal (rows t, b, n).

Layout: struct of arrays, samples sorted by texel (``offsets`` is the CSR pointer), so fitters
vectorise over samples and :meth:`Lumitexels.chunks` cuts independent pieces for a distributed run.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np
import trimesh

from .camera import CameraModel
from .frames import tangent_frames, to_local, to_world
from .photometric_stereo import texel_normal_equations
from .raycast import Mesh, Surface, first_hits, occluded


class LumitexelError(ValueError):
    """Inputs that cannot give lumitexels (shapes, empty views, nothing visible)."""


@dataclass(frozen=True)
class View:
    """One calibrated HDR capture.

    Attributes
    ----------
    camera : CameraModel
        Intrinsics, distortion and world -> camera pose.
    radiance : ndarray of shape (H, W, 3)
        Linear HDR radiance (float32), same units as ``light_intensity`` / mm^2. None only where
        a pipeline keeps a view's geometry without its images (an out-of-core run).
    light_position : ndarray of shape (3,)
        Point light position, world frame, mm.
    light_intensity : float or ndarray of shape (3,)
        Radiant intensity of the light (RGB, per sr).
    object_to_world : ndarray of shape (4, 4)
        Pose of the object (mesh frame -> world) in this capture, e.g. the turntable rotation.
    valid : ndarray of shape (H, W), bool, optional
        Usable pixels (unsaturated, well exposed); default all.
    diffuse, specular : ndarray of shape (H, W, 3), optional
        Polarization-separated components of ``radiance`` (sampled alongside when given).
    """

    camera: CameraModel
    radiance: np.ndarray
    light_position: np.ndarray
    light_intensity: object = 1.0
    object_to_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    valid: np.ndarray | None = None
    diffuse: np.ndarray | None = None
    specular: np.ndarray | None = None


@dataclass
class Lumitexels:
    """Surface points and their reflectance samples (struct of arrays, object frame, mm).

    Per texel (P): ``position`` (P, 3), ``normal`` (P, 3) unit, ``best_view`` (P,) the view the
    point was generated from, ``pixel`` (P, 2) its pixel there, and ``footprint_spread_deg`` (P,)
    float32 or None: how much the surface normal turns across the texel's pixel footprint there,
    degrees (:func:`footprint_normal_spread`; NaN where the samples cannot tell).
    Per sample (S, sorted by texel): ``texel`` (S,), ``view`` (S,), ``wi`` / ``wo`` (S, 3) local unit
    directions to the light / camera, ``reflectance`` (S, 3) = f_r cos(theta_i), ``weight`` (S,);
    ``diffuse`` / ``specular`` (S, 3) when separated images were given.
    """

    position: np.ndarray
    normal: np.ndarray
    best_view: np.ndarray
    pixel: np.ndarray
    texel: np.ndarray
    view: np.ndarray
    wi: np.ndarray
    wo: np.ndarray
    reflectance: np.ndarray
    weight: np.ndarray
    diffuse: np.ndarray | None = None
    specular: np.ndarray | None = None
    footprint_spread_deg: np.ndarray | None = None

    _TEXEL_FIELDS = ("position", "normal", "best_view", "pixel", "footprint_spread_deg")

    @property
    def n_texels(self) -> int:
        return len(self.position)

    @property
    def n_samples(self) -> int:
        return len(self.texel)

    @property
    def offsets(self) -> np.ndarray:
        """CSR pointer (P + 1,): samples of texel i are ``offsets[i]:offsets[i+1]``."""
        return np.concatenate([[0], np.cumsum(np.bincount(self.texel, minlength=self.n_texels))])

    @property
    def counts(self) -> np.ndarray:
        """Samples per texel (P,)."""
        return np.bincount(self.texel, minlength=self.n_texels)

    def brdf_values(self) -> np.ndarray:
        """f_r = reflectance / cos(theta_i) per sample (S, 3), 1/sr."""
        return self.reflectance / np.maximum(self.wi[:, 2:3], 1e-6)

    def subset(self, texels: np.ndarray) -> "Lumitexels":
        """The lumitexels with the given (sorted, unique) indices, re-indexed from 0."""
        texels = np.asarray(texels, dtype=np.int64)
        remap = -np.ones(self.n_texels, np.int64)
        remap[texels] = np.arange(len(texels))
        keep = remap[self.texel] >= 0
        kw = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
                kw[f.name] = None
            elif f.name in self._TEXEL_FIELDS:
                kw[f.name] = v[texels]
            elif f.name == "texel":
                kw[f.name] = remap[v[keep]]
            else:
                kw[f.name] = v[keep]
        return Lumitexels(**kw)

    def chunks(self, n_chunks: int) -> Iterator["Lumitexels"]:
        """Split into ``n_chunks`` independent pieces of about equal sample counts."""
        if n_chunks < 1:
            raise ValueError(f"n_chunks must be >= 1, got {n_chunks}")
        cum = np.cumsum(self.counts)
        bounds = np.searchsorted(cum, np.linspace(0, cum[-1] if len(cum) else 0, n_chunks + 1)[1:-1])
        for idx in np.split(np.arange(self.n_texels), bounds):
            if len(idx):
                yield self.subset(idx)

    def save(self, path: str | Path) -> None:
        """Write to a compressed ``.npz``."""
        arrays = {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> "Lumitexels":
        with np.load(path) as z:
            return cls(**{f.name: (z[f.name] if f.name in z.files else None) for f in fields(cls)})


#: Fewest samples (weight > 0) that give a texel a photometric normal (3 unknowns, highlights
#: trimmed); texels with fewer get no footprint spread (NaN).
SPREAD_MIN_SAMPLES = 6


def _photometric_normals(lt: Lumitexels) -> tuple[np.ndarray, np.ndarray]:
    """Per texel a Lambertian normal from its own samples, object frame (P, 3), and whether the
    samples fix it (P,) bool.

    Least squares of the channel-summed reflectance ``r = g . wi`` (local frame), refit three
    times without the samples above 1.3 x the fit's prediction (plus 2 % of |g|): a glossy texel's
    few highlight samples otherwise pull its normal towards their mirror direction (on the bumpy
    demo object the median error against the true normal falls from 6 to 1.3 deg)."""
    P = lt.n_texels
    tx = lt.texel
    r = lt.reflectance.sum(axis=1, dtype=np.float64)
    wi = lt.wi.astype(np.float64)
    w0 = (lt.weight > 0).astype(np.float64)

    def solve(w):
        A, b = texel_normal_equations(tx, wi, r, w, P)
        return A, np.linalg.solve(A + 1e-12 * np.eye(3), b[..., None])[..., 0]

    w = w0
    for _ in range(3):
        _, g = solve(w)
        pred = np.einsum("si,si->s", g[tx], wi)
        w = w0 * (r <= 1.3 * np.maximum(pred, 0.0) + 0.02 * np.linalg.norm(g[tx], axis=1))
    A, g = solve(w)
    n = np.bincount(tx, w, P)
    # the lights must span the normal's three degrees of freedom: the weakest direction of the
    # samples' light spread holds at least 5 % of an even share
    ok = (n >= SPREAD_MIN_SAMPLES) & (np.linalg.eigvalsh(A)[:, 0] > 0.05 * n / 3) & \
        (np.linalg.norm(g, axis=1) > 0)
    local = np.where(ok[:, None], g, [0.0, 0.0, 1.0])
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    return to_world(local, tangent_frames(lt.normal)), ok


def pixel_neighbours(lt: Lumitexels) -> np.ndarray:
    """Each texel's neighbours on the pixels right, left, below and above its own in its best
    view (the texel that view made there), (4, P) int64; -1 where that pixel made none."""
    P = lt.n_texels
    out = np.full((4, P), -1, np.int64)
    if P == 0:
        return out
    px = np.rint(lt.pixel).astype(np.int64)
    key = (lt.best_view.astype(np.int64) << 42) | (px[:, 1] << 21) | px[:, 0]
    order = np.argsort(key)
    sorted_key = key[order]
    for k, (dx, dy) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
        want = key + (dy << 21) + dx
        at = np.minimum(np.searchsorted(sorted_key, want), P - 1)
        out[k] = np.where(sorted_key[at] == want, order[at], -1)
    return out


def footprint_normal_spread(lt: Lumitexels) -> np.ndarray:
    """How much the surface normal turns across each texel's pixel footprint in its best view,
    (P,) float32, degrees; NaN where the samples cannot tell.

    The mesh need not hold the relief the images show (Lensch Sec. 9: detail below the scan's
    resolution; the demo's bumpy object is fitted on a smooth sphere), so the normal is measured
    from the reflectance: a per-texel Lambertian normal from its samples with weight > 0
    (:func:`_photometric_normals`), then the median angle between it and those of its four pixel
    neighbours that the same best view made. That is the normal's turn over one pixel, the
    footprint a sample's bilinear lookup spans; on the smooth sphere it is the curvature's
    ~2 deg plus noise, across the bumpy object's engraved ring 5-20 deg. A texel whose
    reflectance mixes normals cannot be explained by one: Lensch keeps such texels out of
    material discovery (``SvbrdfOptions.max_footprint_spread_deg``).

    Cost: a few bincounts over the samples and one sort of the texels (0.35 s for 85,000
    samples); samples with weight 0 (held out) take no part.
    """
    P = lt.n_texels
    if P == 0:
        return np.zeros(0, np.float32)
    normal, ok = _photometric_normals(lt)
    angles = np.full((4, P), np.nan)
    for k, j in enumerate(pixel_neighbours(lt)):
        found = (j >= 0) & ok & ok[np.maximum(j, 0)]
        cos = np.clip(np.einsum("ij,ij->i", normal, normal[np.maximum(j, 0)]), -1.0, 1.0)
        angles[k] = np.where(found, np.degrees(np.arccos(cos)), np.nan)
    spread = np.full(P, np.nan, np.float32)
    some = np.isfinite(angles).any(axis=0)
    spread[some] = np.nanmedian(angles[:, some], axis=0)
    return spread


# ----------------------------------------------------------------------------------------------
# assembly
# ----------------------------------------------------------------------------------------------
def _check_views(views: Sequence[View]) -> None:
    if len(views) == 0:
        raise LumitexelError("no views given")
    for k, v in enumerate(views):
        H, W = v.camera.height, v.camera.width
        if np.shape(v.radiance) != (H, W, 3):
            raise LumitexelError(f"views[{k}].radiance must have shape {(H, W, 3)} (camera size), "
                                 f"got {np.shape(v.radiance)}")
        if v.valid is not None and np.shape(v.valid) != (H, W):
            raise LumitexelError(f"views[{k}].valid must have shape {(H, W)}, got {np.shape(v.valid)}")
        if np.shape(v.light_position) != (3,):
            raise LumitexelError(f"views[{k}].light_position must be a 3-vector (mm), got "
                                 f"{np.shape(v.light_position)}")
        for name in ("diffuse", "specular"):
            img = getattr(v, name)
            if img is not None and np.shape(img) != (H, W, 3):
                raise LumitexelError(f"views[{k}].{name} must have shape {(H, W, 3)}")


def _bounds_corners(surfaces: Sequence[Surface]) -> np.ndarray | None:
    """Corners (8k, 3) of the surfaces' bounding boxes (object frame), None if any is unbounded."""
    out = []
    for srf in surfaces:
        if isinstance(srf, Mesh):
            c = trimesh.bounds.corners(srf.mesh.bounds)
            out.append(c @ srf.transform[:3, :3].T + srf.transform[:3, 3])
        elif np.isfinite(srf.bounding_radius):
            r = srf.bounding_radius
            out.append(np.array([[x, y, z] for x in (-r, r) for y in (-r, r) for z in (-r, r)]))
        else:
            return None
    return np.concatenate(out)


def _pixels_covering(cam: CameraModel, corners: np.ndarray | None) -> np.ndarray:
    """Flat indices of the pixels whose rays may hit the geometry: its projected bounding box
    (plus a margin for distortion), or the whole image when a corner lies behind the camera."""
    x0, y0, x1, y1 = 0, 0, cam.width - 1, cam.height - 1
    if corners is not None and np.all(cam.depth(corners) > 0):
        px = cam.project(corners)
        x0 = int(max(np.floor(px[:, 0].min()) - 2, 0))
        y0 = int(max(np.floor(px[:, 1].min()) - 2, 0))
        x1 = int(min(np.ceil(px[:, 0].max()) + 2, cam.width - 1))
        y1 = int(min(np.ceil(px[:, 1].max()) + 2, cam.height - 1))
        if x1 < x0 or y1 < y0:
            return np.zeros(0, np.int64)
    ys, xs = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    return (ys * cam.width + xs).ravel()


def _box_blur(img: np.ndarray, k: int) -> np.ndarray:
    return cv2.blur(img.astype(np.float32), (k, k), borderType=cv2.BORDER_REPLICATE)


def _reject_map(depth: np.ndarray, shadow: np.ndarray, *, filter_px: int, jump_mm: float) -> np.ndarray:
    """Pixels near depth discontinuities or shadow boundaries (Sec. 5.2), (H, W) bool.

    The depth map is blurred with a ``filter_px`` box; on a locally planar surface the box mean
    equals the centre value, while within ``filter_px // 2`` pixels of a jump of ``jump_mm`` it
    moves by at least ``jump_mm / filter_px`` (at least one column of the box lies across the
    jump): that is the threshold. Background counts as a far surface so silhouettes are discontinuities. The
    blurred lit/unlit map marks shadow boundaries where it is neither 0 nor 1.
    """
    far = np.where(np.isfinite(depth), depth, np.nanmax(np.where(np.isfinite(depth), depth, np.nan))
                   + 10 * jump_mm if np.isfinite(depth).any() else 0.0)
    blurred = _box_blur(far, filter_px)
    near_jump = np.abs(blurred - far) > jump_mm / filter_px
    shadow_blur = _box_blur(shadow.astype(np.float32), filter_px)
    near_shadow_edge = (shadow_blur > 1e-3) & (shadow_blur < 1 - 1e-3)
    return near_jump | near_shadow_edge


def _sample(img: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Bilinear samples of an (H, W, C) image at pixel coordinates (N, 2) inside the image."""
    H, W = img.shape[:2]
    x = np.clip(px[:, 0], 0, W - 1)
    y = np.clip(px[:, 1], 0, H - 1)
    x0 = np.minimum(x.astype(np.int64), W - 2)
    y0 = np.minimum(y.astype(np.int64), H - 2)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    bottom = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


@dataclass(frozen=True)
class AssemblyGeometry:
    """What every view's pass of the assembly shares (object frame, mm): the object ``surface``,
    the ``blockers`` that hide or shadow it (the surface first), their bounding-box ``corners``
    (None: unbounded), the rejection box ``reject_filter_px`` and depth jump ``jump_mm``, the
    grazing cut ``min_cos`` and the surface's face count ``n_faces``."""

    surface: Surface
    blockers: tuple[Surface, ...]
    corners: np.ndarray | None
    reject_filter_px: int
    jump_mm: float
    min_cos: float
    n_faces: int


def assembly_geometry(mesh: trimesh.Trimesh | Surface, *, occluders: Sequence[Surface] = (),
                      reject_filter_px: int = 5, reject_jump_mm: float | None = None,
                      min_cos: float = 0.05) -> AssemblyGeometry:
    """The shared part of :func:`assemble_lumitexels` (its parameters, same meaning)."""
    surface = mesh if isinstance(mesh, Surface) else Mesh(mesh)
    blockers = (surface, *occluders)
    extent = float(np.ptp(surface.mesh.bounds, axis=0).max()) if isinstance(surface, Mesh) else \
        2 * surface.bounding_radius
    jump = 0.02 * extent if reject_jump_mm is None else reject_jump_mm
    F = len(surface.mesh.faces) if isinstance(surface, Mesh) else 1
    return AssemblyGeometry(surface, blockers, _bounds_corners(blockers), reject_filter_px, jump, min_cos, F)


def object_frame_camera(camera: CameraModel, object_to_world: np.ndarray) -> CameraModel:
    """``camera`` with its pose expressed relative to the object (object -> camera)."""
    T = np.asarray(object_to_world, float)
    return camera.with_pose(camera.R @ T[:3, :3], camera.R @ T[:3, 3] + camera.t)


def object_frame_point(object_to_world: np.ndarray, p_world) -> np.ndarray:
    """A world point (mm) in the object frame."""
    T = np.asarray(object_to_world, float)
    return np.linalg.solve(T[:3, :3], np.asarray(p_world, float) - T[:3, 3])


@dataclass(frozen=True)
class ViewHits:
    """Pass 1 of one view (object frame): the flat indices ``pixel`` (N,) of the pixels whose rays
    hit the object, their ``face`` (N,), hit ``position`` (N, 3) mm and interpolated ``normal``
    (N, 3); and ``reject`` (H * W,) bool, the pixels near a depth jump or cast-shadow edge."""

    pixel: np.ndarray
    face: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    reject: np.ndarray

    def face_areas(self, n_faces: int) -> np.ndarray:
        """Visible pixels per face (F,): the measure of the paper's I_best."""
        return np.bincount(np.maximum(self.face, 0), minlength=n_faces)


def view_hits(geom: AssemblyGeometry, cam: CameraModel, light: np.ndarray) -> ViewHits:
    """Pass 1 of one view: ray-cast the pixels that may see the object and make the rejection
    map. ``cam`` and ``light`` (mm) in the object frame (:func:`object_frame_camera`,
    :func:`object_frame_point`); needs no image."""
    blockers = list(geom.blockers)
    pix = _pixels_covering(cam, geom.corners)
    o, d = cam.pixel_rays(np.stack([pix % cam.width, pix // cam.width], axis=1))
    hits = first_hits(blockers, o, d)
    on_obj = hits.surface_index == 0
    if geom.reject_filter_px > 1:
        depth = np.full(cam.width * cam.height, np.inf)
        depth[pix[hits.mask]] = cam.depth(hits.position[hits.mask])
        # cast shadows only: the attached-shadow terminator fades smoothly and is kept
        shadow = np.zeros(cam.width * cam.height, bool)
        idx = np.flatnonzero(hits.mask)
        to_l = light - hits.position[idx]
        dist = np.linalg.norm(to_l, axis=1)
        to_l /= dist[:, None]
        facing = np.einsum("ij,ij->i", hits.geometric_normal[idx], to_l) > 0
        idx, to_l, dist = idx[facing], to_l[facing], dist[facing]
        shadow[pix[idx]] = occluded(blockers, hits.position[idx], to_l, dist,
                                    normals=hits.geometric_normal[idx])
        reject = _reject_map(depth.reshape(cam.height, cam.width), shadow.reshape(cam.height, cam.width),
                             filter_px=geom.reject_filter_px, jump_mm=geom.jump_mm).ravel()
    else:
        reject = np.zeros(cam.width * cam.height, bool)
    return ViewHits(pix[on_obj], hits.face_index[on_obj], hits.position[on_obj], hits.normal[on_obj], reject)


@dataclass(frozen=True)
class Texels:
    """Surface points (object frame): ``position`` (P, 3) mm, unit ``normal`` (P, 3), the view
    each was made in ``best_view`` (P,) and its ``pixel`` (P, 2) there."""

    position: np.ndarray
    normal: np.ndarray
    best_view: np.ndarray
    pixel: np.ndarray


def view_texels(hits: ViewHits, best: np.ndarray, k: int, width: int) -> Texels:
    """The texels view ``k`` makes: the pixels of the faces whose best view (``best`` (F,)) is k;
    normals not yet normalised (:func:`join_texels` does)."""
    sel = best[np.maximum(hits.face, 0)] == k
    pix = hits.pixel[sel]
    return Texels(hits.position[sel], hits.normal[sel], np.full(sel.sum(), k, np.int32),
                  np.stack([pix % width, pix // width], axis=1).astype(np.float32))


def join_texels(parts: Sequence[Texels]) -> Texels:
    """The views' texels in view order, normals made unit."""
    parts = [p for p in parts if len(p.position)]
    if not parts:
        raise LumitexelError("the object is not visible in any view (check poses and the mesh frame)")
    normal = np.concatenate([p.normal for p in parts])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return Texels(np.concatenate([p.position for p in parts]), normal,
                  np.concatenate([p.best_view for p in parts]), np.concatenate([p.pixel for p in parts]))


@dataclass(frozen=True)
class ViewSamples:
    """One view's reflectance samples of a block of texels: ``texel`` (n,) indices into the
    block, ``wi`` / ``wo`` (n, 3) local unit directions, ``reflectance`` (n, 3) ``f_r cos``;
    ``diffuse`` / ``specular`` (n, 3) or None (float32)."""

    texel: np.ndarray
    wi: np.ndarray
    wo: np.ndarray
    reflectance: np.ndarray
    diffuse: np.ndarray | None
    specular: np.ndarray | None


def view_samples(geom: AssemblyGeometry, view: View, cam: CameraModel, light: np.ndarray,
                 reject: np.ndarray, position: np.ndarray, normal: np.ndarray, *,
                 separated: bool) -> ViewSamples:
    """Pass 2 of one view over a block of texels (``position``, unit ``normal`` (n, 3), object
    frame): a sample per texel where the point is seen and lit, not grazing, and none of the four
    pixels its bilinear sample touches is rejected (``reject`` (H * W,)) or invalid. Each texel's
    sample depends on that texel alone, so blocks give the same samples as the whole set."""
    blockers = list(geom.blockers)
    frames = tangent_frames(normal)
    to_c = cam.center - position
    dc = np.linalg.norm(to_c, axis=1)
    to_c /= dc[:, None]
    to_l = light - position
    dl = np.linalg.norm(to_l, axis=1)
    to_l /= dl[:, None]
    cos_o = np.einsum("ij,ij->i", normal, to_c)
    cos_i = np.einsum("ij,ij->i", normal, to_l)
    cand = np.flatnonzero((cos_o > geom.min_cos) & (cos_i > geom.min_cos))
    if len(cand) == 0:   # a block facing away (the projection takes no empty input)
        empty = np.zeros((0, 3), np.float32)
        return ViewSamples(cand, empty, empty, empty, empty if separated else None, empty if separated else None)
    px = cam.project(position[cand])
    inside = (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] <= cam.width - 1) & \
             (px[:, 1] <= cam.height - 1)
    cand, px = cand[inside], px[inside]
    seen = ~occluded(blockers, position[cand], to_c[cand], dc[cand], normals=normal[cand])
    cand, px = cand[seen], px[seen]
    lit = ~occluded(blockers, position[cand], to_l[cand], dl[cand], normals=normal[cand])
    cand, px = cand[lit], px[lit]
    # rejection and validity at the four pixels the bilinear sample touches
    bad = reject.reshape(cam.height, cam.width)
    if view.valid is not None:
        bad = bad | ~np.asarray(view.valid, bool)
    x0 = np.clip(np.floor(px[:, 0]).astype(int), 0, cam.width - 2)
    y0 = np.clip(np.floor(px[:, 1]).astype(int), 0, cam.height - 2)
    drop = bad[y0, x0] | bad[y0, x0 + 1] | bad[y0 + 1, x0] | bad[y0 + 1, x0 + 1]
    cand, px = cand[~drop], px[~drop]
    scale = dl[cand, None] ** 2 / np.broadcast_to(np.asarray(view.light_intensity, float), (3,))
    sample = lambda img: (_sample(img, px) * scale).astype(np.float32)  # noqa: E731
    return ViewSamples(cand, to_local(to_l[cand], frames[cand]).astype(np.float32),
                       to_local(to_c[cand], frames[cand]).astype(np.float32), sample(view.radiance),
                       sample(view.diffuse) if separated else None, sample(view.specular) if separated else None)


def best_views(areas: np.ndarray) -> np.ndarray:
    """I_best per face from the visible areas (F, V): the view where the face covers most pixels."""
    return np.argmax(areas, axis=1)


def assemble_lumitexels(mesh: trimesh.Trimesh | Surface, views: Sequence[View], *,
                        occluders: Sequence[Surface] = (), reject_filter_px: int = 5,
                        reject_jump_mm: float | None = None, min_cos: float = 0.05,
                        progress=None) -> Lumitexels:
    """Resample HDR views onto the surface: one lumitexel per visible surface point.

    Parameters
    ----------
    mesh : trimesh.Trimesh or raycast.Surface
        The object's geometry in its own frame (mm).
    views : sequence of View
        Calibrated captures (camera, HDR radiance, light, object pose).
    occluders : sequence of raycast.Surface
        Other geometry that can hide or shadow the object, object frame (mm).
    reject_filter_px : int
        Box filter size of the depth-discontinuity / shadow-boundary test (odd, pixels); 0 or 1
        disables rejection.
    reject_jump_mm : float, optional
        Smallest depth jump treated as a discontinuity; default 2 % of the mesh's bounding size.
    min_cos : float
        Samples with cos(theta_i) or cos(theta_o) below this are dropped (grazing: unreliable).
    progress : callable, optional
        ``progress(done, total)`` after each view of each pass (for progress bars).

    Returns
    -------
    Lumitexels
        Sorted by texel. Points are made per triangle in the view where it covers the most
        pixels (the paper's I_best, measured on the visible, ray-cast area so occluded triangles
        are assigned where they are seen); ``footprint_spread_deg`` from all the samples (a
        caller that holds some out recomputes it: :func:`footprint_normal_spread`).

    Notes
    -----
    Composed of the per-view steps :func:`view_hits`, :func:`view_texels` and
    :func:`view_samples`, which an out-of-core run (``capture.pipeline.lumitexel_arrays``)
    calls one view and one texel block at a time.
    """
    _check_views(views)
    geom = assembly_geometry(mesh, occluders=occluders, reject_filter_px=reject_filter_px,
                             reject_jump_mm=reject_jump_mm, min_cos=min_cos)
    total = 2 * len(views)
    step = 0

    def tick():
        nonlocal step
        step += 1
        if progress is not None:
            progress(step, total)

    cams = [object_frame_camera(v.camera, v.object_to_world) for v in views]
    lights = [object_frame_point(v.object_to_world, v.light_position) for v in views]
    per_view = []
    for cam, light in zip(cams, lights):
        per_view.append(view_hits(geom, cam, light))
        tick()
    best = best_views(np.stack([h.face_areas(geom.n_faces) for h in per_view], axis=1))
    tex = join_texels([view_texels(h, best, k, cam.width) for k, (h, cam) in enumerate(zip(per_view, cams))])

    # pass 2: a reflectance sample per (texel, view) where the point is seen and lit
    separated = all(v.diffuse is not None and v.specular is not None for v in views)
    parts = []
    for k, (v, cam, light) in enumerate(zip(views, cams, lights)):
        s = view_samples(geom, v, cam, light, per_view[k].reject, tex.position, tex.normal, separated=separated)
        if len(s.texel):
            parts.append((k, s))
        tick()
    if not parts:
        raise LumitexelError("no reflectance samples: no surface point is both seen and lit")
    texel = np.concatenate([s.texel for _, s in parts])
    order = np.argsort(texel, kind="stable")
    cat = lambda name: np.concatenate([getattr(s, name) for _, s in parts])[order]  # noqa: E731
    lt = Lumitexels(
        position=tex.position, normal=tex.normal, best_view=tex.best_view, pixel=tex.pixel,
        texel=texel[order], view=np.concatenate([np.full(len(s.texel), k, np.int32) for k, s in parts])[order],
        wi=cat("wi"), wo=cat("wo"), reflectance=cat("reflectance"), weight=np.ones(len(texel), np.float32),
        diffuse=cat("diffuse") if separated else None, specular=cat("specular") if separated else None)
    # points never both seen and lit carry no information
    lt = lt.subset(np.flatnonzero(lt.counts > 0))
    lt.footprint_spread_deg = footprint_normal_spread(lt)
    return lt
