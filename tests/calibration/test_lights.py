"""Light localisation: analytic chrome-sphere images, point-light triangulation, positioner
kinematics, Lensch's collinear spheres, and the real UW chrome-sphere photos."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.errors import DegenerateFit, NotConverged, TargetNotFound, TooFewViews
from calibration.lights import (closest_point_to_lines, detect_sphere, ray_weights, find_highlight, fit_positioner_model,
                                light_direction_orthographic, locate_collinear_spheres,
                                reflect_highlight, sphere_center_from_silhouette,
                                triangulate_point_light)

K = np.array([[3000.0, 0, 959.5], [0, 3000.0, 719.5], [0, 0, 1]])
SIZE = (1920, 1440)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _angle_deg(u, v):
    return np.degrees(np.arccos(np.clip(np.sum(_unit(u) * _unit(v), -1), -1, 1)))


def render_spheres(centres, radius, *, light_dir=None, light_pos=None, K=K, size=SIZE, lobe_deg=0.6,
                   peak=8.0, noise=0.002, rng=None, flash=False, ss=3):
    """Chrome spheres seen by a pinhole camera without skew (``ss`` x ``ss`` supersampled inside each sphere's
    bounding box), lit by a distant light, a point light, or a flash at the camera; returns
    (image clipped at 1, sphere mask)."""
    rng = np.random.default_rng(0) if rng is None else rng
    w, h = size
    s = ss
    img = np.zeros((h, w))
    cover = np.zeros((h, w))
    for C in np.atleast_2d(centres):
        uv = (K @ C)[:2] / C[2]
        rad = 1.3 * K[0, 0] * radius / (C[2] - radius)
        x0, y0 = np.maximum(np.floor(uv - rad).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(uv + rad).astype(int), [w - 1, h - 1])
        # pinhole without skew: separable back-projection; full (N, 3) ray arrays only for the
        # samples that hit the sphere (memory traffic dominates at millions of samples)
        xn = ((np.arange(x0 * s, (x1 + 1) * s) + 0.5) / s - 0.5 - K[0, 2]) / K[0, 0]
        yn = ((np.arange(y0 * s, (y1 + 1) * s) + 0.5) / s - 0.5 - K[1, 2]) / K[1, 1]
        inv = 1.0 / np.sqrt(xn[None, :] ** 2 + yn[:, None] ** 2 + 1.0)
        b = ((xn[None, :] * C[0] + yn[:, None] * C[1] + C[2]) * inv).ravel()
        disc = b ** 2 - (C @ C - radius ** 2)
        hit = disc > 0
        iy, ix = np.divmod(np.flatnonzero(hit), len(xn))
        d = np.stack([xn[ix], yn[iy], np.ones(len(ix))], -1) * inv.ravel()[hit][:, None]
        X = d * (b[hit] - np.sqrt(disc[hit]))[:, None]
        n = (X - C) / radius
        v = -d
        r = 2 * np.sum(n * v, 1, keepdims=True) * n - v
        if flash:
            L = v
        elif light_pos is not None:
            L = _unit(light_pos - X)
        else:
            L = np.broadcast_to(_unit(light_dir), r.shape)
        val = np.zeros(len(b))
        cos_rl = np.sum(r * L, 1)
        # the lobe is below 1e-11 of its peak beyond 5 widths: evaluate it only inside
        near = cos_rl > np.cos(np.radians(5 * lobe_deg))
        lobe = np.zeros(len(r))
        lobe[near] = peak * np.exp(-(np.arccos(np.clip(cos_rl[near], -1, 1)) / np.radians(lobe_deg)) ** 2)
        val[hit] = lobe + 0.05
        shape = ((y1 + 1 - y0), s, (x1 + 1 - x0), s)
        img[y0:y1 + 1, x0:x1 + 1] += val.reshape(shape).mean(axis=(1, 3))
        cover[y0:y1 + 1, x0:x1 + 1] += hit.astype(float).reshape(shape).mean(axis=(1, 3))
    img = np.clip(img + rng.normal(0, noise, img.shape), 0, 1)
    return img, cover > 0.5


@pytest.mark.parametrize("light", [[0.3, -0.4, -0.8], [-0.1, 0.2, -1.0], [0.6, 0.5, -0.5]])
def test_distant_light_direction_within_0p25_deg(light):
    # one large sphere nearly on the optical axis and far away: orthographic is accurate to
    # the angle the sphere subtends; the perspective path is exact.
    C = np.array([0.0, 0.0, 600.0])
    R = 40.0
    img, mask = render_spheres(C, R, light_dir=light)
    sph = detect_sphere(mask)
    hl = find_highlight(img, sph, saturation=1.0)
    assert hl.n_saturated > 3
    P, L = reflect_highlight(hl.xy_px[None], C[None], R, K)
    assert _angle_deg(L[0], light) < 0.25
    # the centre recovered from the silhouette alone (known radius) is as good
    C_fit = sphere_center_from_silhouette(sph, K, radius_mm=R)
    assert np.linalg.norm(C_fit - C) < 0.005 * 600
    _, L2 = reflect_highlight(hl.xy_px[None], C_fit[None], R, K)
    assert _angle_deg(L2[0], light) < 0.25


def test_orthographic_direction_formula():
    from calibration.lights import SphereImage
    sph = SphereImage(np.array([100.0, 50.0]), 40.0, None, np.zeros((0, 2)))
    # highlight at the centre: light straight back at the viewer (-z in the camera frame)
    np.testing.assert_allclose(light_direction_orthographic([100.0, 50.0], sph), [0, 0, -1], atol=1e-12)
    # at 45° of normal tilt the light is perpendicular to the view
    off = 40.0 * np.sin(np.radians(45))
    np.testing.assert_allclose(light_direction_orthographic([100.0 + off, 50.0], sph), [1, 0, 0], atol=1e-12)
    with pytest.raises(ValueError, match="outside"):
        light_direction_orthographic([200.0, 50.0], sph)


def test_point_light_within_half_percent_of_distance():
    R = 25.0
    centres = np.array([[-150.0, -80, 700], [150, -90, 720], [-140, 100, 690], [160, 90, 710], [0, 0, 650]])
    light = np.array([120.0, -600.0, 250.0])
    img, mask = render_spheres(centres, R, light_pos=light, lobe_deg=3.0)  # a bulb of finite size
    n, labels = cv2.connectedComponents(mask.astype(np.uint8))
    hls = []
    for C in centres:  # sphere order: the blob under each centre's projection
        uv = (K @ C)[:2] / C[2]
        blob = labels == labels[int(round(uv[1])), int(round(uv[0]))]
        sph = detect_sphere(blob)
        hls.append(find_highlight(np.where(blob, img, 0), sph, saturation=1.0).xy_px)
    pl = triangulate_point_light(np.array(hls), centres, R, K, sigma_px=0.1)
    dist = np.linalg.norm(light - centres.mean(0))
    err = np.linalg.norm(pl.position_mm - light)
    assert err < 0.005 * dist, (err, dist)
    # the stated uncertainty is of the right size (error within 4 sigma of the worst axis)
    assert err < 4 * np.sqrt(np.trace(pl.covariance_mm2))
    assert pl.residuals_mm.max() < 2.0


def test_point_light_degenerate_and_too_few():
    with pytest.raises(TooFewViews):
        triangulate_point_light([[960, 720]], [[0, 0, 600]], 25.0, K)
    # highlights at each sphere's image centre: rays reflect straight back to the camera,
    # all meeting at the camera centre -> fine; two identical spheres -> parallel rays
    with pytest.raises(DegenerateFit):
        triangulate_point_light([[959.5, 719.5], [959.5, 719.5]], [[0, 0, 600], [0, 0, 600]], 25.0, K)


def test_collinear_spheres_lensch_eq5():
    rng = np.random.default_rng(4)
    p0, d = np.array([-120.0, 30.0, 650.0]), np.array([48.0, -5.0, 12.0])
    d = d / np.linalg.norm(d) * 50.0
    centres = p0 + np.arange(6)[:, None] * d
    img, mask = render_spheres(centres, 12.0, flash=True, rng=rng)
    n, labels = cv2.connectedComponents(mask.astype(np.uint8))
    hls = []
    for C in centres:
        uv = (K @ C)[:2] / C[2]
        blob = labels == labels[int(round(uv[1])), int(round(uv[0]))]
        hls.append(find_highlight(np.where(blob, img, 0), detect_sphere(blob), saturation=1.0).xy_px)
    est = locate_collinear_spheres(np.array(hls), 50.0, K)
    assert np.abs(est - centres).max() < 0.01 * 650


def test_positioner_model_recovers_kinematics():
    rng = np.random.default_rng(2)
    truth = dict(c=np.array([3.0, -2.0, 40.0]), r=800.0, ao=2.5, eo=-1.2)
    az = np.repeat(np.arange(0, 360, 30.0), 3)
    el = np.tile([10.0, 35.0, 60.0], 12)
    a, e = np.radians(az + truth["ao"]), np.radians(el + truth["eo"])
    X = truth["c"] + truth["r"] * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)
    X_meas = X + rng.normal(0, 1.0, X.shape)
    m = fit_positioner_model(az, el, X_meas)
    assert abs(m.radius_mm - truth["r"]) < 1.0
    assert abs(m.azimuth_offset_deg - truth["ao"]) < 0.1 and abs(m.elevation_offset_deg - truth["eo"]) < 0.1
    assert np.linalg.norm(m.centre_mm - truth["c"]) < 2.0
    assert 0.7 < m.rms_mm / np.sqrt(3) < 1.3  # residual matches the 1 mm per-axis noise
    # a pose never measured gets its position from the model
    assert np.linalg.norm(m.position(45.0, 20.0) - (truth["c"] + truth["r"] * np.array(
        [np.cos(np.radians(18.8)) * np.cos(np.radians(47.5)), np.cos(np.radians(18.8)) * np.sin(np.radians(47.5)),
         np.sin(np.radians(18.8))]))) < 3.0
    assert 1 <= m.fit_status <= 4 and m.fit_message  # converged, with scipy's reason
    with pytest.raises(NotConverged, match="positioner arm fit did not converge"):
        fit_positioner_model(az, el, X_meas, max_evaluations=2)
    with pytest.raises(TooFewViews):
        fit_positioner_model(az[:2], el[:2], X[:2])
    with pytest.raises(ValueError, match="positions_mm"):
        fit_positioner_model(az, el, X[:5])


def _arm_rays(seed: int, *, outlier: bool = False):
    """Rays towards 8 lights of a known arm from a 3-ball row turned to 4 turntable angles
    (0.5 deg of direction noise per axis), the lights' triangulated positions and the truth."""
    rng = np.random.default_rng(seed)
    c, r, ao, eo = np.array([4.0, -6.0, 12.0]), 480.0, 1.5, -0.8
    az, el = np.repeat([-60.0, -20, 20, 60], 2), np.tile([25.0, 55.0], 4)
    a, e = np.radians(az + ao), np.radians(el + eo)
    L = c + r * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)
    row = np.array([[-120.0, y, 110.0] for y in (-90, 0, 90)])
    P0 = np.concatenate([row @ np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]]).T
                         for t in np.radians([0, 30, 150, 180])])
    P = P0[None] + rng.normal(0, 5, (len(az), len(P0), 3))   # reflection points on the balls
    D = (L[:, None] - P) / np.linalg.norm(L[:, None] - P, axis=2, keepdims=True)
    D += rng.normal(0, np.radians(0.5), D.shape)
    if outlier:  # a wrongly picked highlight: its ray 10 deg off
        D[0, 0] += np.radians(10.0) * np.array([0.0, 0.0, 1.0])
    D /= np.linalg.norm(D, axis=2, keepdims=True)
    X = np.array([closest_point_to_lines(P[i], D[i])[0] for i in range(len(az))])
    rays = (P.reshape(-1, 3), D.reshape(-1, 3), np.repeat(np.arange(len(az)), len(P0)))
    return az, el, X, rays, L


@pytest.mark.parametrize("outlier", [False, True])
def test_positioner_fit_to_the_rays_beats_triangulated_points(outlier):
    """Each light's depth is poorly determined along its rays; fitting the arm to the rays
    themselves (robustly) weighs each by what it measures. Six noise draws: the ray fit's worst
    light within 1 % of its distance in every draw (seen: 0.85 % worst of 20 draws, 2.3 % for the
    point fit with an outlier), and better than the point fit's worst in the median draw."""
    worst = []
    for seed in range(6):
        az, el, X, rays, L = _arm_rays(seed, outlier=outlier)
        fits = [fit_positioner_model(az, el, X), fit_positioner_model(az, el, X, rays=rays)]
        worst.append([np.max(np.linalg.norm(m.position(az, el) - L, axis=1) / np.linalg.norm(L, axis=1))
                      for m in fits])
        assert np.isnan(fits[0].ray_rms_deg) and 0.5 < fits[1].ray_rms_deg < (1.5 if outlier else 0.9)
    worst = np.array(worst)
    assert worst[:, 1].max() < 0.01
    assert np.median(worst[:, 1]) < np.median(worst[:, 0])


def test_ray_weights_are_the_cosine_between_normal_and_camera():
    """A mirror ball at the origin, the camera 1 m up +z: a reflection point at polar angle t
    has normal n = its position / r, so the weight is cos of n's angle to the camera ray."""
    t = np.radians([0.0, 30.0, 60.0, 80.0])
    n = np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], 1)
    P, C = 25.0 * n, np.array([0.0, 0.0, 1000.0])
    v = (C - P) / np.linalg.norm(C - P, axis=1, keepdims=True)
    D = 2 * np.sum(n * v, axis=1, keepdims=True) * n - v
    np.testing.assert_allclose(ray_weights(P, D, C), np.sum(n * v, axis=1), atol=1e-12)
    assert np.all(np.diff(ray_weights(P, D, C)) < 0)   # towards the limb: less certain rays


def test_positioner_rays_are_validated():
    az, el, X, (P, D, pose), _ = _arm_rays(0)
    with pytest.raises(ValueError, match="rays"):
        fit_positioner_model(az, el, X, rays=(P, D[:-1], pose))
    with pytest.raises(ValueError, match="pose index"):
        fit_positioner_model(az, el, X, rays=(P, D, pose + 1))
    with pytest.raises(ValueError, match="rays must be"):
        fit_positioner_model(az, el, X, rays=(P, D))
    with pytest.raises(ValueError, match="weight must be > 0"):
        fit_positioner_model(az, el, X, rays=(P, D, pose, np.zeros(len(P))))


def test_no_sphere_no_highlight_errors_name_frame():
    with pytest.raises(TargetNotFound, match="img7"):
        detect_sphere(np.zeros((50, 50)), frame="img7")
    with pytest.raises(TargetNotFound, match="img8"):
        find_highlight(np.zeros((50, 50)), frame="img8")


@pytest.mark.realdata
def test_uw_chrome_sphere_light_directions(shared_data):
    root = shared_data / "uw-photometric-stereo"
    from PIL import Image  # OpenCV 5 wheels do not read TGA
    mask = np.asarray(Image.open(root / "chrome" / "chrome.mask.tga"))
    sph = detect_sphere(mask)
    ref = np.loadtxt(root / "lights.txt", skiprows=1)
    dirs = []
    for i in range(12):
        img = np.asarray(Image.open(root / "chrome" / f"chrome.{i}.tga"))
        dirs.append(light_direction_orthographic(find_highlight(img, sph, frame=f"chrome.{i}").xy_px, sph))
    dirs = np.array(dirs)
    # lights.txt uses x right, y up, z towards the viewer; ours is OpenCV (y down, z forward)
    ours = dirs * np.array([1, -1, -1])
    ang = _angle_deg(ours, ref)
    print(f"UW chrome: angular difference to lights.txt mean {ang.mean():.2f}°, max {ang.max():.2f}°")
    # the course reference itself differs from an independent re-derivation by 3° mean, 8° worst
    assert ang.mean() < 4.0 and ang.max() < 10.0
    # the same in one call, as a new user would make it
    from calibration.spheres import light_directions_from_sphere
    imgs = [np.asarray(Image.open(root / "chrome" / f"chrome.{i}.tga")) for i in range(12)]
    one = light_directions_from_sphere(imgs, mask, names=[f"chrome.{i}" for i in range(12)])
    np.testing.assert_allclose(one.directions, dirs, atol=1e-12)


def test_point_light_covariance_includes_centre_noise():
    """With sphere-centre noise stated, the covariance grows to match the actual scatter of the
    triangulated light under random centre errors (Monte Carlo, exact highlights)."""
    R = 12.7
    centres = np.array([-100.0, 20.0, 700.0]) + np.arange(5)[:, None] * np.array([40.0, -3.0, 8.0])
    light = np.array([150.0, -450.0, 300.0])
    unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)  # noqa: E731
    n = unit(unit(light - centres) + unit(-centres))
    for _ in range(100):  # normal bisecting the directions to light and camera (fixed point)
        X = centres + R * n
        n = unit(unit(light - X) + unit(-X))
    X = centres + R * n
    hl = (X @ K.T)[:, :2] / X[:, 2:]
    exact = triangulate_point_light(hl, centres, R, K, sigma_px=0.01)
    assert np.linalg.norm(exact.position_mm - light) < 1e-3
    s = 0.05
    pl = triangulate_point_light(hl, centres, R, K, sigma_px=0.01, sigma_center_mm=s)
    assert np.trace(pl.covariance_mm2) > 10 * np.trace(exact.covariance_mm2)
    rng = np.random.default_rng(9)
    errs = np.array([triangulate_point_light(hl, centres + rng.normal(0, s, centres.shape), R, K).position_mm - light
                     for _ in range(300)])
    # Monte Carlo scatter vs the linearised covariance: total variance within 30 %
    assert 0.7 < np.trace(np.cov(errs.T)) / np.trace(pl.covariance_mm2) < 1.3


def _dim_mirror_ball(rng, centre=(150.3, 120.7), radius=60.0, size=(300, 260), ss=4):
    """A dim mirror ball (reflected room ~0.08) with dark reflections as holes, a highlight 600x
    brighter, on a darker noisy background; the disc is supersampled ``ss`` x ``ss``."""
    w, h = size
    yy, xx = (np.indices((h * ss, w * ss)) + 0.5) / ss - 0.5
    inside = (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 < radius ** 2
    img = np.where(inside, 0.08, 0.01).reshape(h, ss, w, ss).mean(axis=(1, 3))
    for _ in range(8):  # dark reflections: holes well inside the disc
        r, a = rng.uniform(0, 0.7) * radius, rng.uniform(0, 2 * np.pi)
        cx, cy = centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)
        img[(np.indices((h, w))[1] - cx) ** 2 + (np.indices((h, w))[0] - cy) ** 2 < (0.15 * radius) ** 2] = 0.002
    hx, hy = centre[0] - 0.3 * radius, centre[1] - 0.2 * radius
    img[(np.indices((h, w))[1] - hx) ** 2 + (np.indices((h, w))[0] - hy) ** 2 < 9] = 50.0
    return img + rng.normal(0, 0.002, img.shape)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_dim_mirror_ball_centre_from_its_outline(seed):
    rng = np.random.default_rng(seed)
    centre, radius = np.array([150.3 + seed, 120.7 - seed]), 55.0 + 3 * seed
    img = _dim_mirror_ball(rng, centre, radius)
    sph = detect_sphere(img)  # default threshold: the highlight is 600x the ball
    assert np.linalg.norm(sph.center_px - centre) < 0.3
    assert abs(sph.radius_px - radius) < 0.5
    # a user-given threshold inside the ball's range: the holes do not move the centre
    sph = detect_sphere(img, threshold=0.04)
    assert np.linalg.norm(sph.center_px - centre) < 0.3


def test_a_blob_that_is_not_a_sphere_is_refused():
    img = np.zeros((200, 200))
    img[40:160, 60:90] = 1.0  # a bar: axis ratio 0.25
    with pytest.raises(TargetNotFound, match="bar.png: .*not a credible sphere.*axis ratio"):
        detect_sphere(img, frame="bar.png")
    img = np.zeros((200, 200))
    img[:, :100] = 1.0  # background half: open to the border
    with pytest.raises(TargetNotFound, match="touches the image border"):
        detect_sphere(img)


@pytest.mark.realdata
def test_uw_chrome_photo_without_mask_is_found_or_refused(shared_data):
    """On a real, dim mirror-sphere photo (no mask) the sphere is either found where its mask
    says, or refused with the reason: never a centre tens of pixels off without an error."""
    from PIL import Image
    root = shared_data / "uw-photometric-stereo" / "chrome"
    truth = detect_sphere(np.asarray(Image.open(root / "chrome.mask.tga")))
    for i in range(12):
        img = np.asarray(Image.open(root / f"chrome.{i}.tga")).astype(np.float32)
        for threshold in (None, 2.0, 8.0):
            try:
                sph = detect_sphere(img, threshold=threshold, frame=f"chrome.{i}")
            except TargetNotFound as exc:
                assert f"chrome.{i}" in str(exc)
                continue
            assert np.linalg.norm(sph.center_px - truth.center_px) < 2.0, (i, threshold, sph.center_px)
