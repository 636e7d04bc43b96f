"""Lambertian photometric stereo with known distant lights.

Frame: the camera frame of OpenCV (x right along image columns, y down along rows, z forward into
the scene). Light directions point from the surface towards the light, normals point out of the
surface, so surfaces facing the camera have ``n_z < 0`` and lights in front of the object have
``l_z < 0``. Images are linear (radiance or raw values, not gamma-encoded).

Model per pixel: ``I_k = e_k * rho * max(0, n . l_k)`` with light intensity ``e_k`` (given, or
equal), solved for ``g = rho * n`` by least squares over all pixels at once.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class PhotometricStereoError(ValueError):
    """Inputs that cannot give normals (too few lights, degenerate light directions, bad shapes)."""


@dataclass(frozen=True)
class PhotometricStereoResult:
    """Normals and albedo recovered per pixel.

    Attributes
    ----------
    normals : ndarray of shape (H, W, 3), float32
        Unit normals in the camera frame; zero where ``mask`` is False.
    albedo : ndarray of shape (H, W) or (H, W, C), float32
        ``rho`` in the images' units (per channel for colour stacks).
    mask : ndarray of shape (H, W), bool
        Pixels with a valid solution (inside the input mask, enough usable lights).
    residual : ndarray of shape (H, W), float32
        RMS of the fit over the lights used, in image units.
    lights_used : ndarray of shape (H, W), int16
        Number of lights each pixel's solution used (robust mode drops shadows and highlights).
    """

    normals: np.ndarray
    albedo: np.ndarray
    mask: np.ndarray
    residual: np.ndarray
    lights_used: np.ndarray


def _check_inputs(images, light_dirs, mask, light_intensities):
    images = np.asarray(images)
    if images.ndim not in (3, 4):
        raise PhotometricStereoError(
            f"images must have shape (K, H, W) or (K, H, W, C), got {images.shape}")
    if light_intensities is not None:
        e = np.asarray(light_intensities, dtype=np.float64)
        C = images.shape[3] if images.ndim == 4 else None
        if e.shape not in ((images.shape[0],),) + (((images.shape[0], C),) if C else ()):
            raise PhotometricStereoError(
                f"light_intensities must have shape ({images.shape[0]},)"
                + (f" or ({images.shape[0]}, {C})" if C else "") + f", got {e.shape}")
        if not np.all(np.isfinite(e)) or np.any(e <= 0):
            raise PhotometricStereoError("light_intensities must be finite and > 0")
        # I_k / e_k: every image as if lit with unit intensity (per channel for (K, C))
        images = images / (e[:, None, None, :] if e.ndim == 2 else e.reshape((-1,) + (1,) * (images.ndim - 1)))
    L = np.asarray(light_dirs, dtype=np.float64)
    if L.ndim != 2 or L.shape[1] != 3 or L.shape[0] != images.shape[0]:
        raise PhotometricStereoError(
            f"light_dirs must have shape (K, 3) with K = {images.shape[0]} images, got {L.shape}")
    if L.shape[0] < 3:
        raise PhotometricStereoError(f"need at least 3 lights, got {L.shape[0]}")
    norms = np.linalg.norm(L, axis=1)
    if np.any(norms < 1e-9):
        raise PhotometricStereoError("light_dirs contains a zero vector")
    L = L / norms[:, None]
    if np.linalg.matrix_rank(L, tol=1e-3) < 3:
        raise PhotometricStereoError("light directions are (nearly) coplanar: normals are not "
                                     "determined; spread the lights out of one plane")
    H, W = images.shape[1:3]
    if mask is None:
        mask = np.ones((H, W), bool)
    else:
        mask = np.asarray(mask, bool)
        if mask.shape != (H, W):
            raise PhotometricStereoError(f"mask must have shape {(H, W)}, got {mask.shape}")
    return images, L, mask


def photometric_stereo(images: np.ndarray, light_dirs: np.ndarray, mask: np.ndarray | None = None,
                       *, light_intensities: np.ndarray | None = None, robust: bool = False,
                       shadow_threshold: float = 0.0,
                       drop_darkest: int = 2, drop_brightest: int = 1,
                       refine_iterations: int = 3) -> PhotometricStereoResult:
    """Recover normals and albedo from K images under K known distant lights.

    Frame: the OpenCV camera frame (x right along image columns, y down along rows, z forward
    into the scene). ``light_dirs`` point from the surface towards the lights and the normals
    out of the surface, so a surface facing the camera has ``n_z < 0`` and a light on the
    camera's side ``l_z < 0``. Data in another convention (e.g. DiLiGenT and many course sets:
    x right, y up, z towards the viewer) converts by negating y and z of the directions (and
    of the normals it returns).

    Parameters
    ----------
    images : ndarray of shape (K, H, W) or (K, H, W, C)
        Linear images, one per light. Colour stacks share one normal; the normal is solved on
        the channel sum and the albedo per channel.
    light_dirs : ndarray of shape (K, 3)
        Directions towards each light in the camera frame (normalised here).
    mask : ndarray of shape (H, W), bool, optional
        Pixels to solve; default all.
    light_intensities : ndarray of shape (K,) or (K, C), optional
        Each light's intensity (per channel for (K, C), as DiLiGenT's ``light_intensities.txt``):
        each image is divided by it before solving, so the albedo is per unit intensity.
        Default: equal intensities (albedo in image units).
    robust : bool
        Reject per pixel the ``drop_darkest`` darkest observations (attached/cast shadows) and the
        ``drop_brightest`` brightest (specular highlights), plus any at or below
        ``shadow_threshold``; then solve the remaining (at least 3) by least squares.
        Then ``refine_iterations`` re-weighting passes drop, per pixel, the lights the current
        fit puts in shadow and those far above it (3 sigma of the global residual spread plus 5%:
        highlights), and solve again.
    shadow_threshold : float
        Intensities at or below this are treated as shadowed (robust mode), image units (after
        the division by ``light_intensities``).

    Returns
    -------
    PhotometricStereoResult
    """
    images, L, mask = _check_inputs(images, light_dirs, mask, light_intensities)
    K = L.shape[0]
    color = images.ndim == 4
    gray = images.sum(axis=3) if color else images
    I = gray[:, mask].astype(np.float64).T                      # (P, K)
    P = I.shape[0]

    if not robust:
        G = I @ np.linalg.pinv(L).T                               # (P, 3) = rho * n
        weights = np.ones_like(I)
    else:
        if K - drop_darkest - drop_brightest < 3:
            raise PhotometricStereoError(
                f"robust mode drops {drop_darkest}+{drop_brightest} of {K} lights per pixel; "
                "at least 3 must remain")
        srt = np.sort(I, axis=1)
        lo = srt[:, drop_darkest - 1:drop_darkest] if drop_darkest else np.full((P, 1), -np.inf)
        hi = srt[:, K - drop_brightest:K - drop_brightest + 1] if drop_brightest else \
            np.full((P, 1), np.inf)
        weights = ((I > lo) & (I < hi) & (I > shadow_threshold)).astype(np.float64)
        G = _weighted_solve(I, L, weights)
        # re-weighting: a Lambertian pixel is explained to within noise by its lit lights; lights
        # whose value sits far above the fit (highlights) or that the fit puts in shadow are dropped
        for _ in range(refine_iterations):
            pred = G @ L.T
            resid = I - pred
            sigma = 1.4826 * np.median(np.abs(resid[weights > 0])) + 1e-12
            keep = (I > shadow_threshold) & (pred > 0) & (resid < 3 * sigma + 0.05 * pred)
            new_w = keep.astype(np.float64)
            enough = new_w.sum(axis=1) >= 3
            weights = np.where(enough[:, None], new_w, weights)
            G = _weighted_solve(I, L, weights)

    rho = np.linalg.norm(G, axis=1)
    n = np.divide(G, rho[:, None], out=np.zeros_like(G), where=rho[:, None] > 0)
    pred = np.clip(n @ L.T, 0, None) * rho[:, None]
    used = weights.sum(axis=1)
    resid = np.sqrt(np.sum(weights * (I - pred) ** 2, axis=1) / np.maximum(used, 1))
    valid = (rho > 0) & (used >= 3)

    H, W = mask.shape
    normals = np.zeros((H, W, 3), np.float32)
    normals[mask] = np.where(valid[:, None], n, 0)
    out_mask = np.zeros((H, W), bool)
    out_mask[mask] = valid
    residual = np.zeros((H, W), np.float32)
    residual[mask] = resid
    lights_used = np.zeros((H, W), np.int16)
    lights_used[mask] = used
    if color:
        # per-channel albedo: least squares of I_c = rho_c * shading over the lights used
        shading = np.clip(n @ L.T, 0, None) * weights                # (P, K)
        Ic = images[:, mask, :].astype(np.float64).transpose(1, 0, 2)  # (P, K, C)
        denom = np.sum(shading ** 2, axis=1)
        rho_c = np.einsum("pk,pkc->pc", shading, Ic) / np.maximum(denom, 1e-12)[:, None]
        albedo = np.zeros((H, W, images.shape[3]), np.float32)
        albedo[mask] = np.where(valid[:, None], rho_c, 0)
    else:
        albedo = np.zeros((H, W), np.float32)
        albedo[mask] = np.where(valid, rho, 0)
    return PhotometricStereoResult(normals=normals, albedo=albedo, mask=out_mask,
                                   residual=residual, lights_used=lights_used)


def _weighted_solve(I: np.ndarray, L: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per-pixel weighted least squares for g = rho n: a batch of 3x3 normal equations."""
    outer = (L[:, :, None] * L[:, None, :]).reshape(len(L), 9)
    A = (weights @ outer).reshape(-1, 3, 3)          # sum_k w_k l_k l_k^T, as one GEMM
    b = (weights * I) @ L
    # Cramer's rule on the whole batch: ~10x faster than np.linalg.solve on (P, 3, 3)
    r0, r1, r2 = A[:, 0], A[:, 1], A[:, 2]
    c0, c1, c2 = np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)
    det = np.sum(r0 * c0, axis=1)
    ok = (weights.sum(axis=1) >= 3) & (det > 1e-9)
    G = (c0 * b[:, :1] + c1 * b[:, 1:2] + c2 * b[:, 2:3]) / np.where(ok, det, 1.0)[:, None]
    G[~ok] = 0.0
    return G


def angular_error_deg(n_est: np.ndarray, n_true: np.ndarray) -> np.ndarray:
    """Angle between unit normals (..., 3) in degrees."""
    dot = np.sum(np.asarray(n_est, float) * np.asarray(n_true, float), axis=-1)
    return np.degrees(np.arccos(np.clip(dot, -1.0, 1.0)))


def texel_normal_equations(texel: np.ndarray, wi: np.ndarray, value: np.ndarray, weight: np.ndarray,
                           n_texels: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-texel normal equations of the Lambertian least squares ``value = g . wi`` over samples
    scattered across texels: ``A = sum w wi wi^T`` (T, 3, 3) and ``b = sum w value wi`` (T, 3).

    ``texel`` (S,) int in [0, ``n_texels``); ``wi`` (S, 3) unit directions to the light in the
    frame ``g`` is wanted in; ``value`` (S,) the channel-summed reflectance; ``weight`` (S,).
    Solving ``A g = b`` gives ``g = rho n / pi`` in ``wi``'s frame (lumitexels' photometric
    normals, reflectance sharing's diffuse normals).
    """
    A = np.empty((n_texels, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            A[:, i, j] = A[:, j, i] = np.bincount(texel, weight * (wi[:, i] * wi[:, j]), minlength=n_texels)
    b = np.stack([np.bincount(texel, weight * value * wi[:, i], minlength=n_texels) for i in range(3)], axis=1)
    return A, b
