"""Reflectance samples from images of known geometry under distant lights (the paper's input).

An image k of surface points with unit normals n_p, lit by a distant source in direction l_k of
normal irradiance E_k and seen from direction v_p, gives at each point the sample
f_r(wi, wo) = L_kp / (E_k cos theta_i) with wi, wo = l_k, v_p in the point's local frame
(``reconstruct.frames.tangent_frames``: normal = +z).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..frames import tangent_frames, to_local
from .rbf import SharingError


@dataclass(frozen=True)
class ImageSamples:
    """Samples of K images at P points, flattened image-major (row = k * P + p).

    Attributes
    ----------
    wi, wo : ndarray, (K P, 3)
        Local unit directions to the light / camera.
    brdf : ndarray, (K P, C)
        f_r, 1/sr; NaN where the point faces away from the light (cos theta_i <= 0).
    valid : ndarray of bool, (K P,)
        Lit (cos theta_i > 0), not saturated, finite.
    image, point : ndarray of int, (K P,)
        Image and point index of each row.
    """

    wi: np.ndarray
    wo: np.ndarray
    brdf: np.ndarray
    valid: np.ndarray
    image: np.ndarray
    point: np.ndarray


def samples_from_images(normals, radiance, directions, irradiance=1.0, *,
                        view_dirs=(0.0, 0.0, -1.0), saturation=None) -> ImageSamples:
    """Turn K images of P known surface points into reflectance samples.

    Parameters
    ----------
    normals : array_like, (P, 3)
        Unit normals (any frame: the frame of ``directions`` and ``view_dirs``; for
        ``reconstruct.distant`` images the OpenCV camera frame).
    radiance : array_like, (K, P) or (K, P, C)
        Observed radiance of each point in each image.
    directions : array_like, (K, 3)
        Unit direction to each image's distant source.
    irradiance : float or array_like, (K,) or (K, C)
        Each source's irradiance at normal incidence (same units as ``radiance`` x sr).
    view_dirs : array_like, (3,) or (P, 3)
        Unit direction from each point to the camera (default: orthographic along +z).
    saturation : float, optional
        Radiance at or above this is clipped: those samples are marked invalid.

    Returns
    -------
    ImageSamples
    """
    n = np.asarray(normals, dtype=np.float64)
    if n.ndim != 2 or n.shape[1] != 3 or not np.all(np.isfinite(n)):
        raise SharingError(f"normals must be finite with shape (P, 3), got {n.shape}")
    rad = np.asarray(radiance, dtype=np.float64)
    rad = rad[..., None] if rad.ndim == 2 else rad
    if rad.ndim != 3 or rad.shape[1] != len(n):
        raise SharingError(f"radiance must have shape (K, {len(n)}[, C]), got {np.shape(radiance)}")
    k, p, c = rad.shape
    d = np.asarray(directions, dtype=np.float64)
    if d.shape != (k, 3) or not np.all(np.isfinite(d)):
        raise SharingError(f"directions must be finite with shape ({k}, 3), got {d.shape}")
    e = np.broadcast_to(np.asarray(irradiance, dtype=np.float64).reshape(
        (k, -1) if np.ndim(irradiance) else (1, 1)), (k, c))
    if not np.all(e > 0):
        raise SharingError("irradiance must be > 0")
    v = np.broadcast_to(np.asarray(view_dirs, dtype=np.float64), (p, 3))
    frames = tangent_frames(n)
    wo = np.tile(to_local(v, frames), (k, 1))
    wi = to_local(np.repeat(d, p, axis=0), np.tile(frames, (k, 1, 1)))
    cos_i = wi[:, 2].reshape(k, p, 1)
    valid = (cos_i[..., 0] > 0) & np.isfinite(rad).all(axis=2)
    if saturation is not None:
        valid &= (rad < saturation).all(axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(cos_i > 0, rad / (e[:, None, :] * cos_i), np.nan)
    img, pt = np.divmod(np.arange(k * p), p)
    return ImageSamples(wi, wo, f.reshape(k * p, c), valid.reshape(-1), img, pt)
