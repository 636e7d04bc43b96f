"""capture/preview.py against DNGs with known content (written by sims.dng, decoded by rawpy)."""
from __future__ import annotations

import numpy as np
import pytest

from capture.preview import (PreviewError, bin_cfa, decode_dng, downscale, fit_cells,
                             half_block_segments, image_histogram, make_preview, raw_histogram,
                             to_display)
from sims.dng import write_dng

BLACK, WHITE = 64, 4095


def _mosaic_from_rgb(rgb_dn: np.ndarray, pattern: str) -> np.ndarray:
    """Build a CFA from a per-tile RGB image in DN: shape (h, w, 3) -> (2h, 2w)."""
    h, w, _ = rgb_dn.shape
    cfa = np.zeros((2 * h, 2 * w), dtype=np.uint16)
    for k, c in enumerate(pattern):
        cfa[k // 2::2, k % 2::2] = rgb_dn[..., "RGB".index(c)]
    return cfa


@pytest.mark.parametrize("pattern", ["RGGB", "GRBG", "BGGR", "GBRG"])
def test_decode_and_bin_recover_tile_colours(pattern):
    rng = np.random.default_rng(1)
    rgb = rng.integers(BLACK, WHITE + 1, size=(40, 60, 3)).astype(np.uint16)
    dng = write_dng(_mosaic_from_rgb(rgb, pattern), cfa_pattern=pattern, black_level=BLACK,
                    white_level=WHITE)
    mosaic = decode_dng(dng)
    assert mosaic.cfa == pattern
    assert mosaic.white_level == WHITE
    assert np.all(mosaic.black_level_cfa == BLACK)
    binned = bin_cfa(mosaic)
    expected = (rgb - BLACK) / (WHITE - BLACK)
    assert binned.shape == (40, 60, 3) and binned.dtype == np.float32
    np.testing.assert_allclose(binned, expected, atol=1e-6)


def test_bin_averages_the_two_greens():
    cfa = np.full((80, 80), 1000, dtype=np.uint16)
    cfa[0::2, 1::2] = 2000  # RGGB: G at (0, 1)
    cfa[1::2, 0::2] = 3000  # and at (1, 0)
    mosaic = decode_dng(write_dng(cfa, black_level=0, white_level=4000))
    g = bin_cfa(mosaic)[..., 1]
    np.testing.assert_allclose(g, 2500 / 4000, atol=1e-6)


def test_histogram_clipping_fractions_are_exact():
    rng = np.random.default_rng(2)
    # everything else stays below 95 % of the range (the default clipping threshold)
    rgb = rng.integers(BLACK + 1, 3800, size=(50, 50, 3)).astype(np.uint16)
    rgb[:10, :, 0] = WHITE          # 20 % of R saturated
    rgb[:, :5, 2] = BLACK           # 10 % of B at black
    mosaic = decode_dng(write_dng(_mosaic_from_rgb(rgb, "RGGB"), black_level=BLACK,
                                  white_level=WHITE))
    hist = raw_histogram(mosaic, bins=32)
    np.testing.assert_allclose(hist.clipped_white_pct, [20.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(hist.clipped_black_pct, [0.0, 0.0, 10.0], atol=1e-9)
    # every pixel counted once; greens count twice per tile
    np.testing.assert_array_equal(hist.counts.sum(axis=1), [2500, 5000, 2500])
    assert hist.edges[0] == BLACK and hist.edges[-1] == WHITE
    # the saturated R pixels land in the top bin
    assert hist.counts[0, -1] >= 500
    warn = hist.warnings(threshold_pct=1.0)
    assert warn == ["R 20.0% clipped white", "B 10.0% crushed black"]


def test_histogram_counts_saturation_below_the_white_level():
    # full well reached near 15400 DN although the file says WhiteLevel 15871 (as in SimCam)
    rng = np.random.default_rng(4)
    cfa = rng.integers(1000, 14000, size=(40, 40)).astype(np.uint16)
    cfa[:8] = rng.integers(15150, 15650, size=(8, 40))   # 20 % saturated, noisy
    mosaic = decode_dng(write_dng(cfa, black_level=512, white_level=15871))
    hist = raw_histogram(mosaic)
    np.testing.assert_allclose(hist.clipped_white_pct, 20.0)
    assert hist.white == pytest.approx(512 + 0.95 * (15871 - 512))
    strict = raw_histogram(mosaic, white_fraction=1.0)
    np.testing.assert_allclose(strict.clipped_white_pct, 0.0)
    with pytest.raises(PreviewError, match="white_fraction"):
        raw_histogram(mosaic, white_fraction=0)


def test_histogram_counts_match_numpy():
    rng = np.random.default_rng(3)
    cfa = rng.integers(0, 1024, size=(64, 96)).astype(np.uint16)
    mosaic = decode_dng(write_dng(cfa, black_level=0, white_level=1023))
    hist = raw_histogram(mosaic, bins=16)
    r = cfa[0::2, 0::2].ravel()
    ref, _ = np.histogram(r, bins=16, range=(0, 1023))
    # np.histogram closes the last bin; ours puts 1023 in the last bin as well
    np.testing.assert_array_equal(hist.counts[0], ref)


def test_image_histogram_and_preview_of_linear_image():
    img = np.zeros((20, 30, 3), dtype=np.float32)
    img[:, :15] = 1.0
    hist = image_histogram(img, bins=8)
    np.testing.assert_allclose(hist.clipped_white_pct, 50.0)
    np.testing.assert_allclose(hist.clipped_black_pct, 50.0)
    p = make_preview(img)
    lines = p.render(30, 10)
    assert len(lines) == 10
    assert sum(len(s.text) for s in lines[0]) == 30


def test_fit_cells_keeps_aspect():
    # 400 x 600 image into 80 x 24 cells: height limits (48 px rows) -> 72 cols x 24 rows
    assert fit_cells((400, 600), 80, 24) == (72, 24)
    # wide image: width limits
    assert fit_cells((100, 800), 80, 24) == (80, 5)
    with pytest.raises(PreviewError, match="cols and rows"):
        fit_cells((10, 10), 0, 5)


def test_downscale_area_average():
    img = np.zeros((8, 8, 3), dtype=np.float32)
    img[:4] = 1.0
    out = downscale(img, 4, 1)  # -> 2 pixel rows, 4 cols
    assert out.shape == (2, 4, 3)
    np.testing.assert_allclose(out[0], 1.0)
    np.testing.assert_allclose(out[1], 0.0)


def test_to_display_srgb_curve():
    out = to_display(np.array([[0.0, 0.18, 1.0]]).repeat(3, axis=0).T[None])
    # sRGB(0.18) = 0.4614 -> 118
    np.testing.assert_array_equal(out[0, :, 0], [0, 118, 255])
    np.testing.assert_array_equal(to_display(np.full((1, 1, 3), 0.5), gain=4.0), 255)
    with pytest.raises(PreviewError, match="gain"):
        to_display(np.zeros((1, 1, 3)), gain=0)


def test_half_blocks_carry_upper_and_lower_pixels():
    rgb8 = np.zeros((4, 3, 3), dtype=np.uint8)
    rgb8[0] = (255, 0, 0)      # row 0 top: red
    rgb8[1] = (0, 0, 255)      # row 0 bottom: blue
    rgb8[2, 0] = (0, 255, 0)   # row 1 first cell top: green, rest black
    lines = half_block_segments(rgb8)
    assert len(lines) == 2
    assert len(lines[0]) == 1 and lines[0][0].text == "▀▀▀"  # one run
    st = lines[0][0].style
    assert st.color.triplet.hex == "#ff0000" and st.bgcolor.triplet.hex == "#0000ff"
    assert [s.text for s in lines[1]] == ["▀", "▀▀"]
    assert lines[1][0].style.color.triplet.hex == "#00ff00"
    # odd height: padded with black
    odd = half_block_segments(rgb8[:3])
    assert odd[1][0].style.bgcolor.triplet.hex == "#000000"


def test_sparklines_width_and_shape():
    hist = image_histogram(np.linspace(0, 0.999, 300, dtype=np.float32).reshape(10, 10, 3), bins=8)
    rows = hist.sparklines(20)
    assert len(rows) == 3 and all(len(r) == 20 for r in rows)
    narrow = hist.sparklines(4)
    assert all(len(r) == 4 for r in narrow)
    # uniform data: every column full height
    assert set(narrow[0]) == {"█"}


def test_bad_input_is_named():
    with pytest.raises(PreviewError, match="not a raw file"):
        decode_dng(b"not a dng at all" * 100)
    with pytest.raises(PreviewError, match="empty"):
        decode_dng(b"")
    with pytest.raises(PreviewError, match=r"source must have shape \(H, W, 3\)"):
        make_preview(np.zeros((4, 4)))
    with pytest.raises(PreviewError, match="float image"):
        make_preview(np.zeros((4, 4, 3), dtype=np.uint8))
    with pytest.raises(PreviewError, match="rgb8"):
        half_block_segments(np.zeros((4, 4, 3), dtype=np.float32))
