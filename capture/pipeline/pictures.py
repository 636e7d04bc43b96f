"""The pictures a method's report section draws, computed when the method runs (stored with
its result as ``report.npz``): a held-out view captured and predicted, BRDF slices, normal maps.

Frames: views' pixels x right, y down; BRDF slices in the plane of incidence of the texel's local
frame (normal +z), ``theta_o`` positive on the mirror side; radiance DN/s.
"""
from __future__ import annotations

import cv2
import numpy as np

from reconstruct.lumitexels import Lumitexels, View

from .methods import Fitted
from .process import ProcessInputs, select_samples

__all__ = ["PICTURE_MAX_PX", "SLICE_THETA_I_DEG", "SLICE_TEXELS", "method_pictures", "picture_scale", "splat"]

#: longest side of the report's view pictures, pixels: a camera's larger frames are drawn scaled
#: down (a 45 MP frame splatted at full size would hold ~1.5 GB of float64 accumulators, more than
#: any --memory-limit, for a picture a browser shows at a few hundred pixels)
PICTURE_MAX_PX = 1024

#: incidence angle of the BRDF slices the report draws (in the plane of incidence), degrees
SLICE_THETA_I_DEG = 30.0
#: texels per material whose recovered BRDFs are averaged into a slice
SLICE_TEXELS = 200


def splat(px: np.ndarray, values: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Values (N, C) drawn at pixels ``px`` (N, 2; x right, y down, rounded) of a (height, width)
    image (H, W, C), averaged where several fall on one pixel, NaN elsewhere; one-pixel holes
    between them filled from their neighbours (normalised 3 x 3 box)."""
    H, W = size
    px = np.rint(np.asarray(px, float)).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] < W) & (px[:, 1] < H)
    px, values = px[inside], np.asarray(values, np.float64)[inside]
    C = values.shape[1]
    acc = np.zeros((H, W, C))
    cnt = np.zeros((H, W))
    np.add.at(acc, (px[:, 1], px[:, 0]), values)
    np.add.at(cnt, (px[:, 1], px[:, 0]), 1.0)
    hit = cnt > 0
    acc_b = cv2.blur(acc.astype(np.float32), (3, 3)).reshape(H, W, C)
    cnt_b = cv2.blur(cnt.astype(np.float32), (3, 3))
    fill = (~hit) & (cnt_b > 0.3)
    out = np.full((H, W, C), np.nan)
    out[hit] = acc[hit] / cnt[hit, None]
    out[fill] = acc_b[fill] / cnt_b[fill, None]
    return out.astype(np.float32)


def picture_scale(height: int, width: int) -> tuple[float, tuple[int, int]]:
    """The factor a (height, width) view is drawn at in the report (1, or less so that its
    longest side is :data:`PICTURE_MAX_PX`) and the picture's (height, width)."""
    s = min(1.0, PICTURE_MAX_PX / max(height, width))
    return s, (max(1, round(height * s)), max(1, round(width * s)))


def _splat(lt: Lumitexels, values: np.ndarray, view: View) -> np.ndarray:
    """Per-sample values drawn at their texels' pixels in ``view`` (:func:`splat`), at the
    picture's scale (:func:`picture_scale`: texels sharing a scaled pixel are averaged)."""
    cam = view.camera
    pw = lt.position[lt.texel] @ view.object_to_world[:3, :3].T + view.object_to_world[:3, 3]
    s, size = picture_scale(cam.height, cam.width)
    px = cam.project(pw)
    return splat(px if s == 1 else (px + 0.5) * s - 0.5, values, size)   # pixel centres kept


def _picture(image: np.ndarray) -> np.ndarray:
    """A captured view (H, W, 3) at the picture's scale, float32 (area-averaged when smaller)."""
    image = np.asarray(image, np.float32)
    s, (h, w) = picture_scale(*image.shape[:2])
    return image if s == 1 else cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)


def _radiance(lt: Lumitexels, r: np.ndarray, view: View) -> np.ndarray:
    """Reflectance ``f_r cos`` of samples -> radiance in ``view`` (``r I / d^2``)."""
    T = view.object_to_world
    pw = lt.position[lt.texel] @ T[:3, :3].T + T[:3, 3]
    d2 = np.sum((np.asarray(view.light_position, float) - pw) ** 2, axis=1)
    return r * np.broadcast_to(np.asarray(view.light_intensity, float), (3,)) / d2[:, None]


def method_pictures(fit: Fitted, train: Lumitexels, held: Lumitexels, inputs: ProcessInputs,
                    truth) -> dict[str, np.ndarray]:
    """Arrays the report draws: the first held-out view captured / predicted (radiance), BRDF
    slices (recovered, and true per material with truth) and the normal map; the view pictures
    at most :data:`PICTURE_MAX_PX` on their longest side."""
    out: dict[str, np.ndarray] = {}
    if held.n_samples:
        k0 = int(held.view.min())
        view = inputs.held_out[k0 - len(inputs.views)]
        sub = select_samples(held, held.view == k0)
        out["heldout_captured"] = _picture(view.radiance)   # the capture itself
        out["heldout_predicted"] = _splat(sub, _radiance(sub, fit.predict(sub), view), view)
    theta = np.radians(np.linspace(-85, 85, 69))
    ti = np.radians(SLICE_THETA_I_DEG)
    wi = np.tile([-np.sin(ti), 0.0, np.cos(ti)], (len(theta), 1))
    wo = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=1)  # +theta: the mirror side
    out["slice_theta_o_deg"] = np.degrees(theta)
    rng = np.random.default_rng(0)
    groups = {"all": np.arange(train.n_texels)}
    if truth is not None:
        try:
            ids, materials = truth.materials(train.position)
            groups = {f"m{k}": np.flatnonzero(ids == k) for k in range(len(materials))}
            for k, m in enumerate(materials):
                out[f"slice_true_m{k}"] = m.evaluate(wi, wo)
        except ValueError:
            pass
    for g, texels in groups.items():
        if len(texels) == 0:
            continue
        pick = rng.choice(texels, min(SLICE_TEXELS, len(texels)), replace=False)
        model = fit.brdf(np.repeat(pick, len(theta)))
        f = model.evaluate(np.tile(wi, (len(pick), 1)), np.tile(wo, (len(pick), 1)))
        out[f"slice_fit_{g}"] = np.median(f.reshape(len(pick), len(theta), 3), axis=0)
    if fit.normals is not None and inputs.views:
        view = inputs.views[0]
        first = select_samples(train, train.view == 0)
        R = view.object_to_world[:3, :3]
        out["normals_mesh"] = _splat(first, train.normal[first.texel] @ R.T, view)
        out["normals_fitted"] = _splat(first, fit.normals[first.texel] @ R.T, view)
        true_n = truth.normals(train.position) if truth is not None else None
        if true_n is not None:
            out["normals_true"] = _splat(first, true_n[first.texel] @ R.T, view)
    return out
