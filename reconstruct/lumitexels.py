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
from .frames import tangent_frames, to_local
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
        Linear HDR radiance (float32), same units as ``light_intensity`` / mm^2.
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
    point was generated from, ``pixel`` (P, 2) its pixel there.
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

    _TEXEL_FIELDS = ("position", "normal", "best_view", "pixel")

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


# ----------------------------------------------------------------------------------------------
# assembly
# ----------------------------------------------------------------------------------------------
def _object_frame_camera(view: View) -> CameraModel:
    """The view's camera with its pose expressed relative to the object (object -> camera)."""
    T = np.asarray(view.object_to_world, float)
    return view.camera.with_pose(view.camera.R @ T[:3, :3], view.camera.R @ T[:3, 3] + view.camera.t)


def _object_frame_point(view: View, p_world) -> np.ndarray:
    T = np.asarray(view.object_to_world, float)
    return np.linalg.solve(T[:3, :3], np.asarray(p_world, float) - T[:3, 3])


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
        are assigned where they are seen).
    """
    _check_views(views)
    surface = mesh if isinstance(mesh, Surface) else Mesh(mesh)
    blockers = [surface, *occluders]
    extent = float(np.ptp(surface.mesh.bounds, axis=0).max()) if isinstance(surface, Mesh) else \
        2 * surface.bounding_radius
    jump = 0.02 * extent if reject_jump_mm is None else reject_jump_mm
    total = 2 * len(views)
    step = 0

    def tick():
        nonlocal step
        step += 1
        if progress is not None:
            progress(step, total)

    cams = [_object_frame_camera(v) for v in views]
    lights = [_object_frame_point(v, v.light_position) for v in views]

    # pass 1: per view, the pixels seeing the object, their faces, and the rejection maps
    corners = _bounds_corners(blockers)
    per_view = []
    for v, cam, light in zip(views, cams, lights):
        pix = _pixels_covering(cam, corners)
        o, d = cam.pixel_rays(np.stack([pix % cam.width, pix // cam.width], axis=1))
        hits = first_hits(blockers, o, d)
        on_obj = hits.surface_index == 0
        if reject_filter_px > 1:
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
            reject = _reject_map(depth.reshape(cam.height, cam.width),
                                 shadow.reshape(cam.height, cam.width),
                                 filter_px=reject_filter_px, jump_mm=jump).ravel()
        else:
            reject = np.zeros(cam.width * cam.height, bool)
        per_view.append((pix[on_obj], hits.face_index[on_obj], hits.position[on_obj],
                         hits.normal[on_obj], reject))
        tick()

    # I_best per face: the view in which its visible area (in pixels) is largest
    F = len(surface.mesh.faces) if isinstance(surface, Mesh) else 1
    area = np.zeros((F, len(views)), np.int64)
    for k, (_, faces, *_rest) in enumerate(per_view):
        area[:, k] = np.bincount(np.maximum(faces, 0), minlength=F)
    best = np.argmax(area, axis=1)

    # texels: the pixels of each face in its best view (their ray hits are the surface points)
    pos, nrm, bview, bpix = [], [], [], []
    for k, (pix, faces, hit_pos, hit_nrm, _) in enumerate(per_view):
        sel = best[np.maximum(faces, 0)] == k
        if not sel.any():
            continue
        width = cams[k].width
        pos.append(hit_pos[sel])
        nrm.append(hit_nrm[sel])
        bview.append(np.full(sel.sum(), k, np.int32))
        bpix.append(np.stack([pix[sel] % width, pix[sel] // width], axis=1).astype(np.float32))
    if not pos:
        raise LumitexelError("the object is not visible in any view (check poses and the mesh frame)")
    position = np.concatenate(pos)
    normal = np.concatenate(nrm)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    frames = tangent_frames(normal)

    # pass 2: a reflectance sample per (texel, view) where the point is seen and lit
    s_texel, s_view, s_wi, s_wo, s_r, s_dif, s_spec = [], [], [], [], [], [], []
    separated = all(v.diffuse is not None and v.specular is not None for v in views)
    for k, (v, cam, light) in enumerate(zip(views, cams, lights)):
        to_c = cam.center - position
        dc = np.linalg.norm(to_c, axis=1)
        to_c /= dc[:, None]
        to_l = light - position
        dl = np.linalg.norm(to_l, axis=1)
        to_l /= dl[:, None]
        cos_o = np.einsum("ij,ij->i", normal, to_c)
        cos_i = np.einsum("ij,ij->i", normal, to_l)
        cand = np.flatnonzero((cos_o > min_cos) & (cos_i > min_cos))
        px = cam.project(position[cand])
        inside = (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] <= cam.width - 1) & \
                 (px[:, 1] <= cam.height - 1)
        cand, px = cand[inside], px[inside]
        seen = ~occluded(blockers, position[cand], to_c[cand], dc[cand], normals=normal[cand])
        cand, px = cand[seen], px[seen]
        lit = ~occluded(blockers, position[cand], to_l[cand], dl[cand], normals=normal[cand])
        cand, px = cand[lit], px[lit]
        # rejection and validity at the four pixels the bilinear sample touches
        reject = per_view[k][-1]
        bad = reject.reshape(cam.height, cam.width)
        if v.valid is not None:
            bad = bad | ~np.asarray(v.valid, bool)
        x0 = np.clip(np.floor(px[:, 0]).astype(int), 0, cam.width - 2)
        y0 = np.clip(np.floor(px[:, 1]).astype(int), 0, cam.height - 2)
        drop = bad[y0, x0] | bad[y0, x0 + 1] | bad[y0 + 1, x0] | bad[y0 + 1, x0 + 1]
        cand, px = cand[~drop], px[~drop]
        if len(cand) == 0:
            tick()
            continue
        scale = dl[cand, None] ** 2 / np.broadcast_to(np.asarray(v.light_intensity, float), (3,))
        s_r.append((_sample(v.radiance, px) * scale).astype(np.float32))
        if separated:
            s_dif.append((_sample(v.diffuse, px) * scale).astype(np.float32))
            s_spec.append((_sample(v.specular, px) * scale).astype(np.float32))
        s_texel.append(cand)
        s_view.append(np.full(len(cand), k, np.int32))
        s_wi.append(to_local(to_l[cand], frames[cand]).astype(np.float32))
        s_wo.append(to_local(to_c[cand], frames[cand]).astype(np.float32))
        tick()
    if not s_texel:
        raise LumitexelError("no reflectance samples: no surface point is both seen and lit")
    texel = np.concatenate(s_texel)
    order = np.argsort(texel, kind="stable")
    cat = lambda parts: np.concatenate(parts)[order]  # noqa: E731
    lt = Lumitexels(
        position=position, normal=normal, best_view=np.concatenate(bview),
        pixel=np.concatenate(bpix), texel=texel[order], view=cat(s_view), wi=cat(s_wi),
        wo=cat(s_wo), reflectance=cat(s_r), weight=np.ones(len(texel), np.float32),
        diffuse=cat(s_dif) if separated else None, specular=cat(s_spec) if separated else None)
    # points never both seen and lit carry no information
    return lt.subset(np.flatnonzero(lt.counts > 0))
