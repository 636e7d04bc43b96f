"""Radiometric corrections: flat field / vignetting, gray-card absolute scale, and per-pixel
light intensity and inverse-square normalisation.

Frames: pixel (x right, y down); 3-D points and light positions in one common frame
(world or camera), millimetres.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import _fit, _validate
from .errors import DegenerateFit, InvalidInput, TargetNotFound

__all__ = ["VignettingModel", "GrayCard", "flat_field_gain", "fit_vignetting", "apply_flat",
           "find_gray_card", "gray_card_scale", "normalize_irradiance"]


def flat_field_gain(flats, dark=None, *, channels=None) -> np.ndarray:
    """Relative pixel gain (vignetting x pixel response) from flat-field frames.

    Parameters
    ----------
    flats : ndarray of shape (N, H, W) or (N, H, W, C)
        Frames of a uniform source, linear (N >= 1; averaged).
    dark : ndarray, optional
        Dark frame with the flats' exposure, subtracted first.
    channels : ndarray of shape (H, W), int, optional
        CFA channel index of every photosite (``rawpy``'s ``raw_colors_visible``): each channel
        is normalised separately on a mosaic.

    Returns
    -------
    ndarray, float32, shape of one frame
        Gain with mean 1 per channel; divide images by it (:func:`apply_flat`).
    """
    f = _validate.array(flats, "flats", dtype=np.float32, finite=False)
    if f.ndim not in (3, 4) or f.shape[0] < 1:
        raise InvalidInput(f"flats must be a stack (N, H, W) or (N, H, W, C), got shape {f.shape}")
    mean = f.mean(axis=0)
    if dark is not None:
        dk = _validate.array(dark, "dark", dtype=np.float32)
        if dk.shape not in ((), mean.shape):
            raise InvalidInput(f"dark must have one frame's shape {mean.shape}, got {dk.shape}", argument="dark")
        mean = mean - dk
    if not np.all(np.isfinite(mean)):
        raise InvalidInput("flats contain NaN or infinite values")
    if channels is not None:
        ch = np.asarray(channels)
        if ch.shape != mean.shape:
            raise InvalidInput(f"channels {ch.shape} must match the flat's shape {mean.shape}")
        gain = np.empty_like(mean)
        for c in np.unique(ch):  # 3-4 CFA channels
            sel = ch == c
            gain[sel] = mean[sel] / mean[sel].mean()
    elif mean.ndim == 3:
        gain = mean / mean.reshape(-1, mean.shape[2]).mean(axis=0)
    else:
        gain = mean / mean.mean()
    if np.any(gain <= 0):
        raise InvalidInput("flat field has non-positive pixels after dark subtraction (underexposed flat?)")
    return gain.astype(np.float32)


@dataclass(frozen=True)
class VignettingModel:
    """Radial falloff ``V(r) = 1 + sum_k a_k rho^(2k)`` about ``center_px`` with ``rho`` the
    distance in units of ``norm_px`` (half the image diagonal).

    Attributes
    ----------
    center_px : ndarray of shape (2,)
    coeffs : ndarray of shape (order,)
    norm_px : float
    scale : float
        Gain at the centre (the flat's level there, relative to its mean).
    rms : float
        RMS residual of the fit, relative gain units.
    """

    center_px: np.ndarray
    coeffs: np.ndarray
    norm_px: float
    scale: float
    rms: float

    def evaluate(self, shape: tuple[int, int]) -> np.ndarray:
        """Gain map (H, W), float32, for an image of ``shape = (H, W)``."""
        yy, xx = np.indices(shape, dtype=np.float64)
        rho2 = ((xx - self.center_px[0]) ** 2 + (yy - self.center_px[1]) ** 2) / self.norm_px ** 2
        return (self.scale * (1 + np.polynomial.polynomial.polyval(rho2, np.r_[0.0, self.coeffs]))).astype(np.float32)


def fit_vignetting(gain, *, order: int = 3, fit_center: bool = True, step: int = 4) -> VignettingModel:
    """Fit a radial vignetting polynomial to a flat-field gain map (smooths out pixel noise and
    dust, and extrapolates to the corners).

    Parameters
    ----------
    gain : ndarray of shape (H, W)
        Flat-field gain (e.g. :func:`flat_field_gain`, one channel).
    order : int
        Number of even-power terms (rho², rho⁴, ...).
    fit_center : bool
        Fit the optical centre too (else the image centre).
    step : int
        Subsampling of the pixels used in the fit.
    """
    g = _validate.array(gain, "gain")
    step = _validate.integer(step, "step", minimum=1)
    if g.ndim != 2:
        raise InvalidInput(f"gain must be (H, W), got shape {g.shape}")
    if not 1 <= order <= 6:
        raise InvalidInput(f"order must be in 1..6, got {order}")
    h, w = g.shape
    norm = 0.5 * np.hypot(h, w)
    yy, xx = np.mgrid[0:h:step, 0:w:step]
    gv = g[::step, ::step].ravel()
    xx, yy = xx.ravel().astype(float), yy.ravel().astype(float)

    def design(cx, cy):
        rho2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / norm ** 2
        return np.column_stack([rho2 ** (k + 1) for k in range(order)])

    def linear(cx, cy):
        A = np.column_stack([np.ones_like(gv), design(cx, cy)])
        coef = np.linalg.lstsq(A, gv, rcond=None)[0]
        return coef, gv - A @ coef

    c0 = np.array([(w - 1) / 2, (h - 1) / 2])
    if fit_center:
        c0 = _fit.solve(lambda c: linear(*c)[1], c0, what="vignetting centre fit", x_scale=norm / 10).x
    coef, res = linear(*c0)
    if not coef[0] > 0:
        raise DegenerateFit("vignetting fit gives a non-positive centre gain")
    return VignettingModel(c0, coef[1:] / coef[0], norm, float(coef[0]), float(np.sqrt(np.mean(res ** 2))))


def apply_flat(image, gain, *, min_gain: float = 0.05) -> np.ndarray:
    """``image / gain`` (float32); pixels with ``gain < min_gain`` (dead or outside the image
    circle) become 0 rather than being amplified."""
    img = _validate.array(image, "image", dtype=np.float32)
    g = _validate.array(gain, "gain", dtype=np.float32)
    if g.shape != img.shape[:g.ndim]:
        raise InvalidInput(f"gain {g.shape} does not match image {img.shape}")
    if g.ndim < img.ndim:
        g = g[..., None]
    return np.where(g >= min_gain, img / np.maximum(g, min_gain), 0.0).astype(np.float32)


def find_gray_card(image, *, min_pixels: int = 50, frame: str | None = None) -> np.ndarray:
    """The gray card's pixels in a linear image: the largest bright region (above half the 99th
    percentile), eroded by 2 px away from its edges (blur and the card's border).

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, 3)
        Linear radiance of the card under the light.
    min_pixels : int
        Fewest card pixels left after the erosion.
    frame : str, optional
        Frame name for the error messages.

    Returns
    -------
    ndarray of shape (H, W), bool

    Raises
    ------
    TargetNotFound
        No bright region, or fewer than ``min_pixels`` after the erosion.
    """
    lum = _validate.gray(image, "image", dtype=np.float32)
    min_pixels = _validate.integer(min_pixels, "min_pixels", minimum=1)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(
        (lum > 0.5 * np.percentile(lum, 99)).astype(np.uint8), connectivity=4)
    if n < 2:
        raise TargetNotFound("no gray card (bright uniform region)", frame=frame)
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    card = cv2.erode((labels == k).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    if card.sum() < min_pixels:
        raise TargetNotFound(f"gray card region has {int(card.sum())} px after erosion (need {min_pixels})",
                             frame=frame)
    return card


@dataclass(frozen=True)
class GrayCard:
    """Absolute scale from a gray card: ``f_r = value * scale * d² / cos(theta_i)`` turns a
    linear pixel value into reflectance (BRDF, 1/sr) for a light at distance ``d`` (mm)."""

    scale: float
    scale_std: float


def gray_card_scale(values, *, reflectance: float = 0.18, light_distance_mm: float,
                    cos_incidence: float = 1.0) -> GrayCard:
    """Absolute radiometric scale from a Lambertian gray card under the point light.

    A card of albedo ``rho`` has ``f_r = rho / pi``; with pixel value ``M`` observed at light
    distance ``d`` and incidence cosine ``cos_i``: ``scale = (rho / pi) cos_i / (M d²)``.

    Parameters
    ----------
    values : array_like
        Linear pixel values on the card (one channel), e.g. ``hdr[mask]``.
    reflectance : float
        The card's diffuse albedo (0.18 for a standard gray card).
    light_distance_mm : float
        Distance from the light to the card, mm.
    cos_incidence : float
        Cosine of the light's incidence angle on the card.

    Returns
    -------
    GrayCard
        With the standard error of the scale from the pixels' scatter.
    """
    v = _validate.array(values, "values", finite=False).ravel()
    if v.size == 0 or not np.all(np.isfinite(v)):
        raise InvalidInput("values must be a non-empty set of finite pixel values")
    if not 0 < reflectance <= 1:
        raise InvalidInput(f"reflectance must be in (0, 1], got {reflectance}")
    light_distance_mm = _validate.positive(light_distance_mm, "light_distance_mm")
    if not 0 < cos_incidence <= 1:
        raise InvalidInput("light_distance_mm must be > 0 and cos_incidence in (0, 1]")
    m = v.mean()
    if not m > 0:
        raise DegenerateFit("gray card values have a non-positive mean (wrong mask or black frame?)")
    scale = reflectance / np.pi * cos_incidence / (m * light_distance_mm ** 2)
    sem = v.std(ddof=1) / np.sqrt(v.size) if v.size > 1 else 0.0
    return GrayCard(float(scale), float(scale * sem / m))


def normalize_irradiance(radiance, points_mm, light_mm, *, normals=None, scale: float = 1.0,
                         min_cos: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Divide out the point light's irradiance per pixel: ``radiance * scale * r² [/ cos_i]``.

    Parameters
    ----------
    radiance : ndarray of shape (H, W) or (H, W, C)
        Linear radiance.
    points_mm : ndarray of shape (H, W, 3)
        Surface point seen by each pixel, mm (same frame as ``light_mm``).
    light_mm : array_like of shape (3,)
        Light position, mm.
    normals : ndarray of shape (H, W, 3), optional
        Unit surface normals; with them the result is reflectance (BRDF) when ``scale`` comes
        from :func:`gray_card_scale`.
    scale : float
        Light intensity calibration (e.g. ``GrayCard.scale``).
    min_cos : float
        Pixels lit more grazingly than this (or from behind) are invalid.

    Returns
    -------
    normalized : ndarray, float32, shape of ``radiance``
        0 where invalid.
    valid : ndarray of shape (H, W), bool
    """
    L = _validate.array(radiance, "radiance", dtype=np.float32, ndim=(2, 3))
    P = _validate.array(points_mm, "points_mm", finite=False)
    light_mm = _validate.array(light_mm, "light_mm", shape=(3,))
    scale = _validate.positive(scale, "scale")
    if P.shape != L.shape[:2] + (3,):
        raise InvalidInput(f"points_mm must have shape {L.shape[:2] + (3,)}, got {P.shape}")
    to_light = np.asarray(light_mm, np.float64).reshape(3) - P
    r2 = np.sum(to_light ** 2, axis=-1)
    factor = scale * r2
    valid = np.isfinite(r2) & (r2 > 0)
    if normals is not None:
        N = np.asarray(normals, np.float64)
        if N.shape != P.shape:
            raise InvalidInput(f"normals must have shape {P.shape}, got {N.shape}")
        cos = np.sum(N * to_light, axis=-1) / np.sqrt(np.maximum(r2, 1e-30))
        valid &= cos >= min_cos
        factor = factor / np.maximum(cos, min_cos)
    factor = np.where(valid, factor, 0.0).astype(np.float32)
    out = L * (factor[..., None] if L.ndim == 3 else factor)
    return out.astype(np.float32), valid
