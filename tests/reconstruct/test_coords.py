"""BRDF coordinate mappings: round trips, reciprocity, known configurations, bad input."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.coords import (from_halfway_difference, halfway_difference, local_directions,
                                romeiro_st, romeiro_st_inverse, st_from_directions,
                                uvw_from_directions, zickler_uvw, zickler_uvw_inverse)
from reconstruct.frames import linear_rows, normalize, tangent_frames, to_local, to_world


def hemisphere(rng, n):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2])
    return v


def wrap(a):
    """Angle difference folded into (-pi, pi]."""
    return np.angle(np.exp(1j * a))


@pytest.fixture
def pairs():
    rng = np.random.default_rng(7)
    return hemisphere(rng, 20000), hemisphere(rng, 20000)


def test_halfway_difference_round_trip(pairs):
    wi, wo = pairs
    wi2, wo2 = from_halfway_difference(*halfway_difference(wi, wo))
    np.testing.assert_allclose(wi2, wi, atol=1e-12)
    np.testing.assert_allclose(wo2, wo, atol=1e-12)


def test_angles_round_trip_from_angles():
    rng = np.random.default_rng(3)
    n = 5000
    th = rng.uniform(0.01, np.pi / 2 - 0.01, n)
    ph = rng.uniform(-np.pi + 0.01, np.pi - 0.01, n)
    td = rng.uniform(0.01, np.pi / 2 - 0.01, n)
    pd = rng.uniform(-np.pi + 0.01, np.pi - 0.01, n)
    got = halfway_difference(*from_halfway_difference(th, ph, td, pd))
    for a, b in zip(got, (th, ph, td, pd)):
        np.testing.assert_allclose(wrap(a - b), 0.0, atol=1e-10)


def test_swap_is_phi_d_plus_pi(pairs):
    wi, wo = pairs
    a = halfway_difference(wi, wo)
    b = halfway_difference(wo, wi)
    np.testing.assert_allclose(b[0], a[0], atol=1e-12)
    np.testing.assert_allclose(wrap(b[1] - a[1]), 0.0, atol=1e-12)
    np.testing.assert_allclose(b[2], a[2], atol=1e-12)
    np.testing.assert_allclose(wrap(b[3] - a[3] - np.pi), 0.0, atol=1e-10)


def test_mirror_configuration_has_zero_theta_h():
    theta = np.linspace(0.05, 1.5, 20)
    phi = np.linspace(-3.0, 3.0, 20)
    wi = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    wo = wi * [-1, -1, 1]
    th, _, td, _ = halfway_difference(wi, wo)
    np.testing.assert_allclose(th, 0.0, atol=1e-12)
    np.testing.assert_allclose(td, theta, atol=1e-12)


def test_retro_configuration_has_zero_theta_d():
    theta = np.linspace(0.05, 1.5, 20)
    wi = np.stack([np.sin(theta), np.zeros(20), np.cos(theta)], 1)
    th, ph, td, _ = halfway_difference(wi, wi)
    np.testing.assert_allclose(td, 0.0, atol=1e-7)
    np.testing.assert_allclose(th, theta, atol=1e-12)
    np.testing.assert_allclose(ph, 0.0, atol=1e-12)


def test_light_at_normal_splits_the_angle_in_halves():
    theta = np.linspace(0.1, 1.5, 15)
    wi = np.tile([0.0, 0.0, 1.0], (15, 1))
    wo = np.stack([np.zeros(15), np.sin(theta), np.cos(theta)], 1)
    th, ph, td, _ = halfway_difference(wi, wo)
    np.testing.assert_allclose(th, theta / 2, atol=1e-12)
    np.testing.assert_allclose(td, theta / 2, atol=1e-12)
    np.testing.assert_allclose(ph, np.pi / 2, atol=1e-12)


def test_opposite_directions_do_not_produce_nan():
    wi = np.array([[1.0, 0.0, 0.0]])
    out = halfway_difference(wi, -wi)
    assert all(np.isfinite(a).all() for a in out)


def test_zickler_uvw_round_trip_and_ranges():
    rng = np.random.default_rng(11)
    th = rng.uniform(0, np.pi / 2, 4000)
    td = rng.uniform(0, np.pi / 2, 4000)
    pd = rng.uniform(0, np.pi, 4000)
    uvw = zickler_uvw(th, td, pd)
    assert uvw.shape == (4000, 3)
    assert np.all(np.hypot(uvw[:, 0], uvw[:, 1]) <= 1 + 1e-12)
    assert np.all((uvw[:, 2] >= 0) & (uvw[:, 2] <= 1))
    th2, td2, pd2 = zickler_uvw_inverse(uvw)
    np.testing.assert_allclose(th2, th, atol=1e-7)
    np.testing.assert_allclose(td2, td, atol=1e-12)
    # phi_d is recovered modulo pi (the reciprocal pair), compare on the doubled angle
    np.testing.assert_allclose(wrap(2 * (pd2 - pd)), 0.0, atol=1e-7)


def test_zickler_uvw_is_reciprocal_and_regular_at_theta_h_zero(pairs):
    wi, wo = pairs
    np.testing.assert_allclose(uvw_from_directions(wi, wo), uvw_from_directions(wo, wi),
                               atol=1e-10)
    # every phi_d maps to the same point on the theta_h = 0 axis
    uvw = zickler_uvw(0.0, 0.3, np.linspace(0, np.pi, 9))
    np.testing.assert_allclose(uvw[:, :2], 0.0, atol=1e-15)
    np.testing.assert_allclose(uvw[:, 2], 0.3 / (np.pi / 2))


def test_zickler_uvw_known_values_of_eq1():
    """Zickler et al. 2005 Eq. 1 literally: (sin th_h cos 2 phi_d, sin th_h sin 2 phi_d, 2 th_d / pi)."""
    uvw = zickler_uvw(np.pi / 6, np.pi / 3, np.pi / 8)
    np.testing.assert_allclose(uvw, [[0.5 * np.sqrt(0.5), 0.5 * np.sqrt(0.5), 2 / 3]], atol=1e-15)
    # the same point reached from a direction pair with those halfway/difference angles
    wi, wo = from_halfway_difference(np.pi / 6, 0.7, np.pi / 3, np.pi / 8)
    np.testing.assert_allclose(uvw_from_directions(wi, wo), uvw, atol=1e-12)
    # phi_d = pi/4 puts the sample on the v axis; phi_d = pi/2 on -u
    np.testing.assert_allclose(zickler_uvw([0.4, 0.4], 0.2, [np.pi / 4, np.pi / 2])[:, :2],
                               [[0.0, np.sin(0.4)], [-np.sin(0.4), 0.0]], atol=1e-15)


def test_zickler_inverse_rejects_points_off_the_domain():
    with pytest.raises(ValueError, match="u\\^2 \\+ v\\^2"):
        zickler_uvw_inverse([[0.9, 0.9, 0.5]])
    with pytest.raises(ValueError, match="uvw"):
        zickler_uvw_inverse([[0.1, 0.2]])


def test_romeiro_st_round_trip_and_known_values():
    rng = np.random.default_rng(5)
    th = rng.uniform(0, np.pi / 2, 1000)
    td = rng.uniform(0, np.pi / 2, 1000)
    s, t = romeiro_st(th, td)
    assert np.all((s >= 0) & (s <= 1) & (t >= 0) & (t <= 1))
    th2, td2 = romeiro_st_inverse(s, t)
    np.testing.assert_allclose(th2, th, atol=1e-14)
    np.testing.assert_allclose(td2, td, atol=1e-14)
    # t = sqrt(2 theta_h / pi): theta_h = pi/8 -> t = 1/2; theta_d = pi/4 -> s = 1/2
    np.testing.assert_allclose(romeiro_st(np.pi / 8, np.pi / 4), (0.5, 0.5))


def test_st_from_directions_of_mirror_pair():
    theta = 0.6
    wi = np.array([[np.sin(theta), 0, np.cos(theta)]])
    s, t = st_from_directions(wi, wi * [-1, -1, 1])
    np.testing.assert_allclose(t, 0.0, atol=1e-7)
    np.testing.assert_allclose(s, theta / (np.pi / 2))


def test_romeiro_rejects_negative_angles():
    with pytest.raises(ValueError, match="theta_h"):
        romeiro_st(-0.1, 0.2)
    with pytest.raises(ValueError, match="t must be"):
        romeiro_st_inverse(0.5, -0.1)


def test_local_directions_use_the_normal_as_z():
    rng = np.random.default_rng(2)
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    wi_w = rng.normal(size=(500, 3))
    wi_w /= np.linalg.norm(wi_w, axis=1, keepdims=True)
    wo_w = rng.normal(size=(500, 3))
    wo_w /= np.linalg.norm(wo_w, axis=1, keepdims=True)
    wi, wo = local_directions(wi_w, wo_w, n)
    np.testing.assert_allclose(wi[:, 2], np.sum(wi_w * n, axis=1), atol=1e-12)
    np.testing.assert_allclose(np.sum(wi * wo, axis=1), np.sum(wi_w * wo_w, axis=1), atol=1e-12)
    np.testing.assert_allclose(wi, np.einsum("nij,nj->ni", tangent_frames(n), wi_w), atol=1e-12)


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match="wi must be"):
        halfway_difference(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="same shape"):
        halfway_difference(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="same length"):
        local_directions(np.zeros((4, 3)), np.zeros((4, 3)), np.ones((3, 3)))
    with pytest.raises(ValueError, match="theta_d must be finite"):
        from_halfway_difference(0.1, 0.0, np.nan, 0.0)


def test_frames_are_orthonormal_right_handed_and_continuous_through_the_poles():
    rng = np.random.default_rng(21)
    n = rng.normal(size=(5000, 3))
    n[:4] = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, 1e-9, -1]]
    F = tangent_frames(n)
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", F, F), np.broadcast_to(np.eye(3), F.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(F), 1.0, atol=1e-12)   # t x b = n
    np.testing.assert_allclose(F[:, 2], n / np.linalg.norm(n, axis=1, keepdims=True), atol=1e-15)
    v = rng.normal(size=(5000, 3))
    np.testing.assert_allclose(to_world(to_local(v, F), F), v, atol=1e-12)
    # a given tangent is kept (projected into the tangent plane)
    F2 = tangent_frames([[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.5]])
    np.testing.assert_allclose(F2[0], np.eye(3), atol=1e-15)


def test_linear_rows_and_normalize():
    rng = np.random.default_rng(22)
    M, v = rng.normal(size=(3, 3)), rng.normal(size=(1000, 3))
    np.testing.assert_allclose(linear_rows(M, v), v @ M.T, rtol=1e-13, atol=1e-13)
    u = normalize(np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(u, [[0.6, 0.8, 0.0], [0.0, 0.0, 0.0]], atol=1e-15)
    assert np.all(u[1] == 0)  # a zero vector stays zero (no NaN)
    assert normalize(np.ones((2, 3), np.float32)).dtype == np.float32
    np.testing.assert_allclose(normalize(np.array([[3.0, 1.0], [4.0, 0.0]]), axis=0),
                               [[0.6, 1.0], [0.8, 0.0]], atol=1e-15)
