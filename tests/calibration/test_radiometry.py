"""HDR merging (raw and 8-bit), flat field / vignetting, gray card, irradiance normalisation."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.errors import TooFewViews
from calibration.hdr import master_frame, merge_ldr, merge_raw_brackets, recover_response, write_hdr
from calibration.raw import read_raw
from calibration.radiometry import (apply_flat, fit_vignetting, flat_field_gain, gray_card_scale,
                                    normalize_irradiance)

BLACK, WHITE, GAIN, READ = 256.0, 16383.0, 2.0, 3.0  # DN, DN, e-/DN, DN rms
TIMES = np.array([1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4])


def patch_radiance(levels, patch=32):
    """An image of constant patches (DN/s), one level per patch, so patch means can be checked."""
    n = len(levels)
    cols = int(np.ceil(np.sqrt(n)))
    img = np.zeros((cols * patch, cols * patch), np.float64)
    for i, v in enumerate(levels):
        r, c = divmod(i, cols)
        img[r * patch:(r + 1) * patch, c * patch:(c + 1) * patch] = v
    return img


def simulate_raw(X, t, rng, black=BLACK):
    """Raw DN of radiance X (DN/s) for exposure t: Poisson electrons, read noise, 14-bit clip."""
    electrons = rng.poisson(np.maximum(X * t * GAIN, 0))
    dn = electrons / GAIN + rng.normal(0, READ, X.shape) + black
    return np.clip(np.round(dn), 0, WHITE).astype(np.uint16)


def test_raw_merge_within_1_percent_over_unsaturated_range():
    rng = np.random.default_rng(0)
    levels = np.geomspace(400.0, 1.5e7, 40)  # DN/s: 4.5 decades, the top ones clip even at 1/1000 s
    X = patch_radiance(levels)
    frames = [simulate_raw(X, t, rng) for t in TIMES]
    hdr = merge_raw_brackets(frames, TIMES, black_level=BLACK, white_level=WHITE, gain_e_per_dn=GAIN,
                             read_noise_dn=READ)
    assert hdr.radiance.dtype == np.float32 and np.all(np.isfinite(hdr.radiance))
    clip_level = (WHITE - BLACK) * 0.97 / TIMES.min()
    unsat = X < 0.95 * clip_level
    assert not hdr.saturated[unsat].any() and hdr.saturated[X > 1.05 * clip_level].all()
    # every unsaturated patch's mean within 1 % of the truth
    for v in levels[levels < 0.95 * clip_level]:
        sel = X == v
        assert abs(hdr.radiance[sel].mean() / v - 1) < 0.01, v
    # the noise model's sigma describes the actual scatter (normalised residual ~ N(0, 1))
    z = ((hdr.radiance - X) / hdr.sigma)[unsat]
    assert 0.85 < z.std() < 1.15 and abs(z.mean()) < 0.1
    # saturated pixels report a lower bound, never NaN
    assert np.all(hdr.radiance[hdr.saturated] > 0.9 * clip_level)


def test_raw_merge_noise_optimal_beats_single_best_exposure():
    rng = np.random.default_rng(1)
    X = np.full((64, 64), 3000.0)
    frames = [simulate_raw(X, t, rng) for t in TIMES]
    hdr = merge_raw_brackets(frames, TIMES, black_level=BLACK, white_level=WHITE, gain_e_per_dn=GAIN,
                             read_noise_dn=READ)
    best_single = (frames[-1].astype(float) - BLACK) / TIMES[-1]
    assert hdr.radiance.std() < best_single.std()


def test_dark_frame_subtraction_removes_fixed_pattern():
    rng = np.random.default_rng(2)
    X = patch_radiance(np.geomspace(500.0, 5e4, 9))
    hot = np.zeros_like(X)
    hot[rng.integers(0, X.shape[0], 30), rng.integers(0, X.shape[1], 30)] = 400.0  # DN at 1/4 s
    t = TIMES[2:]
    darks = [master_frame([np.clip(simulate_raw(np.zeros_like(X), tk, rng) + hot * tk / 0.25, 0, WHITE)
                           for _ in range(9)]) for tk in t]
    frames = [np.clip(simulate_raw(X, tk, rng) + hot * tk / 0.25, 0, WHITE) for tk in t]
    hdr = merge_raw_brackets(frames, t, white_level=WHITE, gain_e_per_dn=GAIN, read_noise_dn=READ,
                             darks=np.stack(darks))
    hot_px = hot > 0
    naive = merge_raw_brackets(frames, t, black_level=BLACK, white_level=WHITE, gain_e_per_dn=GAIN,
                               read_noise_dn=READ)
    assert np.abs(naive.radiance - X)[hot_px].mean() > 10 * np.abs(hdr.radiance - X)[hot_px].mean() / 3
    assert np.abs(hdr.radiance / X - 1)[hot_px].mean() < 0.05


def test_raw_merge_bad_input():
    f = np.zeros((4, 4), np.uint16)
    with pytest.raises(TooFewViews):
        merge_raw_brackets([], [], white_level=WHITE)
    with pytest.raises(ValueError, match="exposure_s"):
        merge_raw_brackets([f, f], [0.1], white_level=WHITE)
    with pytest.raises(ValueError, match="exposure_s"):
        merge_raw_brackets([f], [0.0], white_level=WHITE)
    with pytest.raises(ValueError, match="black_level"):
        merge_raw_brackets([f], [0.1], black_level=WHITE, white_level=WHITE)


def _ldr_bracket(rng, E, times, gamma=2.2):
    """8-bit images of relative radiance E through a known response code = 255 (E t)^(1/gamma)."""
    imgs = [np.clip(np.round(255 * np.clip(E * t, 0, 1) ** (1 / gamma) + rng.normal(0, 0.5, E.shape)), 0, 255)
            .astype(np.uint8) for t in times]
    codes = np.arange(256) / 255.0
    resp = np.maximum(codes, 0.5 / 255) ** gamma  # exposure E*t that gives each code
    return imgs, resp


def test_ldr_merge_with_true_and_recovered_response():
    rng = np.random.default_rng(3)
    h, w = 64, 96
    E = np.geomspace(0.05, 400.0, w)[None, :, None] * np.array([1.0, 0.8, 0.6]) * np.ones((h, 1, 1))
    times = np.array([1 / 256, 1 / 64, 1 / 16, 1 / 4, 1.0, 4.0])
    imgs, resp = _ldr_bracket(rng, E, times)
    hdr = merge_ldr(imgs, times, np.stack([resp] * 3, 1))
    assert hdr.radiance.shape == E.shape and hdr.radiance.dtype == np.float32
    ok = (E * times.min() < 0.98) & (E * times.max() > 0.02)
    rel = np.abs(hdr.radiance / E - 1)[ok]
    assert np.median(rel) < 0.01 and rel.max() < 0.05
    # recovered response (OpenCV Debevec, defined up to scale): relative radiance within 10 %
    resp_est = recover_response(imgs, times)
    hdr2 = merge_ldr(imgs, times, resp_est)
    ratio = (hdr2.radiance / E)[ok]
    assert np.median(np.abs(ratio / np.median(ratio) - 1)) < 0.10


def test_flat_field_and_vignetting():
    rng = np.random.default_rng(4)
    h, w = 120, 160
    yy, xx = np.indices((h, w))
    rho2 = ((xx - 83.0) ** 2 + (yy - 57.0) ** 2) / (0.5 * np.hypot(h, w)) ** 2
    V = 1 - 0.35 * rho2 + 0.05 * rho2 ** 2
    prnu = 1 + rng.normal(0, 0.01, (h, w))
    flats = np.stack([1000 * V * prnu + rng.normal(0, 2, (h, w)) for _ in range(8)])
    gain = flat_field_gain(flats)
    assert abs(gain.mean() - 1) < 1e-5
    model = fit_vignetting(gain)
    np.testing.assert_allclose(model.center_px, [83.0, 57.0], atol=1.0)
    fitted = model.evaluate((h, w))
    assert np.abs(fitted / fitted.mean() - V / V.mean()).max() < 0.005
    scene = 500 * V * prnu
    flat_scene = apply_flat(scene, gain)
    assert flat_scene.std() / flat_scene.mean() < 0.005
    with pytest.raises(ValueError, match="flats"):
        flat_field_gain(np.ones((4, 4)))


def test_gray_card_and_irradiance_normalisation_give_albedo():
    # a Lambertian plane of albedo 0.5 under a point light: value = k * (rho/pi) * I cos / r^2
    h, w = 50, 60
    yy, xx = np.indices((h, w))
    P = np.stack([xx * 2.0 - 60, yy * 2.0 - 50, np.zeros((h, w))], -1)  # mm, plane z = 0
    N = np.broadcast_to([0.0, 0.0, 1.0], P.shape)
    light = np.array([30.0, -20.0, 400.0])
    d = light - P
    r2 = np.sum(d ** 2, -1)
    cos = d[..., 2] / np.sqrt(r2)
    k_times_I = 7.0e8  # unknown camera gain x light intensity
    img = k_times_I * (0.5 / np.pi) * cos / r2
    # gray card (albedo 0.18) measured at 500 mm, normal incidence
    card = k_times_I * (0.18 / np.pi) / 500.0 ** 2 * (1 + np.random.default_rng(5).normal(0, 0.01, 400))
    gc = gray_card_scale(card, reflectance=0.18, light_distance_mm=500.0)
    fr, valid = normalize_irradiance(img, P, light, normals=N, scale=gc.scale)
    assert valid.all()
    np.testing.assert_allclose(fr * np.pi, 0.5, rtol=3 * gc.scale_std / gc.scale + 1e-4)
    with pytest.raises(ValueError, match="points_mm"):
        normalize_irradiance(img, P[:10], light)


def test_write_hdr_tiff_round_trip(tmp_path):
    import tifffile
    img = np.random.default_rng(6).random((8, 9, 3)).astype(np.float32) * 1e4
    write_hdr(tmp_path / "x.tif", img)
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "x.tif"), img)
    with pytest.raises(ValueError, match="unsupported"):
        write_hdr(tmp_path / "x.png", img)


def test_write_hdr_exr_round_trip_or_clear_error(tmp_path):
    img = np.random.default_rng(7).random((6, 5, 3)).astype(np.float32) * 100
    try:
        import OpenEXR
    except ImportError:  # optional dependency: the error must say what to install
        with pytest.raises(ValueError, match="OpenEXR"):
            write_hdr(tmp_path / "x.exr", img)
        return
    write_hdr(tmp_path / "x.exr", img)
    with OpenEXR.File(str(tmp_path / "x.exr")) as f:
        ch = f.channels()
        back = ch["RGB"].pixels if "RGB" in ch else np.stack([ch[c].pixels for c in "RGB"], -1)
    np.testing.assert_array_equal(back, img)


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["Blackmagic.dng", "RAW_KODAK_DC50.KDC", "picam_test.dng"])
def test_real_raw_files_decode_and_merge(shared_data, name):
    full = read_raw(shared_data / "raw" / name)
    assert full.data.ndim == 2 and full.data.dtype == np.uint16 and len(full.cfa) == 4
    # merge a central crop of at most 1024 x 1024 (even offsets keep the CFA phase): the full
    # 9 MP Blackmagic frame would only add seconds, not coverage
    h, w = full.data.shape
    y0, x0 = (max(h - 1024, 0) // 4) * 2, (max(w - 1024, 0) // 4) * 2
    crop = (slice(y0, y0 + 1024), slice(x0, x0 + 1024))
    raw = type(full)(full.data[crop], full.cfa, full.black_level_cfa, full.white_level)
    # a 2-frame bracket from the real mosaic: the frame itself and a 4x shorter exposure of it
    short = np.round((raw.data.astype(np.float64) - raw.black_level) / 4 + raw.black_level).astype(np.uint16)
    hdr = merge_raw_brackets([raw.data, short], [0.01, 0.0025], black_level=raw.black_level,
                             white_level=raw.white_level)
    assert hdr.radiance.shape == raw.data.shape and np.all(np.isfinite(hdr.radiance))
    lin = (raw.data < raw.black_level + 0.9 * (raw.white_level - raw.black_level)) & (raw.data > raw.black_level + 200)
    ref = (raw.data.astype(np.float64) - raw.black_level) / 0.01
    assert np.median(np.abs(hdr.radiance[lin] / ref[lin] - 1)) < 0.01


def test_ldr_merge_beats_opencv_merge_debevec():
    """The issue's bar: on the same bracket and the same (true) response, our merge (hat weight
    zero at 0 and 255, per-channel weights, clipped exposures blocked) is measurably more accurate
    than cv2.MergeDebevec. Measured log-RMS error 0.0092 vs 0.077 (8x); asserted > 3x."""
    import cv2
    rng = np.random.default_rng(8)
    h, w = 32, 128
    E = (np.geomspace(0.05, 400.0, w)[None, :, None] * np.array([1.0, 0.8, 0.6]) * np.ones((h, 1, 1)))
    times = np.array([1 / 256, 1 / 64, 1 / 16, 1 / 4, 1.0, 4.0], np.float32)
    imgs, resp = _ldr_bracket(rng, E, times)
    resp3 = np.stack([resp] * 3, 1).astype(np.float32)
    ours = merge_ldr(imgs, times, resp3).radiance
    theirs = cv2.createMergeDebevec().process(imgs, times, resp3.reshape(256, 1, 3))
    ok = (E * times.min() < 0.98) & (E * times.max() > 0.02)
    err = lambda a: np.sqrt(np.mean(np.log(np.maximum(a, 1e-12) / E)[ok] ** 2))  # noqa: E731
    assert err(ours) < 0.015  # 8-bit quantisation and 0.5-code noise: ~1 % per sample at best
    assert err(theirs) > 3 * err(ours), (err(ours), err(theirs))
