"""The report's view pictures are bounded in size: a real camera's 20-45 MP frame is drawn at most
PICTURE_MAX_PX on its longest side (issue 21: nothing in `gonio process` may grow with the
pixels past what --memory-limit holds), texels sharing a scaled pixel averaged, pixel centres kept."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from capture.pipeline.pictures import PICTURE_MAX_PX, _picture, _splat, picture_scale
from reconstruct.camera import CameraModel


def _plane_view(width: int, height: int):
    """A camera looking down at the plane z = 0 and one texel per camera pixel on it."""
    cam = CameraModel.look_at((0.0, 0.0, 1000.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), width=width,
                              height=height, focal_px=width)
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    rays = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
    d = rays.reshape(-1, 3) @ cam.R                  # camera -> world directions
    pos = cam.center + d * (-cam.center[2] / d[:, 2:3])
    lt = SimpleNamespace(position=pos, texel=np.arange(len(pos)))
    return lt, SimpleNamespace(camera=cam, object_to_world=np.eye(4)), u.ravel()


def test_a_large_frame_is_drawn_scaled_with_its_pixel_centres_kept():
    assert picture_scale(1536, 2048) == (PICTURE_MAX_PX / 2048, (768, 1024))
    lt, view, u = _plane_view(2048, 32)   # a strip: the longest side decides (3 M points take 7 s)
    s, size = picture_scale(32, 2048)
    assert size == (16, 1024) and s == PICTURE_MAX_PX / 2048
    pic = _splat(lt, u[:, None], view)
    assert pic.shape == (16, 1024, 1) and np.isfinite(pic).all()
    # each scaled pixel averages the 2 x 2 camera pixels it covers: its centre's camera column
    x = np.arange(1024)
    np.testing.assert_allclose(pic[:, :, 0], np.broadcast_to((x + 0.5) / s - 0.5, (16, 1024)), atol=1e-3)


def test_the_captured_frame_is_area_averaged_and_a_small_one_kept_bit_for_bit():
    rng = np.random.default_rng(0)
    big = rng.random((1536, 2048, 3), dtype=np.float32)
    small = _picture(big)
    assert small.shape == (768, 1024, 3) and small.dtype == np.float32
    np.testing.assert_allclose(small.mean(axis=(0, 1), dtype=np.float64), big.mean(axis=(0, 1), dtype=np.float64),
                               rtol=1e-5)
    np.testing.assert_allclose(small[10, 20], big[20:22, 40:42].mean(axis=(0, 1)), rtol=1e-5)
    quick = rng.random((240, 320, 3)).astype(np.float32)
    assert np.array_equal(_picture(quick), quick)
    lt, view, u = _plane_view(320, 240)
    assert picture_scale(240, 320) == (1.0, (240, 320))
    pic = _splat(lt, u[:, None], view)
    np.testing.assert_allclose(pic[:, :, 0], np.broadcast_to(np.arange(320.0), (240, 320)), atol=1e-6)
