"""Lobes broadened per texel by the uncertainty of its fitted normal (reconstruct/lensch/broadening.py)."""
import numpy as np
import pytest

from reconstruct.brdf import Lafortune
from reconstruct.lensch import SvbrdfError, fit_svbrdf
from reconstruct.lensch.broadening import broadened_lobes, normal_turn_excess
from reconstruct.lumitexels import Lumitexels, pixel_neighbours
from sims.reflectance_samples import synthetic_samples


def _lobe(cx, cz, n):
    return Lafortune(rho_d=np.zeros(3), cx=np.full((1, 3), cx), cz=np.full((1, 3), cz), n=np.full((1, 3), n))


@pytest.mark.parametrize("incidence_deg, rtol", [(0.0, 0.01), (30.0, 0.05)])
def test_broadened_lobe_is_the_lobe_averaged_over_normal_errors(incidence_deg, rtol):
    """Ground truth by Monte Carlo: a mirror lobe (C_x = -C_z = 1, N 70) averaged over 40,000
    normals whose slopes are Gaussian, 2 deg per axis, moves its highlight by twice that, an
    added variance of 4 sigma^2. Along the plane of incidence, within 12 deg of the mirror
    direction, the broadened lobe matches that average to ``rtol`` of its peak (seen 0.2 % at
    normal incidence, 3.3 % at 30 deg, where the small-angle approximation bends); the sharp
    lobe misses it by 30 % of the peak."""
    N, sigma = 70.0, np.radians(2.0)
    slopes = np.random.default_rng(0).normal(0.0, sigma, (40_000, 2))
    normals = np.column_stack([slopes, np.ones(len(slopes))])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    inc = np.radians(incidence_deg)
    wi = np.array([np.sin(inc), 0.0, np.cos(inc)])
    theta = inc + np.radians(np.linspace(-12, 12, 13))
    wo = np.column_stack([-np.sin(theta), np.zeros_like(theta), np.cos(theta)])
    # the lobe about each drawn normal: max(0, 2 (wi.n)(wo.n) - wi.wo)^N
    base = 2.0 * (normals @ wi)[None, :] * (wo @ normals.T) - (wo @ wi)[:, None]
    averaged = np.mean(np.maximum(base, 0.0) ** N, axis=1)
    wis = np.tile(wi, (len(wo), 1))
    broad = _lobe(*broadened_lobes(-1.0, 1.0, N, 4.0 * sigma ** 2)).evaluate(wis, wo)[:, 0]
    sharp = _lobe(-1.0, 1.0, N).evaluate(wis, wo)[:, 0]
    assert np.max(np.abs(broad - averaged)) < rtol * averaged.max()
    assert np.max(np.abs(sharp - averaged)) > 0.25 * averaged.max()


def test_broadening_leaves_lobes_without_a_peak_at_normal_incidence_and_zero_variance_alone():
    cx, cz, n = broadened_lobes(np.array([-1.0, 0.8, -1.0]), np.array([1.0, -0.5, 0.9]), np.array([40.0, 5.0, 20.0]),
                                np.array([0.0, 0.01, 0.01]))
    np.testing.assert_allclose([cx[0], cz[0], n[0]], [-1.0, 1.0, 40.0])   # no variance
    np.testing.assert_allclose([cx[1], cz[1], n[1]], [0.8, -0.5, 5.0])    # C_z <= 0: retro-reflective
    np.testing.assert_allclose(n[2], 1.0 / (1.0 / 20.0 + 0.01))
    np.testing.assert_allclose(cz[2] ** n[2], n[2] / 20.0 * 0.9 ** 20.0)  # the peak lowered by N'/N


def _grid_lumitexels(width=4, height=3):
    """One texel per pixel of a width x height image (best view 0), texels in random order."""
    order = np.random.default_rng(1).permutation(width * height)
    x, y = np.meshgrid(np.arange(width), np.arange(height))
    pixel = np.column_stack([x.ravel(), y.ravel()])[order].astype(float)
    T = width * height
    z = np.zeros((0, 3))
    return Lumitexels(position=np.zeros((T, 3)), normal=np.tile([0.0, 0.0, 1.0], (T, 1)), best_view=np.zeros(T, np.int32),
                      pixel=pixel, texel=np.zeros(0, np.int64), view=np.zeros(0, np.int64), wi=z, wo=z,
                      reflectance=z, weight=np.zeros(0))


def test_pixel_neighbours_are_the_texels_on_the_adjacent_pixels():
    lt = _grid_lumitexels()
    nb = pixel_neighbours(lt)
    at = {tuple(p): t for t, p in enumerate(lt.pixel.astype(int))}
    for t, (x, y) in enumerate(lt.pixel.astype(int)):
        for k, (dx, dy) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
            assert nb[k, t] == at.get((x + dx, y + dy), -1)


def test_turn_excess_is_the_fitted_normals_turn_beyond_the_references():
    """A 5 x 1 strip of texels on a reference curving 1 deg a pixel (normals at 0, 1, 2, 3, 4 deg);
    the fitted normals follow it but texel 2's turns 4 deg further (6 deg). Median turns against
    the neighbours minus the reference's 1 deg: texel 2 {5, 3} -> 3 deg, texel 1 {1, 5} -> 2,
    texel 3 {3, 1} -> 1, the ends 0."""
    ang = np.radians([0.0, 1.0, 2.0, 3.0, 4.0])
    ref = np.column_stack([np.sin(ang), np.zeros(5), np.cos(ang)])
    ang_fit = ang + np.radians([0.0, 0.0, 4.0, 0.0, 0.0])
    fitted = np.column_stack([np.sin(ang_fit), np.zeros(5), np.cos(ang_fit)])
    right = np.array([1, 2, 3, 4, -1])
    left = np.array([-1, 0, 1, 2, 3])
    neighbours = np.stack([right, left, np.full(5, -1), np.full(5, -1)])
    np.testing.assert_allclose(np.degrees(normal_turn_excess(fitted, ref, neighbours)), [0, 2, 3, 1, 0], atol=1e-6)
    np.testing.assert_allclose(normal_turn_excess(ref, ref, np.full((4, 5), -1)), 0.0)   # no neighbour: 0


def test_the_fit_broadens_only_its_predictions_and_only_where_normals_turn():
    """With ``normal_broadening`` the fit (labels, weights, normals, Table II) is the same; the
    lobe variance is c x (the turn excess)^2, and predictions change only where it is > 0, where
    every lobe the texel weights is broader."""
    materials = (Lafortune.phong(rho_d=(0.5, 0.4, 0.3), rho_s=0.5, exponent=20.0),)
    d = synthetic_samples(materials, 120, samples_per_texel=12, rng=3, noise=0.02)
    neighbours = np.stack([np.roll(np.arange(120), -1), np.roll(np.arange(120), 1)])   # a ring of texels
    common = dict(normals=d.normal, fit_normals=True, n_materials=1, rng=0)
    plain = fit_svbrdf(d.texel, d.wi, d.wo, d.reflectance, **common)
    broad = fit_svbrdf(d.texel, d.wi, d.wo, d.reflectance, neighbours=neighbours, normal_broadening=4.0, **common)
    assert plain.lobe_variance is None
    np.testing.assert_array_equal(broad.labels, plain.labels)
    np.testing.assert_allclose(broad.weights, plain.weights)
    np.testing.assert_allclose(broad.normals, plain.normals)
    assert broad.rms == plain.rms
    excess = normal_turn_excess(broad.normals, d.normal, neighbours)
    np.testing.assert_allclose(broad.lobe_variance, 4.0 * excess ** 2)
    turned = broad.lobe_variance > 0
    assert 0 < turned.sum() < 120
    p_plain, p_broad = plain.predict(d.texel, d.wi, d.wo), broad.predict(d.texel, d.wi, d.wo)
    still = ~turned[d.texel]
    np.testing.assert_allclose(p_broad[still], p_plain[still], rtol=1e-9, atol=1e-12)
    sharp, broadened = plain.brdf(np.flatnonzero(turned)), broad.brdf(np.flatnonzero(turned))
    used = sharp.cz > 0   # the slots a texel weights (the others are 0)
    assert np.all(broadened.n[used] < sharp.n[used]) and np.all(broadened.n[~used] == sharp.n[~used])


def test_broadening_without_what_it_needs_names_it():
    d = synthetic_samples((Lafortune.phong(rho_d=0.5, rho_s=0.5, exponent=20.0),), 20, samples_per_texel=8, rng=0)
    args = (d.texel, d.wi, d.wo, d.reflectance)
    with pytest.raises(SvbrdfError, match="neighbours"):
        fit_svbrdf(*args, normals=d.normal, fit_normals=True, normal_broadening=4.0)
    with pytest.raises(SvbrdfError, match="fit_normals"):
        fit_svbrdf(*args, normals=d.normal, neighbours=np.full((4, 20), -1), normal_broadening=4.0)
    with pytest.raises(SvbrdfError, match=r"\(K, 20\)"):
        fit_svbrdf(*args, normals=d.normal, fit_normals=True, neighbours=np.full((4, 19), -1), normal_broadening=4.0)
    with pytest.raises(SvbrdfError, match="normal_broadening must be"):
        fit_svbrdf(*args, normals=d.normal, fit_normals=True, normal_broadening=-1.0)
