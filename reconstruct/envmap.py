"""Latitude-longitude environment maps: lookup, solid angles, sampling, irradiance.

Convention (world = turntable frame, +z up), the one of PBRT's infinite area light:

- a unit direction ``w`` has polar angle ``theta = arccos(w_z)`` from +z and azimuth
  ``phi = atan2(w_y, w_x)`` in [0, 2 pi), counted from +x towards +y;
- in an H x W map, the column coordinate is ``x = phi / (2 pi) * W - 1/2`` and the row
  coordinate ``y = theta / pi * H - 1/2`` (pixel centres at integers; row 0 is the zenith +z,
  the last row the nadir -z, column 0 starts at phi = 0 = +x);
- pixel (i, j) covers theta in [i, i + 1] * pi / H and phi in [j, j + 1] * 2 pi / W, a solid
  angle of ``2 pi / W * (cos theta_i - cos theta_{i+1})`` sr.

An optional ``rotation`` (3x3, world -> map frame) turns the map relative to the world, e.g. a
probe captured with the camera's axes. Values are linear radiance, RGB, in the units of the
image (radiance seen along ``-w``, i.e. arriving from direction ``w``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .frames import linear_rows

#: Rec. 709 / sRGB luminance weights of linear RGB.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


@dataclass(frozen=True, eq=False)
class EnvironmentMap:
    """A lat-long environment map in the world frame (see module docstring for the convention).

    Parameters
    ----------
    image : ndarray of shape (H, W, 3)
        Linear radiance, RGB (stored as float32). W is usually 2 H.
    rotation : ndarray of shape (3, 3), optional
        World -> map rotation applied to every direction before the lookup.
    """

    image: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 2 or img.shape[1] < 2:
            raise ValueError(f"image must have shape (H, W, 3) with H, W >= 2, got {img.shape}")
        img = img.astype(np.float32)
        if not np.all(np.isfinite(img)) or img.min() < 0:
            raise ValueError("image must hold finite, non-negative linear radiance")
        R = np.asarray(self.rotation, dtype=np.float64)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
            raise ValueError(f"rotation must be a 3x3 rotation matrix, got {R!r}")
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "_dist", None)  # sampling tables, built on first use

    # -- construction ---------------------------------------------------------------------------
    @classmethod
    def load(cls, path, rotation=None) -> "EnvironmentMap":
        """Read a lat-long Radiance .hdr (or float TIFF) file; OpenCV's BGR becomes RGB."""
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise FileNotFoundError(f"cannot read an environment map from {Path(path)}")
        if img.ndim != 3 or img.shape[2] < 3:
            raise ValueError(f"{path}: expected a colour image, got shape {img.shape}")
        return cls(img[..., 2::-1], np.eye(3) if rotation is None else rotation)

    @classmethod
    def constant(cls, radiance, height: int = 16) -> "EnvironmentMap":
        """A uniform environment of ``radiance`` (scalar or RGB), ``height`` x 2 ``height``."""
        rgb = np.broadcast_to(np.asarray(radiance, np.float32), (3,))
        return cls(np.broadcast_to(rgb, (height, 2 * height, 3)).copy())

    @classmethod
    def from_function(cls, fn, height: int, width: int | None = None) -> "EnvironmentMap":
        """Sample ``fn(directions (N, 3) world) -> (N, 3) radiance`` at the pixel centres."""
        width = 2 * height if width is None else width
        d = pixel_directions(height, width).reshape(-1, 3)
        return cls(np.asarray(fn(d), np.float32).reshape(height, width, 3))

    def resized(self, height: int) -> "EnvironmentMap":
        """Averaged to ``height`` x 2 ``height`` (faster integration and sampling), weighting
        by solid angle so that the radiance integral over the sphere is kept (exactly for an
        integer reduction factor)."""
        if int(height) < 2:
            raise ValueError(f"height must be >= 2 pixels, got {height!r}")
        size = (2 * int(height), int(height))
        sa = self.solid_angles().astype(np.float32)
        num = cv2.resize(self.image * sa[..., None], size, interpolation=cv2.INTER_AREA)
        den = cv2.resize(sa, size, interpolation=cv2.INTER_AREA)
        return EnvironmentMap(num / den[..., None], self.rotation)

    # -- geometry -------------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape[:2]

    def solid_angles(self) -> np.ndarray:
        """Solid angle of every pixel, sr, shape (H, W); sums to 4 pi."""
        return pixel_solid_angles(*self.shape)

    def directions(self) -> np.ndarray:
        """World-frame unit directions of the pixel centres, shape (H, W, 3)."""
        d = pixel_directions(*self.shape)
        return d @ self.rotation  # map -> world: R^T applied to row vectors (a small grid)

    def sources(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The map as distant sources, one per pixel: world directions (H*W, 3), radiance
        (H*W, 3) and solid angles (H*W,) sr (for :func:`reconstruct.distant.shade_distant`)."""
        return (self.directions().reshape(-1, 3), self.image.reshape(-1, 3).astype(np.float64),
                self.solid_angles().reshape(-1))

    def to_pixel(self, dirs) -> np.ndarray:
        """Continuous pixel coordinates (x, y) of world directions (N, 3) -> (N, 2)."""
        d = linear_rows(self.rotation, _check_dirs(dirs))
        return direction_to_pixel(d, *self.shape)

    def lookup(self, dirs, *, interpolation: str = "bilinear") -> np.ndarray:
        """Radiance arriving from world directions ``dirs`` (N, 3) -> (N, 3) float32.

        ``interpolation``: 'bilinear' (wraps in azimuth, clamps at the poles) or 'nearest'
        (the exact pixel value, as the importance sampler's pdf assumes).
        """
        H, W = self.shape
        if interpolation == "nearest":
            return self.image.reshape(-1, 3)[self._pixel_index(dirs)]
        if interpolation != "bilinear":
            raise ValueError(f"interpolation must be 'bilinear' or 'nearest', got "
                             f"{interpolation!r}")
        xy = self.to_pixel(dirs)
        x0 = np.floor(xy[:, 0])
        y = np.clip(xy[:, 1], 0, H - 1)
        y0 = np.minimum(np.floor(y), H - 2)
        fx = (xy[:, 0] - x0)[:, None].astype(np.float32)
        fy = (y - y0)[:, None].astype(np.float32)
        j0 = np.mod(x0.astype(np.int64), W)
        j1 = np.mod(j0 + 1, W)
        i0 = y0.astype(np.int64)
        img = self.image
        top = img[i0, j0] * (1 - fx) + img[i0, j1] * fx
        bot = img[i0 + 1, j0] * (1 - fx) + img[i0 + 1, j1] * fx
        return top * (1 - fy) + bot * fy

    # -- integration and sampling ---------------------------------------------------------------
    def irradiance(self, normals, *, chunk: int = 4096) -> np.ndarray:
        """Irradiance E(n) = sum over pixels of L * max(0, n . w) * d_omega on surfaces with world
        unit ``normals`` (N, 3) -> (N, 3), by direct summation over every pixel (no occlusion).
        Units: the map's radiance times sr."""
        n = _check_dirs(normals)
        d = self.directions().reshape(-1, 3)
        Lw = (self.image.reshape(-1, 3) * self.solid_angles().reshape(-1, 1)).astype(np.float64)
        out = np.empty((len(n), 3))
        for s in range(0, len(n), chunk):
            out[s:s + chunk] = np.maximum(n[s:s + chunk] @ d.T, 0.0) @ Lw
        return out

    def luminance(self) -> np.ndarray:
        """Luminance of every pixel (Rec. 709 weights), shape (H, W)."""
        return self.image @ LUMINANCE.astype(np.float32)

    def sample(self, n: int, rng: np.random.Generator, *, method: str = "importance"):
        """Draw ``n`` world directions with their pdf (1/sr, w.r.t. solid angle).

        ``method='importance'``: pick a pixel with probability proportional to luminance times
        solid angle (falls back to uniform for an all-black map), then a uniform direction inside
        it. ``method='uniform'``: uniform over the sphere, pdf = 1 / (4 pi).

        Returns
        -------
        dirs : ndarray of shape (n, 3)
        pdf : ndarray of shape (n,)
        """
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        if int(n) < 1:
            raise ValueError(f"n must be >= 1, got {n!r}")
        n = int(n)
        if method == "uniform":
            z = rng.uniform(-1.0, 1.0, n)
            phi = rng.uniform(0.0, 2 * np.pi, n)
            r = np.sqrt(np.maximum(0.0, 1 - z * z))
            d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
            return d, np.full(n, 1 / (4 * np.pi))
        if method != "importance":
            raise ValueError(f"method must be 'importance' or 'uniform', got {method!r}")
        H, W = self.shape
        p_pix, sa, cdf = self._pixel_distribution()
        k = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), H * W - 1)
        i, j = np.divmod(k, W)
        # uniform in solid angle within the pixel: uniform in phi and in cos(theta)
        c0 = np.cos(np.pi * i / H)
        c1 = np.cos(np.pi * (i + 1) / H)
        z = c0 + rng.random(n) * (c1 - c0)
        phi = 2 * np.pi * (j + rng.random(n)) / W
        r = np.sqrt(np.maximum(0.0, 1 - z * z))
        d = linear_rows(self.rotation.T, np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1))
        return d, p_pix[k] / sa[k]

    def pdf(self, dirs) -> np.ndarray:
        """Importance-sampling pdf (1/sr) of world directions (N, 3) -> (N,)."""
        return self.lookup_pdf(dirs)[1]

    def lookup_pdf(self, dirs) -> tuple[np.ndarray, np.ndarray]:
        """Nearest-pixel radiance (N, 3) and importance-sampling pdf (N,) (1/sr) of world
        directions (N, 3), finding each pixel once (the Monte-Carlo estimator needs both)."""
        k = self._pixel_index(dirs)
        p_pix, sa, _ = self._pixel_distribution()
        return self.image.reshape(-1, 3)[k], p_pix[k] / sa[k]

    def _pixel_index(self, dirs) -> np.ndarray:
        """Flat index of the pixel containing each world direction (N, 3) -> (N,)."""
        H, W = self.shape
        xy = self.to_pixel(dirs)
        j = np.mod(np.floor(xy[:, 0] + 0.5).astype(np.int64), W)
        i = np.clip(np.floor(xy[:, 1] + 0.5).astype(np.int64), 0, H - 1)
        return i * W + j

    def _pixel_distribution(self):
        """(probability of each pixel, its solid angle, cumulative probability), flattened."""
        if self._dist is None:
            sa = self.solid_angles().ravel()
            w = self.luminance().ravel().astype(np.float64) * sa
            p = w / w.sum() if w.sum() > 0 else sa / sa.sum()
            object.__setattr__(self, "_dist", (p, sa, np.cumsum(p)))
        return self._dist


def _check_dirs(dirs) -> np.ndarray:
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3), got {d.shape}")
    return d


def pixel_solid_angles(height: int, width: int) -> np.ndarray:
    """Exact solid angle (sr) of each pixel of a lat-long map, shape (H, W)."""
    edges = np.cos(np.pi * np.arange(height + 1) / height)
    return np.repeat(((edges[:-1] - edges[1:]) * 2 * np.pi / width)[:, None], width, axis=1)


def pixel_directions(height: int, width: int) -> np.ndarray:
    """Unit directions (map frame) of the pixel centres of a lat-long map, shape (H, W, 3)."""
    theta = np.pi * (np.arange(height) + 0.5) / height
    phi = 2 * np.pi * (np.arange(width) + 0.5) / width
    st = np.sin(theta)[:, None]
    return np.stack([st * np.cos(phi)[None, :], st * np.sin(phi)[None, :],
                     np.broadcast_to(np.cos(theta)[:, None], (height, width))], axis=-1)


def direction_to_pixel(dirs, height: int, width: int) -> np.ndarray:
    """Continuous pixel coordinates (x, y) of map-frame unit directions (N, 3) -> (N, 2)."""
    d = _check_dirs(dirs)
    phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    theta = np.arccos(np.clip(d[:, 2] / np.sqrt(np.einsum("ij,ij->i", d, d)), -1.0, 1.0))
    return np.stack([phi / (2 * np.pi) * width - 0.5, theta / np.pi * height - 0.5], axis=1)


def pixel_to_direction(xy, height: int, width: int) -> np.ndarray:
    """Map-frame unit directions of continuous pixel coordinates (N, 2) -> (N, 3)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    phi = 2 * np.pi * (xy[:, 0] + 0.5) / width
    theta = np.pi * (xy[:, 1] + 0.5) / height
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=1)
