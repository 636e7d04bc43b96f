"""High-dynamic-range radiance from exposure brackets.

Raw path: decoded Bayer mosaics (:func:`calibration.raw.read_raw`) are black-subtracted,
saturation-masked, normalised by exposure time and merged with noise-optimal weights
(inverse variance under a shot + read noise model, Granados et al. 2010). Output: float32
linear radiance in DN per second on the mosaic grid (demosaic afterwards if needed).

8-bit path: the camera response is recovered with OpenCV's Debevec calibration, and the merge
is our own weighted average in log space (OpenCV's ``MergeDebevec`` weights 0 and 255 non-zero
and shares one weight across channels, which biases it for measurement).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from . import _validate
from .errors import InvalidInput, TooFewViews

__all__ = ["HDRImage", "merge_raw_brackets", "master_frame",
           "recover_response", "merge_ldr", "write_hdr"]


@dataclass(frozen=True)
class HDRImage:
    """Merged radiance.

    Attributes
    ----------
    radiance : ndarray, float32
        Linear radiance, DN/s (raw) or relative units (8-bit), input shape.
    sigma : ndarray, float32
        1-sigma noise of ``radiance`` from the noise model (raw path; zeros for 8-bit).
    saturated : ndarray, bool
        Clipped in every exposure: ``radiance`` is then only a lower bound.
    n_used : ndarray, uint8
        How many exposures contributed to each pixel.
    """

    radiance: np.ndarray
    sigma: np.ndarray
    saturated: np.ndarray
    n_used: np.ndarray


def master_frame(frames, method: str = "median") -> np.ndarray:
    """Combine dark (or flat) frames (N, H, W[, C]) into one float32 master, pixel by pixel.

    ``'median'`` rejects cosmic rays and hot single events; ``'mean'`` has lower noise.
    """
    try:
        f = np.asarray(frames, dtype=np.float32)
    except (TypeError, ValueError):
        raise InvalidInput("frames must be a stack of equally sized numeric frames", argument="frames") from None
    if f.ndim < 3 or f.shape[0] < 1:
        raise InvalidInput(f"frames must be a stack (N, H, W[, C]), got shape {f.shape}")
    if not np.all(np.isfinite(f)):
        raise InvalidInput("frames contain NaN or infinite values", argument="frames")
    if method == "median":
        return np.median(f, axis=0).astype(np.float32)
    if method == "mean":
        return f.mean(axis=0, dtype=np.float64).astype(np.float32)
    raise InvalidInput(f"method must be 'median' or 'mean', got {method!r}")


def merge_raw_brackets(frames: Sequence[np.ndarray], exposure_s, *, black_level=0.0, white_level: float,
                       gain_e_per_dn: float | None = None, gain_dn_per_e: float | None = None,
                       read_noise_dn: float = 1.0,
                       linear_fraction: float = 0.97, darks=None) -> HDRImage:
    """Merge raw exposures of a static scene into linear radiance (noise-optimal weights).

    For exposure ``k`` the estimate is ``X_k = (D_k - dark_k) / t_k`` with variance
    ``(X t_k / g + s_r²) / t_k²`` (``g`` electrons per DN, ``s_r`` read noise in DN); samples at
    or above ``black + linear_fraction * (white - black)`` are excluded as clipped. The weights
    use a pooled first estimate of ``X`` (not each frame's own noisy value, which would bias
    the merge low), then one re-weighting pass.

    Parameters
    ----------
    frames : sequence of ndarray of shape (H, W)
        Raw mosaics (or any linear single-channel frames), DN, same shape.
    exposure_s : array_like of shape (N,)
        Exposure times, seconds (> 0).
    black_level : float or ndarray of shape (H, W)
        Black level, DN (scalar or per photosite, e.g. :attr:`calibration.raw.RawMosaic.black_level`). Ignored for
        frames that have a dark frame.
    white_level : float
        Sensor clipping level, DN.
    gain_e_per_dn, gain_dn_per_e : float, optional
        Conversion gain, given one way or the other (> 0): electrons per DN (EMVA 1288's
        1/K, what photon-transfer curves give) or DN per electron (what many data sheets
        quote as "system gain" K). Give at most one; neither: 1 e-/DN.
    read_noise_dn : float
        Read noise, DN rms (>= 0).
    linear_fraction : float
        Fraction of the black-to-white range regarded as linear.
    darks : ndarray of shape (H, W) or (N, H, W), optional
        Dark frame(s) at the same exposure time(s) (include the black level): subtracted
        instead of ``black_level`` (which then only sets the clip level).

    Returns
    -------
    HDRImage
        ``radiance`` in DN/s, float32, shape (H, W).

    Raises
    ------
    TooFewViews
        No frames.
    InvalidInput
        A bad argument (named), or both gains given.
    """
    if gain_e_per_dn is not None and gain_dn_per_e is not None:
        raise InvalidInput("give the conversion gain once: gain_e_per_dn (electrons per DN) or "
                           "gain_dn_per_e (DN per electron), not both", argument="gain_dn_per_e")
    if gain_dn_per_e is not None:
        gain_e_per_dn = 1.0 / _validate.positive(gain_dn_per_e, "gain_dn_per_e")
    elif gain_e_per_dn is None:
        gain_e_per_dn = 1.0
    if len(frames) == 0:
        raise TooFewViews("HDR merge (exposures)", have=0, need=1)
    D = [_validate.image(f, f"frames[{k}]") for k, f in enumerate(frames)]
    if len({f.shape for f in D}) != 1:
        raise InvalidInput(f"frames must share one shape, got {sorted({f.shape for f in D})}", argument="frames")
    D = np.stack(D)  # converted to float32 block by block
    if D.ndim != 3:
        raise InvalidInput(f"frames must be 2-D mosaics of one shape, got stack shape {D.shape}")
    t = _validate.array(exposure_s, "exposure_s").ravel()
    white_level = _validate.positive(white_level, "white_level")
    gain_e_per_dn = _validate.positive(gain_e_per_dn, "gain_e_per_dn")
    read_noise_dn = _validate.positive(read_noise_dn, "read_noise_dn", allow_zero=True)
    if t.shape != (len(D),):
        raise InvalidInput(f"exposure_s must have one time per frame ({len(D)}), got shape {t.shape}")
    if np.any(~(t > 0)):
        raise InvalidInput(f"exposure_s must be positive, got {t}")
    if not 0 < linear_fraction <= 1:
        raise InvalidInput(f"linear_fraction must be in (0, 1], got {linear_fraction}")
    black = _validate.array(black_level, "black_level", dtype=np.float32)
    if black.shape not in ((), D.shape[1:]):
        raise InvalidInput(f"black_level must be a scalar or one level per photosite {D.shape[1:]}, "
                           f"got shape {black.shape}", argument="black_level")
    black = np.broadcast_to(black, D.shape[1:])
    if np.any(black >= white_level):
        raise InvalidInput(f"black_level must be below white_level ({white_level})")
    dk = None if darks is None else _validate.array(darks, "darks", dtype=np.float32)
    if dk is not None:
        if dk.shape not in (D.shape[1:], D.shape):
            raise InvalidInput(f"darks must have shape {D.shape[1:]} or {D.shape}, got {dk.shape}", argument="darks")
        dk = np.broadcast_to(dk, D.shape)
    out = HDRImage(np.empty(D.shape[1:], np.float32), np.empty(D.shape[1:], np.float32),
                   np.empty(D.shape[1:], bool), np.empty(D.shape[1:], np.uint8))
    # Row blocks: the per-pixel work needs several (N, rows, W) temporaries; whole 24 MP frames
    # would allocate (and page-fault) gigabytes.
    rows = max(1, _BLOCK_SAMPLES // (len(D) * D.shape[2]))
    for r0 in range(0, D.shape[1], rows):
        sl = slice(r0, r0 + rows)
        _merge_block(D[:, sl].astype(np.float32), t, black[sl], None if dk is None else dk[:, sl],
                     white_level, linear_fraction,
                     np.float32(gain_e_per_dn), np.float32(read_noise_dn ** 2),
                     out.radiance[sl], out.sigma[sl], out.saturated[sl], out.n_used[sl])
    return out


#: samples (frames x pixels) per block of :func:`merge_raw_brackets`
_BLOCK_SAMPLES = 1 << 19  # 12 MP x 5 frames: 2.6 s in blocks vs 10.3 s whole (loaded 2-core box)


def _merge_block(D, t, black, dark, white_level, linear_fraction, g, rn2, radiance, sigma, saturated, n_used):
    """Merge one row block in place (see :func:`merge_raw_brackets`)."""
    clip_at = black + linear_fraction * (white_level - black)
    valid = D < clip_at
    X = (D - (black if dark is None else dark)) / t[:, None, None].astype(np.float32)
    tt = t[:, None, None].astype(np.float32)

    def pooled(estimate):
        var = (np.maximum(estimate, 0)[None] * tt / g + rn2) / tt ** 2
        w = np.where(valid, 1.0 / np.maximum(var, 1e-30), 0.0).astype(np.float32)
        sw = w.sum(axis=0)
        return np.sum(w * X, axis=0) / np.maximum(sw, 1e-30), sw

    # First estimate: each pixel's longest unclipped exposure (its best single SNR).
    longest = np.where(valid, tt, 0).argmax(axis=0)
    est, sw = pooled(np.take_along_axis(X, longest[None], axis=0)[0])
    est, sw = pooled(est)
    n_used[:] = valid.sum(axis=0)
    saturated[:] = n_used == 0
    # All exposures clipped: the clip level of the shortest exposure is a lower bound.
    radiance[:] = np.where(saturated, (clip_at - black) / t.min(), est)
    sigma[:] = np.where(saturated, 0.0, 1.0 / np.sqrt(np.maximum(sw, 1e-30)))


def _ldr_stack(images, exposure_s):
    imgs = [_validate.image(i, f"images[{k}]") for k, i in enumerate(images)]
    if len({i.shape for i in imgs}) > 1:
        raise InvalidInput(f"images must share one shape, got {sorted({i.shape for i in imgs})}", argument="images")
    imgs = np.stack(imgs) if imgs else np.zeros((0, 1, 1), np.uint8)
    if imgs.dtype != np.uint8:
        raise InvalidInput(f"images must be 8-bit (uint8), got {imgs.dtype}")
    if imgs.ndim == 3:
        imgs = imgs[..., None]
    if imgs.ndim != 4:
        raise InvalidInput(f"images must be (H, W) or (H, W, C) each, got stack shape {imgs.shape}")
    t = np.asarray(exposure_s, np.float64).ravel()
    if t.shape != (len(imgs),) or np.any(~(t > 0)):
        raise InvalidInput(f"exposure_s must hold {len(imgs)} positive times, got {t}")
    if len(imgs) < 2:
        raise TooFewViews("response recovery / LDR merge (exposures)", have=len(imgs), need=2)
    return imgs, t


def recover_response(images, exposure_s, *, samples: int = 70, smoothness: float = 10.0) -> np.ndarray:
    """Camera response of 8-bit images (Debevec & Malik, via ``cv2.createCalibrateDebevec``).

    Parameters
    ----------
    images : sequence of ndarray of shape (H, W, 3), uint8
        A bracket of a static scene.
    exposure_s : array_like of shape (N,)
        Exposure times, seconds.
    samples, smoothness : OpenCV's sample count and smoothness lambda.

    Returns
    -------
    ndarray of shape (256, 3), float32
        Relative exposure (radiance x time) that produces each code value, per channel.
    """
    imgs, t = _ldr_stack(images, exposure_s)
    if imgs.shape[-1] != 3:
        raise InvalidInput("recover_response needs 3-channel images (OpenCV's calibration is RGB)")
    cal = cv2.createCalibrateDebevec(samples, smoothness, False)
    resp = cal.process([np.ascontiguousarray(i) for i in imgs], t.astype(np.float32))
    return resp.reshape(256, 3).astype(np.float32)


def merge_ldr(images, exposure_s, response, *, clip_margin: int = 3) -> HDRImage:
    """Weighted merge of 8-bit exposures with a known response (numpy; per channel).

    ``ln E = sum_k w(z_k) (ln f(z_k) - ln t_k) / sum_k w(z_k)`` with the hat weight
    ``w(z) = min(z, 255 - z)``, zero at 0 and 255. Pixels clipped high in every exposure take
    the shortest exposure's value at code 254 (flagged ``saturated``); pixels at 0 in every
    exposure take the longest exposure's value at code 1.

    Parameters
    ----------
    images : sequence of ndarray of shape (H, W) or (H, W, C), uint8
    exposure_s : array_like of shape (N,)
        Exposure times, seconds.
    response : ndarray of shape (256,) or (256, C)
        Exposure that produces each code (e.g. :func:`recover_response`), positive.
    clip_margin : int
        Codes within this of 0 or 255 count as clipped: they and every longer (resp. shorter)
        exposure of the pixel get zero weight.

    Returns
    -------
    HDRImage
        ``radiance`` float32 (H, W, C) (or (H, W)), in the response's units per second.
    """
    imgs, t = _ldr_stack(images, exposure_s)
    C = imgs.shape[-1]
    resp = _validate.array(response, "response")
    if resp.shape not in ((256,), (256, 1), (256, C)):
        raise InvalidInput(f"response must be (256,) or (256, {C}), got {resp.shape}", argument="response")
    resp = resp.reshape(256, -1)
    if resp.shape[1] not in (1, C):
        raise InvalidInput(f"response must be (256,) or (256, {C}), got {np.shape(response)}")
    if np.any(~(resp[1:255] > 0)):
        raise InvalidInput("response must be positive for codes 1..254")
    log_f = np.log(np.maximum(np.broadcast_to(resp, (256, C)), 1e-30)).astype(np.float32)
    codes = np.arange(256)
    w_lut = np.minimum(codes, 255 - codes).astype(np.float32)
    order = np.argsort(t)
    # A pixel clipped in a shorter exposure is clipped in every longer one, whatever noise says
    # (a noisy 254 there would carry a wildly low value); likewise for black in longer ones.
    clipped_hi = np.zeros(imgs.shape[1:], bool)
    blocked = np.zeros(imgs.shape, bool)
    for k in order:
        clipped_hi |= imgs[k] >= 255 - clip_margin
        blocked[k] = clipped_hi
    clipped_lo = np.zeros(imgs.shape[1:], bool)
    for k in order[::-1]:
        clipped_lo |= imgs[k] <= clip_margin
        blocked[k] |= clipped_lo
    num = np.zeros(imgs.shape[1:], np.float32)
    sw = np.zeros(imgs.shape[1:], np.float32)
    n_used = np.zeros(imgs.shape[1:], np.uint8)
    w_lut_c = np.repeat(w_lut[None, :, None], C, axis=2)
    log_lut = log_f[None]  # (1, 256, C): cv2.LUT maps each channel through its own column
    for k in range(len(imgs)):  # a few exposures; per-pixel work is table look-ups
        img = np.ascontiguousarray(imgs[k])
        wk = cv2.LUT(img, w_lut_c).reshape(img.shape)
        wk[blocked[k]] = 0
        num += wk * (cv2.LUT(img, log_lut).reshape(img.shape) - np.float32(np.log(t[k])))
        sw += wk
        n_used += wk > 0
    none = sw == 0
    high = none & clipped_hi
    fallback = np.where(high, log_f[254] - np.log(t.min()), log_f[1] - np.log(t.max()))
    out = np.exp(np.where(none, fallback, num / np.maximum(sw, 1e-30))).astype(np.float32)
    squeeze = np.asarray(images[0]).ndim == 2
    pick = (lambda a: a[..., 0]) if squeeze else (lambda a: a)  # noqa: E731
    return HDRImage(pick(out), np.zeros_like(pick(out)), pick(high), pick(n_used))


def write_hdr(path: str | os.PathLike, image) -> None:
    """Write linear radiance as float32: ``.tif``/``.tiff`` (tifffile, exact round trip) or
    ``.exr`` (needs the ``OpenEXR`` package; OpenCV 5 wheels cannot write EXR).

    Parameters
    ----------
    path : path
        Output file; the suffix picks the format.
    image : ndarray of shape (H, W) or (H, W, 3)
        Finite values.
    """
    img = np.asarray(image, np.float32)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
        raise InvalidInput(f"image must be (H, W) or (H, W, 1|3|4), got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise InvalidInput("image contains NaN or infinite values")
    suffix = os.fspath(path).lower().rsplit(".", 1)[-1]
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    if not os.path.isdir(folder):
        raise InvalidInput(f"path: folder {folder} does not exist", argument="path")
    if suffix in ("tif", "tiff"):
        import tifffile

        tifffile.imwrite(path, img, photometric="rgb" if img.ndim == 3 and img.shape[2] >= 3 else "minisblack")
    elif suffix == "exr":
        try:
            import OpenEXR
        except ImportError:
            raise InvalidInput(f"{path}: writing EXR needs the 'OpenEXR' package (pip install OpenEXR); "
                               "use .tif for float32 TIFF") from None
        chans = img if img.ndim == 3 else img[..., None]
        names = "RGBA"[:chans.shape[2]] if chans.shape[2] > 1 else "Y"
        channels = {n: np.ascontiguousarray(chans[..., i]) for i, n in enumerate(names)}
        with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                          channels) as f:
            f.write(os.fspath(path))
    else:
        raise InvalidInput(f"{path}: unsupported HDR format '.{suffix}' (use .tif, .tiff or .exr)")
