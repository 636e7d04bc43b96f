"""Sensor model: noise statistics against the model's own stated bounds, saturation, CFA, vignetting,
and the DNG round trip through rawpy."""
from __future__ import annotations

import io

import numpy as np
import pytest
import rawpy

from sims.sensor import CFA_PATTERNS, SensorModel


def _ramp(h: int, w: int, top: float) -> np.ndarray:
    """Radiance image: a horizontal ramp 0..top with different levels per channel."""
    x = np.linspace(0.0, top, w, dtype=np.float32)
    img = np.broadcast_to(x, (h, w))[..., None] * np.array([0.8, 1.0, 1.3], np.float32)
    return np.ascontiguousarray(img)


def test_photon_transfer_gives_the_stated_gain_and_read_noise():
    """EMVA 1288's photon-transfer method, which needs nothing of the model but two frames: on
    flat patches the temporal variance var(A - B) / 2 grows with the mean signal above black as
    ``mu / K + (read_e / K)^2 + 1/12`` (shot noise, read noise, 1 DN quantisation), K the gain in
    electrons per DN. The line fitted through 16 levels from ~20 e- (the Poisson regime) to ~45
    ke- must give the gain and read noise the sensor states: slope within 2 %, intercept within
    0.15 DN^2 (five frame pairs, seeds 1-10: slope -0.8..+0.2 %, intercept -0.05..+0.05 DN^2
    from the stated 1.05)."""
    s = SensorModel.full_frame(vignetting="none")
    levels = np.geomspace(0.001, 2.0, 16)          # radiance at 1/100 s: ~20 e- to ~45 ke-
    patch = 112
    rad = np.repeat(levels, patch).astype(np.float32)[None, :, None] * np.ones((patch, 1, 3), np.float32)
    a = s.expose(rad, 0.01, 100, np.random.default_rng(1)).astype(float)
    b = s.expose(rad, 0.01, 100, np.random.default_rng(2)).astype(float)
    green = s.cfa_channels(*a.shape) == 1
    mu, var = [], []
    for k in range(len(levels)):
        sel = green[:, k * patch:(k + 1) * patch]
        pa, pb = a[:, k * patch:(k + 1) * patch][sel], b[:, k * patch:(k + 1) * patch][sel]
        if max(pa.max(), pb.max()) >= s.white_level:   # clipped: off the line
            continue
        mu.append((pa.mean() + pb.mean()) / 2 - s.black_level)
        var.append(np.var(pa - pb) / 2)
    assert len(mu) >= 12 and min(mu) * s.e_per_dn(100) < 100   # both regimes are on the line
    var = np.array(var)
    slope, intercept = np.polyfit(mu, var, 1, w=1 / var)   # each level to its relative error
    K = s.e_per_dn(100)
    assert slope == pytest.approx(1 / K, rel=0.02)
    assert intercept == pytest.approx((s.read_noise_e / K) ** 2 + 1 / 12, abs=0.15)


def test_seeded_noise_is_reproducible():
    s = SensorModel.compact()
    rad = _ramp(16, 24, 1.0)
    a = s.expose(rad, 0.01, 200, 7)
    b = s.expose(rad, 0.01, 200, np.random.default_rng(7))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, s.expose(rad, 0.01, 200, 8))


def test_read_noise_and_dark_current():
    s = SensorModel.full_frame(vignetting="none", dark_current_e_s=50.0, read_noise_e=4.0)
    dark = np.zeros((256, 256, 3), np.float32)
    g = 1 / s.e_per_dn(800)  # high ISO so single electrons are visible in DN
    rng = np.random.default_rng(3)
    short = s.expose(dark, 1e-4, 800, rng).astype(float)
    # read noise (+ quantisation) only: dark signal 0.005 e-
    sigma = np.sqrt((4.0 * g) ** 2 + 1 / 12)
    assert short.std() == pytest.approx(sigma, rel=0.03)
    assert short.mean() - s.black_level == pytest.approx(50 * 1e-4 * g, abs=5 * sigma / 256)
    # dark signal grows linearly with exposure: 4 s -> 200 e-, 8 s -> 400 e-
    m4 = s.expose(dark, 4.0, 800, rng).astype(float).mean() - s.black_level
    m8 = s.expose(dark, 8.0, 800, rng).astype(float).mean() - s.black_level
    assert m4 == pytest.approx(200 * g, rel=0.01)
    assert m8 / m4 == pytest.approx(2.0, rel=0.01)


def test_iso_is_an_analogue_gain():
    s = SensorModel.full_frame(vignetting="none")
    rad = np.full((64, 64, 3), 0.1, np.float32)
    rng = np.random.default_rng(5)
    d100 = s.expose(rad, 0.01, 100, rng).astype(float) - s.black_level
    d400 = s.expose(rad, 0.01, 400, rng).astype(float) - s.black_level
    assert d400.mean() / d100.mean() == pytest.approx(4.0, rel=0.01)


@pytest.mark.parametrize("iso", [100, 400])
def test_saturation_reads_exactly_the_white_level(iso):
    s = SensorModel.full_frame(vignetting="none")
    rad = np.full((32, 32, 3), 50.0, np.float32)  # ~50x full well
    raw = s.expose(rad, 0.01, iso, np.random.default_rng(0))
    assert s.saturation_dn(iso) == s.white_level
    assert np.all(raw == s.white_level)


def test_below_base_iso_the_full_well_clips_first():
    s = SensorModel.full_frame(vignetting="none", read_noise_e=0.0)
    rad = np.full((32, 32, 3), 50.0, np.float32)
    raw = s.expose(rad, 0.01, 50, np.random.default_rng(0))
    sat = s.saturation_dn(50)
    assert sat < s.white_level
    # full well 50 ke- at 2 x 2.96 e-/DN: every pixel at the full-well DN (no read noise here)
    assert np.all(raw == sat)
    assert sat == round(50_000 / s.e_per_dn(50) + s.black_level)


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_cfa_pattern_puts_each_colour_on_its_sites(pattern):
    s = SensorModel.compact(cfa_pattern=pattern, vignetting="none", dark_current_e_s=0.0,
                            read_noise_e=0.0)
    rad = np.zeros((32, 48, 3), np.float32)
    rad[..., 0] = 0.5  # pure red scene
    raw = s.expose(rad, 0.01, 100, np.random.default_rng(0)).astype(int) - s.black_level
    red_sites = s.cfa_channels(32, 48) == 0
    assert red_sites.sum() == 32 * 48 // 4
    assert np.all(raw[red_sites] > 100) and np.all(raw[~red_sites] == 0)
    # rawpy agrees on where the red sites are
    with rawpy.imread(io.BytesIO(s.to_dng(s.expose(rad, 0.01, 100, 1)))) as r:
        desc = r.color_desc.decode()
        assert np.array_equal(np.array([desc[c] for c in r.raw_colors.ravel()]).reshape(32, 48) == "R",
                              red_sites)


def test_cos4_vignetting_and_polynomial():
    s = SensorModel.full_frame(vignetting="cos4")
    f = 500.0
    v = s.vignetting_map(101, 201, focal_px=f)
    assert v[50, 100] == 1.0
    theta = np.arctan(np.hypot(100, 50) / f)
    assert v[0, 0] == pytest.approx(np.cos(theta) ** 4, rel=1e-12)
    half = SensorModel.full_frame(vignetting="cos4", vignetting_strength=0.5)
    assert half.vignetting_map(101, 201, focal_px=f)[0, 0] == pytest.approx(1 - 0.5 * (1 - np.cos(theta) ** 4))
    p = SensorModel.compact(vignetting="poly", vignetting_coeffs=(-0.3, 0.1))
    vp = p.vignetting_map(101, 201)
    assert vp[0, 0] == pytest.approx(1 - 0.3 + 0.1) and vp[50, 100] == 1.0
    # a flat field shows the fall-off: corner / centre mean ratio (both red sites)
    flat = np.full((101, 201, 3), 0.5, np.float32)
    mean_e = s.mean_electrons(flat, 0.01, focal_px=f)
    assert mean_e[0, 0] / mean_e[50, 100] == pytest.approx(np.cos(theta) ** 4, rel=1e-9)
    assert (mean_e / v)[0, 1] / (mean_e / v)[0, 0] == pytest.approx(0.50 / 0.38, rel=1e-9)  # QE G / R


def test_fnumber_follows_the_camera_equation():
    s = SensorModel.full_frame(vignetting="none")
    rad = np.full((4, 4, 3), 1.0, np.float32)
    e8 = s.mean_electrons(rad, 0.01, fnumber=8.0)
    e4 = s.mean_electrons(rad, 0.01, fnumber=4.0)
    assert np.allclose(e4 / e8, 4.0)
    # pi / (4 N^2) * QE_G * photon_flux * pitch^2 * t for a green site (RGGB: (0, 1))
    assert e8[0, 1] == pytest.approx(np.pi / 256 * 0.5 * 1e7 * 5.9 ** 2 * 0.01)


def test_dng_round_trip_through_rawpy():
    """scene -> sensor -> DNG -> rawpy -> linear image within the model's noise; clipping at white."""
    s = SensorModel.full_frame()
    h, w, f = 120, 160, 300.0
    rad = _ramp(h, w, 5.0)  # the right part of the ramp saturates at 1/100 s
    exposure, iso, fn = 0.01, 100, 8.0
    raw = s.expose(rad, exposure, iso, np.random.default_rng(11), fnumber=fn, focal_px=f)
    dng = s.to_dng(raw, exposure_s=exposure, iso=iso, fnumber=fn)
    with rawpy.imread(io.BytesIO(dng)) as r:
        got = r.raw_image_visible.copy()
        assert np.array_equal(got, raw)                      # bit-exact
        assert list(r.black_level_per_channel) == [s.black_level] * 4
        assert r.white_level == s.white_level == 16383
        desc = r.color_desc.decode()
        assert "".join(desc[c] for c in r.raw_pattern.ravel()) == "RGGB"
        wb = np.array(r.camera_whitebalance[:3])
        # LibRaw's camera multipliers are 1 / AsShotNeutral
        assert np.allclose(wb / wb[1], [0.50 / 0.38, 1.0, 0.50 / 0.34], rtol=1e-3)
        black = np.array(r.black_level_per_channel)[r.raw_colors]
        white = r.white_level
    # linear image: black-subtracted, white-normalised, then exposure-normalised with the model
    linear = (got.astype(float) - black) / (white - black)
    k = s.e_per_dn(iso) * (white - s.black_level)
    est = (linear * k - s.dark_current_e_s * exposure) / \
        s._electrons_per_radiance((h, w), exposure, fn, f, None)
    exp = s.expected_raw(rad, exposure, iso, fnumber=fn, focal_px=f)
    truth = s.mosaic(rad)
    # noise bound from the model: sigma_DN converted to radiance units, 5 sigma per pixel
    sigma_rad = exp.sigma_dn * s.e_per_dn(iso) / s._electrons_per_radiance((h, w), exposure, fn, f, None)
    ok = ~exp.saturated
    assert ok.sum() > 0.3 * ok.size and (~ok).sum() > 0.2 * ok.size
    assert np.all(np.abs(est - truth)[ok] < 5 * sigma_rad[ok])
    # unbiased as a whole
    zs = ((est - truth) / sigma_rad)[ok]
    assert abs(zs.mean()) < 5 / np.sqrt(zs.size)
    # clipping: pixels the model calls clearly saturated read exactly the white level
    sure = exp.mean_dn - 5 * exp.sigma_dn > s.white_level
    assert sure.sum() > 1000 and np.all(got[sure] == s.white_level)
    assert got.max() == s.white_level
    # raw_to_radiance is the same inverse
    assert np.allclose(s.raw_to_radiance(raw, exposure, iso, fnumber=fn, focal_px=f), est)


def test_dng_white_balance_makes_a_grey_scene_neutral_in_rawpy():
    s = SensorModel.compact(vignetting="none")
    rad = np.full((64, 96, 3), 0.4, np.float32)
    raw = s.expose(rad, 0.01, 100, np.random.default_rng(2))
    with rawpy.imread(io.BytesIO(s.to_dng(raw, exposure_s=0.01, iso=100))) as r:
        rgb = r.postprocess(use_camera_wb=True, output_color=rawpy.ColorSpace.raw, gamma=(1, 1),
                            no_auto_bright=True, output_bps=16, half_size=True)
    m = rgb[4:-4, 4:-4].reshape(-1, 3).mean(axis=0)
    assert m[0] / m[1] == pytest.approx(1.0, abs=0.01) and m[2] / m[1] == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize("bad, match", [
    (np.zeros((4, 4)), "radiance must be a linear"),
    (np.full((4, 4, 3), -1.0), "radiance must be >= 0"),
    (np.full((4, 4, 3), np.nan), "NaN"),
])
def test_bad_radiance_is_named(bad, match):
    with pytest.raises(ValueError, match=match):
        SensorModel.compact().expose(bad, 0.01)


def test_bad_settings_are_named():
    s = SensorModel.compact()
    img = np.zeros((4, 4, 3))
    with pytest.raises(ValueError, match="exposure_s"):
        s.expose(img, 0.0)
    with pytest.raises(ValueError, match="iso"):
        s.expose(img, 0.01, iso=-100)
    with pytest.raises(ValueError, match="focal_px"):
        SensorModel.full_frame().expose(img, 0.01)
    with pytest.raises(ValueError, match="cfa_pattern"):
        SensorModel(cfa_pattern="RGBX")
    with pytest.raises(ValueError, match="quantum_efficiency"):
        SensorModel(quantum_efficiency=(0.5, 0.5))
    with pytest.raises(ValueError, match="black_level"):
        SensorModel(bit_depth=12, black_level=5000)
    with pytest.raises(ValueError, match="white level"):
        s.to_dng(np.full((2, 2), 65535, np.uint16))


def test_dng_colour_matrix_develops_to_the_scene_colours_in_srgb():
    """ColorMatrix1 + AsShotNeutral are consistent: rawpy's camera -> sRGB matrix is the
    identity after white balance, so a developed frame has the simulator's (linear sRGB) colours."""
    s = SensorModel.full_frame(vignetting="none")
    rad = np.broadcast_to(np.array([0.4, 0.1, 0.2], np.float32), (64, 96, 3)).copy()
    with rawpy.imread(io.BytesIO(s.to_dng(s.expose(rad, 0.01, 100, 0)))) as r:
        assert np.allclose(r.color_matrix[:3, :3], np.eye(3), atol=1e-4)
        rgb = r.postprocess(use_camera_wb=True, no_auto_bright=True, gamma=(1, 1), output_bps=16)
    m = rgb[8:-8, 8:-8].reshape(-1, 3).mean(axis=0)
    # shot noise averages out over ~4000 pixels: ratios within 1 %
    assert m[0] / m[1] == pytest.approx(4.0, rel=0.01) and m[2] / m[1] == pytest.approx(2.0, rel=0.01)
