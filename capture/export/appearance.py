"""What a reconstruction leaves for export: per texel, where it is, its normal, its confidence and
the exported BRDF fitted to the recovered one; plus the held-out samples that check the export.

``gonio process`` stores it beside each method's model as ``appearance.npz``
(:func:`appearance_npz`, called from :func:`capture.pipeline.run._run_method`), because the
recovered models (Lensch's clustered lobes, sharing's RBFs) live only in memory while the method
runs; ``gonio export`` reads it back with :meth:`Appearance.from_npz`.

Frames and units: object frame (the lab frame at turntable reading 0), mm; normals unit vectors
in the object frame; reflectance ``f_r cos theta_i`` in the calibration's units (1/sr when it
is absolute, :mod:`reconstruct.lumitexels`).
"""
from __future__ import annotations

import io
from dataclasses import dataclass, fields
from typing import Sequence

import numpy as np

from reconstruct.frames import tangent_frames, to_local
from reconstruct.lumitexels import Lumitexels, View

from .ggx import GgxMaps, fit_ggx, ggx_reflectance

__all__ = ["Appearance", "appearance_npz", "HIGHLIGHT_DEG", "EXPORTED_METHODS", "HOMOGENEOUS_METHODS"]

#: the methods ``gonio export`` writes (the Lambertian reference stays inside gonio)
EXPORTED_METHODS = ("lensch", "sharing", "passive")
#: methods that recover one BRDF for the whole object: one fit serves every texel
HOMOGENEOUS_METHODS = ("passive",)

#: a texel counts as having seen its highlight when a training sample's halfway vector came
#: within this angle of its normal
HIGHLIGHT_DEG = 10.0


@dataclass(frozen=True)
class Appearance:
    """One method's recovered appearance, ready to export.

    Attributes
    ----------
    method : str
    position : (T, 3) float   texel positions, object frame, mm
    mesh_normal : (T, 3)      the mesh's interpolated normal at the texel
    normal : (T, 3)           the normal the model uses (fitted where the method fits normals)
    label : (T,) int          material of the texel, 0 .. M - 1 (Lensch: clusters that no held-out
                              test tells apart are one material; 0 for a method without materials)
    cluster : (T,) int        the method's cluster of the texel (Lensch's Eq. 10 labels: a
                              material's variant clusters, with their broader lobes, apart; the
                              GGX roughness is fitted per cluster); ``label`` where it has none
    samples : (T,) int        training samples of the texel
    no_highlight : (T,) bool  no training sample's halfway vector within :data:`HIGHLIGHT_DEG`
    rho_d, ks : (T, 3); alpha : (T,)   the exported BRDF (:mod:`capture.export.ggx`)
    fit_rel_rms : (M,)        per material (``label``), the exported BRDF against the method's predictions
                              at the training samples (relative RMS of f_r cos)
    held_texel, held_view : (H,) int; held_wi, held_wo : (H, 3) local (mesh-normal) frame;
    held_captured, held_predicted : (H, 3)   held-out samples: captured ``f_r cos`` and the
                              method's own prediction
    K : (3, 3); image_size : (2,) width, height; light_intensity : (3,)   the calibrated camera's
                              intrinsics and the lamp's intensity (the calibration's units)
    view_camera_to_object : (V, 4, 4)   per captured pose (training views, then held-out ones:
                              ``held_view`` indexes these), OpenCV camera -> object frame, mm
    view_light_mm : (V, 3)    its light, object frame, mm
    view_held_out : (V,) bool
    """

    method: str
    position: np.ndarray
    mesh_normal: np.ndarray
    normal: np.ndarray
    label: np.ndarray
    cluster: np.ndarray
    samples: np.ndarray
    no_highlight: np.ndarray
    rho_d: np.ndarray
    ks: np.ndarray
    alpha: np.ndarray
    fit_rel_rms: np.ndarray
    held_texel: np.ndarray
    held_view: np.ndarray
    held_wi: np.ndarray
    held_wo: np.ndarray
    held_captured: np.ndarray
    held_predicted: np.ndarray
    K: np.ndarray
    image_size: np.ndarray
    light_intensity: np.ndarray
    view_camera_to_object: np.ndarray
    view_light_mm: np.ndarray
    view_held_out: np.ndarray

    @property
    def n_texels(self) -> int:
        return len(self.position)

    @property
    def n_materials(self) -> int:
        return int(self.label.max()) + 1 if len(self.label) else 0

    @property
    def maps(self) -> GgxMaps:
        return GgxMaps(self.rho_d, self.ks, self.alpha)

    def to_npz(self) -> bytes:
        buf = io.BytesIO()
        np.savez_compressed(buf, **{f.name: np.asarray(getattr(self, f.name)) for f in fields(self)})
        return buf.getvalue()

    @classmethod
    def from_npz(cls, data: bytes) -> "Appearance":
        with np.load(io.BytesIO(data)) as z:
            values = {f.name: z[f.name] for f in fields(cls) if f.name in z}
        if "cluster" not in values and "label" in values:   # stored before materials: labels were clusters
            values["cluster"] = values["label"]
        missing = [f.name for f in fields(cls) if f.name not in values]
        if missing:
            raise ValueError(f"appearance.npz lacks {', '.join(missing)}")
        values["method"] = str(values["method"])
        return cls(**values)


def appearance_npz(method: str, fit, train: Lumitexels, held: Lumitexels, views: Sequence[View],
                   held_views: Sequence[View], predicted_train: np.ndarray, predicted_held: np.ndarray) -> bytes:
    """:class:`Appearance` of a fitted method (``capture.pipeline.methods.Fitted``) as npz bytes.

    ``predicted_train`` / ``predicted_held`` are ``fit.predict`` of ``train`` / ``held`` (the
    pipeline computes them for its figures). The exported BRDF is fitted to the method's
    predictions at the training samples: roughness
    per cluster, albedo and lobe scale per texel (:func:`capture.export.ggx.fit_ggx`); one fit
    for a method of one BRDF (:data:`HOMOGENEOUS_METHODS`).
    """
    T = train.n_texels
    normal = train.normal if fit.normals is None else np.asarray(fit.normals, float)
    frames = tangent_frames(train.normal)
    n_local = to_local(normal, frames)
    cluster = np.asarray(fit.arrays.get("labels", np.zeros(T)), np.int64)
    label = np.asarray(fit.arrays.get("materials", cluster), np.int64)

    # fitted where the data is: at the training samples, to the method's own predictions there
    # (away from them a recovered lobe may extrapolate to anything: Lafortune lobes reached
    # f_r = 65 / sr at normal incidence on the quick demo, where no sample was)
    homogeneous = method in HOMOGENEOUS_METHODS
    texel = np.zeros(train.n_samples, np.int64) if homogeneous else train.texel
    n, wi, wo, y = n_local[train.texel], train.wi, train.wo, np.asarray(predicted_train, float)
    maps = fit_ggx(texel, n, wi, wo, y, 1 if homogeneous else T, group=None if homogeneous else cluster)
    if homogeneous:
        maps, texel = maps.take(np.zeros(T, np.int64)), train.texel

    err = ggx_reflectance(maps.take(texel), n, wi, wo) - y
    M = int(label.max()) + 1 if T else 1
    num = np.bincount(label[texel], np.sum(err ** 2, axis=1), M)
    den = np.bincount(label[texel], np.sum(y ** 2, axis=1), M)
    fit_rel = np.sqrt(num / np.maximum(den, 1e-300))

    h = train.wi + train.wo
    cos_h = np.einsum("ij,ij->i", h / np.linalg.norm(h, axis=1, keepdims=True), n_local[train.texel])
    seen = np.bincount(train.texel, cos_h > np.cos(np.radians(HIGHLIGHT_DEG)), T) > 0
    return Appearance(
        method=method, position=train.position.astype(np.float64), mesh_normal=train.normal.astype(np.float64),
        normal=normal.astype(np.float64), label=label, cluster=cluster, samples=np.bincount(train.texel, minlength=T),
        no_highlight=~seen, rho_d=maps.rho_d, ks=maps.ks, alpha=maps.alpha, fit_rel_rms=fit_rel,
        held_texel=held.texel.astype(np.int64), held_view=held.view.astype(np.int64),
        held_wi=held.wi.astype(np.float64), held_wo=held.wo.astype(np.float64),
        held_captured=held.reflectance.astype(np.float64),
        held_predicted=np.asarray(predicted_held, np.float64).reshape(-1, 3),
        **_view_geometry([*views, *held_views], len(views)),
    ).to_npz()


def _view_geometry(views: Sequence[View], n_training: int) -> dict[str, np.ndarray]:
    """The cameras and lights of the captures, in the object frame (one camera model: the session's)."""
    cam = views[0].camera
    cam_to_world = np.eye(4)
    cam_to_world[:3, :3], cam_to_world[:3, 3] = cam.R.T, -cam.R.T @ cam.t
    to_obj = [np.linalg.inv(v.object_to_world) for v in views]
    return {"K": np.asarray(cam.K, float), "image_size": np.array([cam.width, cam.height]),
            "light_intensity": np.broadcast_to(np.asarray(views[0].light_intensity, float), (3,)).copy(),
            "view_camera_to_object": np.stack([m @ cam_to_world for m in to_obj]),
            "view_light_mm": np.stack([m[:3, :3] @ np.asarray(v.light_position, float) + m[:3, 3]
                                       for m, v in zip(to_obj, views)]),
            "view_held_out": np.arange(len(views)) >= n_training}
