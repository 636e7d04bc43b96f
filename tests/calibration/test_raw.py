"""calibration.raw: the one raw decoder against DNGs of known content (written by sims.dng)."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.errors import InvalidInput
from calibration.hdr import merge_raw_brackets
from calibration.raw import cfa_channels, demosaic_bilinear, demosaic_smooth_hue, read_raw
from sims.dng import write_dng

BLACKS = (200, 260, 330, 410)  # per 2x2 tile position, DN
WHITE = 15000


@pytest.mark.parametrize("pattern", ["RGGB", "GRBG", "BGGR", "GBRG"])
def test_read_raw_from_bytes_and_path(tmp_path, pattern):
    rng = np.random.default_rng(3)
    data = rng.integers(500, 14000, size=(48, 64)).astype(np.uint16)
    dng = write_dng(data, cfa_pattern=pattern, black_level=BLACKS, white_level=WHITE,
                    exposure_s=1 / 125, iso=400)
    path = tmp_path / "f.dng"
    path.write_bytes(dng)
    for m in (read_raw(dng), read_raw(path)):
        np.testing.assert_array_equal(m.data, data)
        assert m.cfa == pattern and m.white_level == WHITE
        np.testing.assert_array_equal(m.black_level_cfa, np.reshape(BLACKS, (2, 2)))
        # per photosite: the tile repeated, position (y % 2, x % 2)
        yy, xx = np.indices(data.shape)
        np.testing.assert_array_equal(m.black_level, np.asarray(BLACKS)[2 * (yy % 2) + xx % 2])
        assert m.exposure_s == pytest.approx(1 / 125, rel=1e-6) and m.iso == 400
        assert [m.channels[0, 0], m.channels[0, 1], m.channels[1, 0], m.channels[1, 1]] == \
            ["RGB".index(c) for c in pattern]


def test_signal_is_zero_at_each_black_and_one_at_white():
    black = np.tile(np.reshape(BLACKS, (2, 2)), (32, 32))
    m = read_raw(write_dng(black.astype(np.uint16), black_level=BLACKS, white_level=WHITE))
    np.testing.assert_array_equal(m.signal(), 0.0)
    m = read_raw(write_dng(np.full((64, 64), WHITE, np.uint16), black_level=BLACKS, white_level=WHITE))
    np.testing.assert_allclose(m.signal(), 1.0, atol=1e-6)


def test_bad_input_is_named(tmp_path):
    with pytest.raises(InvalidInput, match="empty"):
        read_raw(b"")
    with pytest.raises(InvalidInput, match="shot 7: not a raw file"):
        read_raw(b"JPEG" * 100, name="shot 7")
    with pytest.raises(InvalidInput, match="nothere.dng"):
        read_raw(tmp_path / "nothere.dng")
    with pytest.raises(InvalidInput, match="source must be a path or the bytes"):
        read_raw(12)
    with pytest.raises(InvalidInput, match="cfa must be four letters"):
        cfa_channels("RGBX", (4, 4))
    with pytest.raises(InvalidInput, match="channels must have the mosaic's shape"):
        demosaic_bilinear(np.zeros((4, 4)), np.zeros((4, 6)))


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_bilinear_demosaic_reproduces_a_linear_ramp(pattern):
    """Closed form: bilinear interpolation is exact on a plane; each channel is its own plane."""
    h, w = 20, 30
    yy, xx = np.indices((h, w), dtype=np.float64)
    planes = np.stack([1 + 0.5 * xx + 0.2 * yy, 3 + 0.1 * xx - 0.3 * yy, 7 - 0.25 * xx + 0.4 * yy], -1)
    ch = cfa_channels(pattern, (h, w))
    mosaic = np.take_along_axis(planes, ch[..., None].astype(int), axis=2)[..., 0]
    rgb = demosaic_bilinear(mosaic, ch)
    np.testing.assert_allclose(rgb[2:-2, 2:-2], planes[2:-2, 2:-2], atol=1e-4)


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_smooth_hue_demosaic_gives_a_one_photosite_source_its_surroundings_hue(pattern):
    """A uniform colour comes back exactly; a source seen by one green photosite keeps that
    reading and takes the hue around it (bilinear: green only, and twice its light in green)."""
    hue = np.array([0.8, 1.0, 0.5])
    ch = cfa_channels(pattern, (16, 16))
    mosaic = hue[ch].astype(np.float32)
    np.testing.assert_allclose(demosaic_smooth_hue(mosaic, ch), np.broadcast_to(hue, (16, 16, 3)), rtol=1e-6)
    y, x = 8, (8 if ch[8, 8] == 1 else 9)
    mosaic[y, x] = 1000.0  # a window of the room in one green photosite
    smooth, bilinear = demosaic_smooth_hue(mosaic, ch), demosaic_bilinear(mosaic, ch)
    np.testing.assert_allclose(smooth[y, x], 1000.0 * hue, rtol=1e-5)
    assert bilinear[y, x, 0] < 2 and bilinear[y, x, 2] < 2
    # the source's light per channel over the image: about its own (1000 x hue) with the smooth
    # hue; bilinear interpolation puts twice it in green and none in red and blue
    excess = lambda img: img.reshape(-1, 3).sum(axis=0) - 255 * hue  # noqa: E731 (255 other pixels)
    np.testing.assert_allclose(excess(smooth), 1000.0 * hue, rtol=0.01)
    assert excess(bilinear)[1] > 1900 and np.all(excess(bilinear)[[0, 2]] < 10)


def test_merge_gain_in_either_unit_gives_one_result():
    rng = np.random.default_rng(4)
    t = np.array([0.01, 0.04])
    frames = [np.clip(rng.normal(1000 * k, 30, (16, 16)) + 100, 0, 4095).astype(np.uint16) for k in (1, 4)]
    a = merge_raw_brackets(frames, t, black_level=100, white_level=4095, gain_e_per_dn=4.0, read_noise_dn=2)
    b = merge_raw_brackets(frames, t, black_level=100, white_level=4095, gain_dn_per_e=0.25, read_noise_dn=2)
    np.testing.assert_array_equal(a.radiance, b.radiance)
    np.testing.assert_array_equal(a.sigma, b.sigma)
    # a different gain changes the noise model: the argument is really used
    c = merge_raw_brackets(frames, t, black_level=100, white_level=4095, gain_e_per_dn=0.25, read_noise_dn=2)
    assert not np.allclose(a.sigma, c.sigma)
    with pytest.raises(InvalidInput, match="not both"):
        merge_raw_brackets(frames, t, white_level=4095, gain_e_per_dn=4.0, gain_dn_per_e=0.25)
    with pytest.raises(InvalidInput, match="gain_dn_per_e"):
        merge_raw_brackets(frames, t, white_level=4095, gain_dn_per_e=0)
