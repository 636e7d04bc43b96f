"""fit_lafortune (Lensch et al. 2003, Sec. 6): recovery of known models, covariance honesty, errors."""
import numpy as np
import pytest

from reconstruct.brdf import Lafortune
from reconstruct.lensch import LafortuneFitError, fit_lafortune
from reconstruct.lensch.lafortune_fit import fit_geometry, lobe_geometry


def _directions(rng, n, *, near_mirror_of=None, spread=0.15):
    """Random upper-hemisphere unit vectors; with ``near_mirror_of`` close to those vectors' mirrors."""
    if near_mirror_of is None:
        v = rng.normal(size=(n, 3))
        v[:, 2] = np.abs(v[:, 2]) + 0.1
    else:
        v = near_mirror_of * [-1, -1, 1] + spread * rng.normal(size=near_mirror_of.shape)
        v[:, 2] = np.abs(v[:, 2]) + 0.05
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _samples(rng, n=3000, frac_mirror=0.4):
    wi = _directions(rng, n)
    wo = _directions(rng, n)
    k = int(frac_mirror * n)
    wo[:k] = _directions(rng, k, near_mirror_of=wi[:k])
    return wi, wo


MODELS = {
    "phong": Lafortune.phong(rho_d=(0.15, 0.3, 0.1), rho_s=1.0, exponent=48.2),
    "off_specular_rgb": Lafortune(rho_d=(0.3, 0.5, 0.2), cx=[[-0.95, -1.0, -1.05]],
                                  cz=[[0.75, 0.8, 0.85]], n=[[20.0, 25.0, 30.0]]),
    "broad_dark": Lafortune(rho_d=(0.05, 0.04, 0.06), cx=-0.9, cz=0.9, n=4.0),
}


@pytest.mark.parametrize("name", list(MODELS))
def test_noise_free_samples_give_the_model_back(name):
    true = MODELS[name]
    rng = np.random.default_rng(3)
    wi, wo = _samples(rng)
    r = true.evaluate(wi, wo) * wi[:, 2:3]
    fit = fit_lafortune(wi, wo, r)
    assert fit.converged
    np.testing.assert_allclose(fit.model.rho_d, np.broadcast_to(true.rho_d, (3,)), rtol=1e-6, atol=1e-9)
    for k in ("cx", "cz", "n"):
        np.testing.assert_allclose(getattr(fit.model, k), np.broadcast_to(getattr(true, k), (1, 3)),
                                   rtol=1e-6)
    assert fit.rms < 1e-8 * np.abs(r).max()
    assert fit.n_samples == len(wi)


def test_covariance_predicts_the_scatter_of_repeated_noisy_fits():
    """The reported standard errors match the spread of fits to independent noise draws."""
    true = MODELS["off_specular_rgb"]
    rng = np.random.default_rng(11)
    wi, wo = _samples(rng, n=1500)
    clean = true.evaluate(wi, wo) * wi[:, 2:3]
    fits = [fit_lafortune(wi, wo, clean + 0.02 * rng.normal(size=clean.shape)) for _ in range(40)]
    est = np.array([f.params for f in fits])
    predicted = np.median([f.std for f in fits], axis=0)
    observed = est.std(axis=0, ddof=1)
    # 40 draws: the sample std is within ~+-25 % of the truth at 2 sigma
    np.testing.assert_allclose(observed / predicted, 1.0, atol=0.35)
    # and the truth lies within 4 standard errors of every estimate
    truth = fits[0].params * 0
    truth[:3] = true.rho_d
    for k, name in enumerate(("cx", "cz", "n")):
        truth[3 + 3 * k:6 + 3 * k] = np.asarray(getattr(true, name))[0]
    assert np.all(np.abs(est - truth) < 4 * predicted)


def test_two_lobes_forward_plus_retro_reproduce_held_out_values():
    true = Lafortune(rho_d=(0.2, 0.2, 0.3), cx=[-1.0, 0.9], cz=[1.0, 0.9], n=[40.0, 6.0])
    rng = np.random.default_rng(5)
    wi, wo = _samples(rng, n=4000)
    k = 800  # some views near the light so the retro lobe is seen
    wo[-k:] = _directions(rng, k, near_mirror_of=wi[-k:] * [-1, -1, 1])
    r = true.evaluate(wi, wo) * wi[:, 2:3]
    fit = fit_lafortune(wi, wo, r, n_lobes=2)
    assert fit.model.n_lobes == 2 and fit.params.shape == (21,) and fit.covariance.shape == (21, 21)
    wi2, wo2 = _samples(np.random.default_rng(6), n=2000)
    np.testing.assert_allclose(fit.model.evaluate(wi2, wo2), true.evaluate(wi2, wo2), rtol=1e-4, atol=1e-6)
    lobes = sorted(zip(np.asarray(fit.model.n)[:, 0], np.asarray(fit.model.cx)[:, 0]))
    np.testing.assert_allclose(lobes, [(6.0, 0.9), (40.0, -1.0)], rtol=1e-4)


def test_weights_exclude_samples_and_init_is_used():
    true = MODELS["phong"]
    rng = np.random.default_rng(8)
    wi, wo = _samples(rng, n=1000)
    r = true.evaluate(wi, wo) * wi[:, 2:3]
    r[:100] = 50.0  # corrupt samples that carry zero weight
    w = np.ones(len(wi))
    w[:100] = 0
    fit = fit_lafortune(wi, wo, r, weight=w, init=Lafortune.phong(0.5, 0.5, 10.0))
    np.testing.assert_allclose(np.asarray(fit.model.n)[0], 48.2, rtol=1e-6)
    assert fit.rms < 1e-8


def test_bad_input_names_the_argument():
    rng = np.random.default_rng(0)
    wi, wo = _samples(rng, n=20)
    r = np.full((20, 3), 0.1)
    with pytest.raises(LafortuneFitError, match="fewer than the 4 parameters"):
        fit_lafortune(wi[:3], wo[:3], r[:3])
    with pytest.raises(LafortuneFitError, match="fewer than the 7 parameters"):
        fit_lafortune(wi[:5], wo[:5], r[:5], n_lobes=2)
    bad = r.copy()
    bad[4, 1] = np.nan
    with pytest.raises(LafortuneFitError, match="reflectance holds 1 non-finite"):
        fit_lafortune(wi, wo, bad)
    with pytest.raises(LafortuneFitError, match=r"wo must have shape \(S, 3\)"):
        fit_lafortune(wi, wo[:, :2], r)
    with pytest.raises(LafortuneFitError, match="reflectance has 19 rows"):
        fit_lafortune(wi, wo, r[:19])
    with pytest.raises(LafortuneFitError, match="wi has 1 directions at or below"):
        below = wi.copy()
        below[0, 2] *= -1
        fit_lafortune(below, wo, r)
    with pytest.raises(LafortuneFitError, match="wi must hold unit vectors"):
        fit_lafortune(wi * 2, wo, r)
    with pytest.raises(LafortuneFitError, match="n_lobes"):
        fit_lafortune(wi, wo, r, n_lobes=0)
    with pytest.raises(LafortuneFitError, match="weight must have shape"):
        fit_lafortune(wi, wo, r, weight=np.ones(3))
    with pytest.raises(LafortuneFitError, match="init has 1 lobes"):
        fit_lafortune(wi, wo, r, n_lobes=2, init=Lafortune.phong())


def _cone(rng, n, max_deg):
    cz = rng.uniform(np.cos(np.radians(max_deg)), 1, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - cz ** 2)
    return np.c_[s * np.cos(ph), s * np.sin(ph), cz]


def _largest_reflectance(model):
    """max f_r cos(theta_i) over a grid of all light / view directions (plane of incidence and
    out of it), by brute force."""
    th = np.radians(np.linspace(0, 89, 90))
    ph = np.radians(np.linspace(0, 180, 37))
    T, P = np.meshgrid(th, ph)
    wo = np.c_[(np.sin(T) * np.cos(P)).ravel(), (np.sin(T) * np.sin(P)).ravel(), np.cos(T).ravel()]
    best = 0.0
    for ci in np.linspace(0.02, 1, 50):
        wi = np.broadcast_to([np.sqrt(1 - ci * ci), 0, ci], wo.shape)
        best = max(best, float(np.max(model.evaluate(wi, wo)) * ci))
    return best


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_lobe_fitted_with_the_camera_near_the_normal_stays_credible_at_held_out_lights(seed):
    # the demo's blow-up (held-out relative RMS 12.2): a texel seen from near its normal has
    # t = u_x v_x + u_y v_y ~ 0 at every training sample, so C_x is not pinned; a fit drifted to
    # -C_x = 1.5 C_z at N = 20 (same training RMS) and predicted 610 1/sr near grazing (seed 3)
    # where the true lobe never exceeds 9.3. Samples: a shiny Phong lobe averaged over a pixel
    # footprint of slightly tilted normals, lights within 60 deg, camera within 5 deg, 3 % noise.
    from reconstruct.frames import tangent_frames, to_local
    true = Lafortune.phong(rho_d=(0.10, 0.20, 0.50), rho_s=0.8, exponent=70.0)
    rng = np.random.default_rng(seed)
    S = 600
    wi, wo = _cone(rng, S, 60), _cone(rng, S, 5)
    r = np.zeros((S, 3))
    for _ in range(4):
        n = np.c_[rng.normal(0, 0.05, (S, 2)), np.ones(S)]
        frames = tangent_frames(n / np.linalg.norm(n, axis=1)[:, None])
        a, b = to_local(wi, frames), to_local(wo, frames)
        lit = (a[:, 2:3] > 0) & (b[:, 2:3] > 0)
        r += np.where(lit, true.evaluate(a, b) * np.maximum(a[:, 2:3], 0), 0) / 4
    r *= 1 + 0.03 * rng.standard_normal((S, 3))
    far = np.einsum("ij,ij->i", wi * [-1, -1, 1], wo) < 0.9  # the training lights miss the peak
    fit = fit_lafortune(wi[far], wo[far], r[far])
    assert _largest_reflectance(fit.model) <= 1.5 * _largest_reflectance(true)


@pytest.mark.parametrize("cx, cz, n", [(-1.0, 1.0, 10.0), (-1.02, 0.95, 12.0), (-0.9, 1.1, 3.0),
                                       (-1.3, 0.9, 40.0)])
def test_lobe_albedo_matches_quadrature(cx, cz, n):
    # largest directional albedo over incidence, against Monte Carlo quadrature of
    # int max(0, C.(u, v))^N cos(theta_o) dv (4e5 directions: ~1 % noise); the closed form is
    # exact for lobes above the horizon and within a factor 2 for strongly off-specular ones
    from reconstruct.lensch.lafortune_fit import lobe_albedo
    rng = np.random.default_rng(1)
    v = rng.standard_normal((400_000, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    v[:, 2] = np.abs(v[:, 2])
    quad = max(2 * np.pi * np.mean(np.maximum(cx * np.sqrt(1 - c * c) * v[:, 0] + cz * c * v[:, 2], 0) ** n
                                   * v[:, 2]) for c in np.linspace(0.02, 1, 40))
    tol = 0.03 if cx * cx <= 1.1 * cz * cz else 0.5
    assert lobe_albedo(cx, cz, n) == pytest.approx(quad, rel=tol)
    # the paper's normalised Phong lobe: C^N = rho_s (N + 2) / 2 pi has albedo rho_s
    C = (0.4 * (n + 2) / (2 * np.pi)) ** (1 / n)
    assert lobe_albedo(-C, C, n) == pytest.approx(0.4, rel=1e-9)


def test_fitted_lobe_albedo_stays_physical_when_samples_miss_the_highlight():
    # samples only far from the mirror direction cannot pin C against N: the fit must not trade a
    # large C for a large N (such a lobe explodes at the untried mirror angle)
    from reconstruct.lensch.lafortune_fit import MAX_LOBE_ALBEDO, albedo_penalty, lobe_albedo
    rng = np.random.default_rng(5)
    wi = _directions(rng, 4000)
    wo = _directions(rng, 4000)
    mirror = wi * np.array([-1, -1, 1])
    far = np.einsum("ij,ij->i", mirror, wo) < 0.6
    wi, wo = wi[far], wo[far]
    true = Lafortune(rho_d=0.2, cx=-1.0, cz=1.0, n=60.0)
    r = true.evaluate(wi, wo) * wi[:, 2:3] * (1 + 0.05 * rng.standard_normal((len(wi), 1)))
    fit = fit_lafortune(wi, wo, r)
    cx, cz, n = (np.asarray(getattr(fit.model, k), float).reshape(-1) for k in ("cx", "cz", "n"))
    assert np.all(lobe_albedo(cx, cz, n) <= 1.01 * MAX_LOBE_ALBEDO)
    # physical lobes (the paper's normalised Phong, the demo's off-specular gold) are never
    # penalised; the demo's exploded lobe (-C_x = 2.5 C_z, albedo ~ 66-109) is
    lobes = np.array([[0.1, -1.07, 1.07, 10.0], [0.1, -1.02, 0.95, 12.0], [0.1, -1.0, 1.0, 5000.0]])
    assert np.all(albedo_penalty(lobes, np.ones(3))[0] == 0)
    assert np.all(albedo_penalty(np.array([[0.1, -1.621, 0.653, 16.5]]), np.ones(1))[0] > 0)


def test_a_stalled_two_lobe_fit_stops_early_and_predicts_as_the_full_fit():
    """Two nearly alike lobes on noisy samples crawl (the lobes trading energy) until the
    200-iteration cap; with ``stall`` (20 iterations, 1e-4 of the cost, as on imported sets)
    the fit stops in under 50 iterations, its cost within 1e-3 of the full fit's and its
    predictions at held-out directions within 1 % of the full fit's (RMS)."""
    true = Lafortune(rho_d=(0.2, 0.25, 0.3), cx=[-1.0, -0.95], cz=[1.0, 0.95], n=[30.0, 20.0])
    rng = np.random.default_rng(11)
    wi, wo = _samples(rng, n=6000)
    r = true.evaluate(wi, wo) * wi[:, 2:3]
    r = r + rng.normal(0, 0.05 * r.std(), r.shape)
    t, z = lobe_geometry(wi, wo)
    fits = {s: fit_geometry(t, z, wi[:, 2], r, np.ones(len(t)), n_lobes=2, stall=s) for s in (None, (20, 1e-4))}
    full, early = fits[None], fits[(20, 1e-4)]
    assert full.n_iter == 200 and early.n_iter < 50, (early.n_iter, full.n_iter)
    assert early.rms ** 2 <= (1 + 1e-3) * full.rms ** 2, (early.rms, full.rms)
    wi2, wo2 = _samples(np.random.default_rng(12), n=2000)
    a, b = early.model.evaluate(wi2, wo2), full.model.evaluate(wi2, wo2)
    assert np.sqrt(np.mean((a - b) ** 2)) < 0.01 * np.sqrt(np.mean(b ** 2))
