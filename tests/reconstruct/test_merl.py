"""MERL binary format: a synthetic file written here byte by byte (no MERL data is shipped)."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.brdf import CookTorrance, TabulatedIsotropic
from reconstruct.coords import from_halfway_difference, halfway_difference
from reconstruct.merl import MERL_SCALE, MERL_SHAPE, read_merl, write_merl

DIMS = (6, 5, 8)  # small stand-in for MERL's (90, 90, 180)


def write_by_hand(path, raw: np.ndarray) -> None:
    """Header of three little-endian int32 counts, then R, G, B blocks of float64 values with
    index phi_d + theta_d * n_phi_d + theta_h * n_phi_d * n_theta_d (as BRDFRead.cpp)."""
    n_h, n_d, n_p = raw.shape[1:]
    flat = np.empty(3 * n_h * n_d * n_p)
    for c in range(3):
        for i in range(n_h):
            for j in range(n_d):
                for k in range(n_p):
                    flat[c * n_h * n_d * n_p + k + j * n_p + i * n_p * n_d] = raw[c, i, j, k]
    with open(path, "wb") as fh:
        fh.write(np.array([n_h, n_d, n_p], "<i4").tobytes())
        fh.write(flat.astype("<f8").tobytes())


@pytest.fixture
def raw():
    rng = np.random.default_rng(31)
    values = rng.uniform(0.0, 3000.0, (3,) + DIMS)
    values[0, 5, 4, 2] = -1.0  # invalid entries, one per channel
    values[1, 0, 0, 0] = -1.0
    values[2, 3, 4, 7] = -1.0
    return values


def test_read_scales_and_orders_channels(tmp_path, raw):
    path = tmp_path / "synthetic.binary"
    write_by_hand(path, raw)
    model = read_merl(path)
    assert isinstance(model, TabulatedIsotropic)
    assert model.shape == DIMS and model.theta_h_warp == "sqrt"
    expected = np.moveaxis(raw, 0, -1) * [1 / 1500, 1.15 / 1500, 1.66 / 1500]
    expected[expected < 0] = np.nan
    np.testing.assert_array_equal(np.isnan(model.table), np.isnan(expected))
    np.testing.assert_allclose(model.table, expected, rtol=1e-15)


def test_write_then_read_round_trip(tmp_path, raw):
    path = tmp_path / "a.binary"
    write_by_hand(path, raw)
    model = read_merl(path)
    again = tmp_path / "b.binary"
    write_merl(again, model)
    a, b = path.read_bytes(), again.read_bytes()
    assert len(a) == len(b) and a[:12] == b[:12]
    # scaling and unscaling may move the last bit; invalid entries are -1 in both
    np.testing.assert_allclose(np.frombuffer(b[12:], "<f8"), np.frombuffer(a[12:], "<f8"),
                               rtol=1e-15)
    np.testing.assert_array_equal(read_merl(again).table, model.table)


def test_tabulated_model_round_trip(tmp_path):
    model = TabulatedIsotropic.from_brdf(CookTorrance(0.3, 0.5, 0.2), DIMS)
    path = tmp_path / "ct.binary"
    write_merl(path, model)
    back = read_merl(path)
    assert path.stat().st_size == 12 + 3 * 8 * int(np.prod(DIMS))
    np.testing.assert_array_equal(np.isnan(back.table), np.isnan(model.table))
    np.testing.assert_allclose(back.table, model.table, rtol=1e-14)


def merl_bin(theta_h, theta_d, phi_d, dims):
    """Nearest-bin lookup of BRDFRead.cpp (lower bin, clamped), generalised to ``dims``."""
    n_h, n_d, n_p = dims
    i = np.clip(np.floor(np.sqrt(theta_h / (np.pi / 2)) * n_h), 0, n_h - 1)
    j = np.clip(np.floor(theta_d / (np.pi / 2) * n_d), 0, n_d - 1)
    k = np.clip(np.floor(np.where(phi_d < 0, phi_d + np.pi, phi_d) / np.pi * n_p), 0, n_p - 1)
    return i.astype(int), j.astype(int), k.astype(int)


def test_nodes_sit_where_merl_bins_start(tmp_path, raw):
    """Just above each node our trilinear value equals the MERL lower-bin lookup."""
    path = tmp_path / "synthetic.binary"
    write_by_hand(path, np.abs(raw))
    model = read_merl(path)
    th, td, pd = (a.ravel() for a in np.meshgrid(*model.node_angles(), indexing="ij"))
    keep = (th > 0) & (td > 0) & (th + td < np.pi / 2 - 0.05)
    wi, wo = from_halfway_difference(th[keep] + 1e-9, 0.0, td[keep] + 1e-9, pd[keep] + 1e-9)
    a_th, _, a_td, a_pd = halfway_difference(wi, wo)
    i, j, k = merl_bin(a_th, a_td, a_pd, DIMS)
    # neighbouring random nodes differ by O(1); the 1e-9 rad offsets move values by < 1e-4
    np.testing.assert_allclose(model.evaluate(wi, wo), model.table[i, j, k], rtol=1e-4)


def test_merl_constants():
    assert MERL_SHAPE == (90, 90, 180)
    np.testing.assert_allclose(MERL_SCALE, [1 / 1500, 1.15 / 1500, 1.66 / 1500])


def test_malformed_files_raise(tmp_path):
    short = tmp_path / "short.binary"
    short.write_bytes(b"\x00" * 8)
    with pytest.raises(ValueError, match="too short for a MERL header"):
        read_merl(short)
    truncated = tmp_path / "truncated.binary"
    truncated.write_bytes(np.array(DIMS, "<i4").tobytes() + b"\x00" * 64)
    with pytest.raises(ValueError, match=r"header \(6, 5, 8\) needs 5772 bytes, file has 76"):
        read_merl(truncated)
    bad = tmp_path / "bad.binary"
    bad.write_bytes(np.array([0, 5, 8], "<i4").tobytes())
    with pytest.raises(ValueError, match="non-positive node counts"):
        read_merl(bad)


def test_write_needs_the_merl_layout(tmp_path):
    with pytest.raises(ValueError, match="theta_h_warp='sqrt'"):
        write_merl(tmp_path / "x.binary", TabulatedIsotropic(np.ones((2, 2, 2, 3)), "linear"))
