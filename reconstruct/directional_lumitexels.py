"""Lumitexels of an image set under distant lights seen by an orthographic camera.

Photometric-stereo data (DiLiGenT and the like) has no mesh and no camera pose: each pixel of the
mask is a texel, its normal an estimate (e.g. least-squares photometric stereo), every light a
direction and the view one direction for all pixels. :func:`directional_lumitexels` turns such a
stack into :class:`~reconstruct.lumitexels.Lumitexels` so the reconstruction methods run on it
unchanged. Frame: any one frame shared by the lights, the view and the normals (gonio's data in
the OpenCV camera frame); ``position`` holds the pixel (column, row, 0), as there is no depth.
"""
from __future__ import annotations

import numpy as np

from .frames import tangent_frames, to_local
from .lumitexels import LumitexelError, Lumitexels


def directional_lumitexels(radiance, light_dirs, view_dir, normals, mask, *, valid=None,
                           min_cos: float = 0.0) -> Lumitexels:
    """One texel per mask pixel, one sample per light that lies above its horizon.

    Parameters
    ----------
    radiance : ndarray (K, H, W, 3)
        Images per unit light intensity: f_r cos(theta_i) up to one common factor.
    light_dirs : ndarray (K, 3)
        Unit directions from the surface towards each light.
    view_dir : ndarray (3,)
        Unit direction from the surface towards the (orthographic) camera.
    normals : ndarray (H, W, 3)
        Unit normals of the texels (the local frames' z).
    mask : ndarray (H, W) bool
        The texels.
    valid : ndarray (K, H, W) bool, optional
        Usable observations (e.g. not clipped); the others get weight 0.
    min_cos : float
        Samples with cos(theta_i) or cos(theta_o) at or below this are left out (the light or
        the camera is below the texel's horizon).

    Returns
    -------
    Lumitexels
        ``texel`` in row-major mask order, ``view`` the light index, ``pixel`` (column, row).
    """
    R = np.asarray(radiance)
    K, H, W = R.shape[:3]
    L = np.asarray(light_dirs, np.float64)
    m = np.asarray(mask, bool)
    if R.ndim != 4 or R.shape[3] != 3 or L.shape != (K, 3) or m.shape != (H, W):
        raise LumitexelError(f"radiance (K, H, W, 3), light_dirs (K, 3) and mask (H, W) must agree, "
                             f"got {R.shape}, {L.shape}, {m.shape}")
    rows, cols = np.nonzero(m)
    n = np.asarray(normals, np.float64)[rows, cols]
    T = len(rows)
    frames = tangent_frames(n)
    wi_all = np.einsum("tij,kj->tki", frames, L)                     # (T, K, 3) local
    wo = frames @ np.asarray(view_dir, np.float64)                   # (T, 3)
    keep = (wi_all[..., 2] > min_cos) & (wo[:, None, 2] > min_cos)
    tx, k = np.nonzero(keep)                                         # sorted by texel
    refl = R[:, rows, cols][k, tx].astype(np.float64)
    weight = np.ones(len(tx)) if valid is None else \
        np.asarray(valid)[:, rows, cols][k, tx].astype(np.float64)
    return Lumitexels(position=np.stack([cols, rows, np.zeros(T)], 1).astype(np.float64),
                      normal=n, best_view=np.zeros(T, np.int64),
                      pixel=np.stack([cols, rows], 1).astype(np.float64), texel=tx.astype(np.int64),
                      view=k.astype(np.int64), wi=wi_all[tx, k], wo=wo[tx], reflectance=refl,
                      weight=weight)
