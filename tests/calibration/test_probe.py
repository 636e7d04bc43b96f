"""Light probe: analytic environment -> rendered mirror sphere -> lat-long, one and two views."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.probe import latlong_directions, merge_probes, mirror_sphere_to_latlong


def env_fn(w):
    """A smooth RGB environment (radiance per world direction) with a warm 'sun' blob."""
    sun = np.exp(-np.sum((w - np.array([0.5, 0.3, 0.81]) / np.linalg.norm([0.5, 0.3, 0.81])) ** 2, -1) / 0.05)
    return np.stack([1.2 + 0.5 * w[..., 0] + 3 * sun, 1.0 + 0.4 * w[..., 1] + 2 * sun,
                     0.8 + 0.3 * w[..., 2] + sun], -1).astype(np.float32)


def render_probe(R, size=512, radius=240.0):
    """Orthographic mirror-sphere image of env_fn seen with world->camera rotation R."""
    c = (size - 1) / 2
    yy, xx = np.indices((size, size), dtype=float)
    nx, ny = (xx - c) / radius, (yy - c) / radius
    rho2 = nx ** 2 + ny ** 2
    inside = rho2 < 1
    n = np.stack([nx, ny, -np.sqrt(np.clip(1 - rho2, 0, 1))], -1)
    v = np.array([0.0, 0.0, -1.0])
    r_cam = 2 * (n @ v)[..., None] * n - v
    img = env_fn(r_cam @ R) * inside[..., None]  # world dir = R^T r_cam
    return img.astype(np.float32), (c, c), radius


def _look_from(azimuth_deg, elevation_deg=10.0):
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    fwd = -eye
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(fwd, right), fwd])


def test_latlong_convention():
    d = latlong_directions(4)
    assert d.shape == (4, 8, 3)
    assert d[0, 0, 2] > 0.9 and d[-1, 0, 2] < -0.9          # row 0 looks up (+z)
    assert d[2, 0, 0] > 0.9 * np.sin(np.radians(67.5)) and d[2, 0, 1] > 0  # column 0 near +x, towards +y
    assert d[2, 2, 1] > 0.9 * np.sin(np.radians(67.5))       # a quarter turn on: +y


def test_single_view_matches_environment_outside_blind_spot():
    R = _look_from(30.0)
    img, c, r = render_probe(R)
    probe = mirror_sphere_to_latlong(img, c, r, R, height=64)
    truth = env_fn(latlong_directions(64))
    good = probe.weight >= 1
    assert good.mean() > 0.85
    rel = np.abs(probe.env / truth - 1)[good]
    assert np.median(rel) < 0.005 and np.percentile(rel, 99) < 0.03
    # the blind spot is straight behind the sphere, i.e. the direction away from the camera
    behind = -(R.T @ [0, 0, -1.0])
    d = latlong_directions(64)
    assert np.all(probe.weight[(d @ behind) > np.cos(np.radians(10))] == 0)


def test_two_views_cover_every_direction():
    views = [_look_from(30.0), _look_from(210.0)]
    probes = [mirror_sphere_to_latlong(*render_probe(R), R, height=64) for R in views]
    merged = merge_probes(probes)
    assert merged.valid.all()
    truth = env_fn(latlong_directions(64))
    rel = np.abs(merged.env / truth - 1)
    assert np.median(rel) < 0.005 and np.percentile(rel, 99) < 0.03


def test_bad_inputs():
    img = np.zeros((10, 10, 3), np.float32)
    with pytest.raises(ValueError, match="rotation"):
        mirror_sphere_to_latlong(img, (5, 5), 4.0, np.ones((3, 3)))
    with pytest.raises(ValueError, match="radius_px"):
        mirror_sphere_to_latlong(img, (5, 5), 0.0, np.eye(3))
    with pytest.raises(ValueError, match="shape"):
        merge_probes([mirror_sphere_to_latlong(img, (5, 5), 4.0, np.eye(3), height=8),
                      mirror_sphere_to_latlong(img, (5, 5), 4.0, np.eye(3), height=16)])


@pytest.mark.realdata
def test_real_probe_round_trip(shared_data):
    """Grace Cathedral (a real lat-long HDR, taken as our convention) -> two mirror-sphere
    views -> lat-long again: the bright, detailed scene survives resampling."""
    grace = cv2.imread(str(shared_data / "probes" / "grace.hdr"), cv2.IMREAD_UNCHANGED)[..., ::-1].copy()
    h = grace.shape[0]
    d = latlong_directions(h)

    def sample(w):  # radiance of the real map in direction(s) w
        theta = np.arccos(np.clip(w[..., 2], -1, 1))
        phi = np.mod(np.arctan2(w[..., 1], w[..., 0]), 2 * np.pi)
        x = (phi * h / np.pi - 0.5).astype(np.float32)
        y = (theta * h / np.pi - 0.5).astype(np.float32)
        return cv2.remap(grace, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    probes = []
    size, radius = 1024, 500.0
    yy, xx = np.indices((size, size), dtype=float)
    nx, ny = (xx - 511.5) / radius, (yy - 511.5) / radius
    inside = nx ** 2 + ny ** 2 < 1
    n = np.stack([nx, ny, -np.sqrt(np.clip(1 - nx ** 2 - ny ** 2, 0, 1))], -1)
    r_cam = 2 * (-n[..., 2])[..., None] * n - np.array([0.0, 0.0, -1.0])
    for az in (0.0, 180.0):
        R = _look_from(az)
        img = sample(r_cam @ R) * inside[..., None]
        probes.append(mirror_sphere_to_latlong(img, (511.5, 511.5), radius, R, height=h))
    merged = merge_probes(probes)
    assert merged.valid.all()
    # total light (the probe's integral, solid-angle weighted) is preserved within 2 %
    sa = np.sin((np.arange(h) + 0.5) * np.pi / h)[:, None, None]
    assert abs(np.sum(merged.env * sa) / np.sum(grace * sa) - 1) < 0.02
    assert d.shape[:2] == merged.env.shape[:2]


def test_perspective_probe_is_exact_where_orthographic_is_not():
    """A 25 mm ball 300 mm from a pinhole camera: the perspective resampling matches the
    environment; the orthographic model is off by degrees near the rim."""
    from calibration.probe import mirror_sphere_to_latlong_perspective
    K = np.array([[2400.0, 0, 399.5], [0, 2400.0, 399.5], [0, 0, 1]])
    C, rad = np.array([3.0, -2.0, 300.0]), 25.0
    R = _look_from(30.0)
    s = 3  # supersampled render, only over the ball's bounding box (a quarter of the frame)
    uv = K @ C
    uv = uv[:2] / uv[2]
    r_px = K[0, 0] * rad / np.sqrt(C @ C - rad ** 2)
    x0, y0 = np.floor(uv - r_px - 2).astype(int)
    x1, y1 = np.ceil(uv + r_px + 2).astype(int)
    yy, xx = np.mgrid[y0 * s:(y1 + 1) * s, x0 * s:(x1 + 1) * s].astype(float)
    d = np.stack([(xx + 0.5) / s - 0.5, (yy + 0.5) / s - 0.5, np.ones_like(xx)], -1) @ np.linalg.inv(K).T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    b = d @ C
    disc = b ** 2 - (C @ C - rad ** 2)
    hit = disc > 0
    X = d * (b - np.sqrt(np.clip(disc, 0, None)))[..., None]
    n = (X - C) / rad
    r_cam = d - 2 * np.sum(d * n, -1, keepdims=True) * n
    img = np.zeros((800, 800, 3), np.float32)
    img[y0:y1 + 1, x0:x1 + 1] = (env_fn(r_cam @ R) * hit[..., None]).reshape(y1 + 1 - y0, s, x1 + 1 - x0, s,
                                                                            3).mean(axis=(1, 3))
    probe = mirror_sphere_to_latlong_perspective(img, K, None, C, rad, R, height=64)
    truth = env_fn(latlong_directions(64))
    good = probe.weight >= 1
    assert good.mean() > 0.8
    rel = np.abs(probe.env / truth - 1)[good]
    assert np.median(rel) < 0.005 and np.percentile(rel, 99) < 0.03
    # the orthographic shortcut on the same photo is measurably worse
    ortho = mirror_sphere_to_latlong(img, uv, r_px, R, height=64)
    both = good & (ortho.weight >= 1)
    assert np.percentile(np.abs(ortho.env / truth - 1)[both], 99) > 2 * np.percentile(rel, 99)
