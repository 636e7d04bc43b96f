"""A renderer gonio did not write checks the export: Mitsuba 3 renders an exported held-out
capture, and the render is read at the held-out samples (through the same pinhole it rendered
with) beside the method's predictions and the captures, all as radiance."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .appearance import Appearance
from .mitsuba import MitsubaView, pinhole_project, render

__all__ = ["HeldOutRender", "render_held_out"]


@dataclass(frozen=True)
class HeldOutRender:
    """Radiance (N, 3) at the held-out samples Mitsuba's render covers (calibration units):
    ``rendered`` by Mitsuba, ``predicted`` by the method (``f_r cos I / d^2``), ``captured``;
    ``pixels`` (N, 2) where the pinhole images them on the capture's film (x right, y down,
    pixel centres at integers); ``image`` the render itself on the capture's film (H, W, 3),
    area-averaged from the finer film."""

    rendered: np.ndarray
    predicted: np.ndarray
    captured: np.ndarray
    pixels: np.ndarray
    image: np.ndarray


def render_held_out(xml: str | Path, app: Appearance, view: int, *, spp: int = 4,
                    supersample: int = 3) -> HeldOutRender:
    """Render ``xml`` (the export's scene of capture ``view``, an index of
    ``app.view_camera_to_object``) on a ``supersample`` times finer film, so a pixel's footprint
    does not blur highlights, and read it bilinearly at the view's held-out samples whose pixel
    lies inside the silhouette with a one-pixel margin."""
    img = render(xml, spp=spp, supersample=supersample)
    light = app.view_light_mm[view]
    W, H = (int(v) * supersample for v in app.image_size)
    K = np.diag([supersample, supersample, 1.0]) @ app.K
    mv = MitsubaView("check", app.view_camera_to_object[view], K, (W, H), light, app.light_intensity)
    s = app.held_view == view
    p = app.position[app.held_texel[s]]
    px = pinhole_project(mv, p) - 0.5          # pixel centres at integers for cv2.remap
    inside = cv2.erode((img.sum(axis=2) > 0).astype(np.uint8), np.ones((3, 3), np.uint8))
    xi, yi = np.rint(px[:, 0]).astype(int), np.rint(px[:, 1]).astype(int)
    ok = (xi >= 0) & (yi >= 0) & (xi < W) & (yi < H)
    ok[ok] &= inside[yi[ok], xi[ok]] > 0
    mx, my = px[ok, 0].astype(np.float32)[None], px[ok, 1].astype(np.float32)[None]
    got = np.stack([cv2.remap(img[..., c], mx, my, cv2.INTER_LINEAR)[0] for c in range(3)], axis=1)
    scale = app.light_intensity / np.sum((light - p[ok]) ** 2, axis=1)[:, None]
    native = cv2.resize(img, (W // supersample, H // supersample), interpolation=cv2.INTER_AREA)
    centres = (px[ok] + 0.5) / supersample - 0.5
    return HeldOutRender(got, app.held_predicted[s][ok] * scale, app.held_captured[s][ok] * scale, centres, native)
