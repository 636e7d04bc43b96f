"""The peak test of Lensch's per-texel normal fit (:func:`reconstruct.lensch.normals.fit_normals_chunk`,
``peak_ratio``), the basis slot of a material's lobes alone (``make_bases(lobes_alone=True)``)
and the dark samples left out of the normal fit (``shadow_ratio``), on synthetic lumitexels of a
sharp lobe whose true normals are known."""
import numpy as np
import pytest

from reconstruct.brdf import Lafortune
from reconstruct.frames import tangent_frames, to_local, to_world
from reconstruct.lensch import SvbrdfError, SvbrdfOptions
from reconstruct.lensch.lafortune_fit import lobe_geometry, params_of
from reconstruct.lensch.normals import fit_normals_chunk
from reconstruct.lensch.projection import basis_values, make_bases, project_chunk
from reconstruct.lensch.interreflection import Interreflection, axis_lobes, held_extras
from reconstruct.lensch.svbrdf import _below_brightest, _not_dark


def _sharp_texels(T=200, M=60, tilt_deg=20.0, seed=0, rho_d=0.2, exponent=300.0):
    """T texels of a sharp Phong lobe (exponent 300), M random lights each and the camera 20 deg
    off the true normal; the first half's frames are ``tilt_deg`` off their true normals, the
    second half's exact. Returns texel, wi, wo, reflectance (in the frames, +z the start normal),
    the true normals in the frames, and the material."""
    m = Lafortune.phong(rho_d=(rho_d,) * 3, rho_s=0.8, exponent=exponent)
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, T)
    tilt = np.where(np.arange(T) < T // 2, np.radians(tilt_deg), 0.0)
    n_true = np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], 1)
    texel = np.repeat(np.arange(T), M)
    u = rng.normal(size=(T * M, 3))
    u[:, 2] = np.abs(u[:, 2]) + 0.3
    u /= np.linalg.norm(u, axis=1, keepdims=True)          # lights in the true normal's frame
    v = np.tile([np.sin(0.35), 0.0, np.cos(0.35)], (T * M, 1))
    refl = m.evaluate(u, v) * u[:, 2:3] + rng.normal(0, 0.002, (T * M, 3))
    frames = tangent_frames(n_true)[texel]   # true-normal frame -> the start frame (+z)
    wi, wo = to_world(u, frames), to_world(v, frames)
    up = (wi[:, 2] > 0.02) & (wo[:, 2] > 0.02)
    return texel[up], wi[up], wo[up], refl[up], n_true, m


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))


def test_the_peak_test_holds_texels_whose_highlight_the_fit_lost_near_their_peak():
    """As on goblet (docs/diligent.md): a metal (no diffuse) reflects itself, a weaker mirror
    image of the highlight 20 deg from the true one, and the fit leaves each texel's brightest
    10 % out, the highlight with them. On the texels whose frames are 20 deg off, the free fit
    follows the mirror image (median error > 15 deg); the peak test must find them (their
    brightest sample many times the model) and hold them near its half vector, within the few
    degrees the 60 lights' spacing allows (median < 6 deg), where that fits all their samples
    at least as well under Tukey's loss (the rest, whose mirror image explains them as well as
    the highlight, keep the free fit: the mean only below 0.7x). Texels without the mirror image, whose
    fit explains their peak, must (nearly all) come out exactly as without the test. Cut-off 3,
    as on imported sets (capture.pipeline.imported.LENSCH_OPTIONS)."""
    texel, wi, wo, refl, n_true, m = _sharp_texels(rho_d=0.0, exponent=60.0)
    T = len(n_true)
    tilted = np.arange(T) < T // 2
    fake = n_true + np.tan(np.radians(20.0)) * np.cross(n_true, [0.0, 1.0, 0.0])
    frames = tangent_frames(fake / np.linalg.norm(fake, axis=1, keepdims=True))[texel]
    u, v = to_local(wi, frames), to_local(wo, frames)
    image = Lafortune(rho_d=0.0, cx=m.cx, cz=m.cz, n=m.n).evaluate(u, v) * u[:, 2:3] * (u[:, 2:3] > 0) * (v[:, 2:3] > 0)
    refl = refl + 0.6 * image * tilted[texel, None]
    fit_weight = _below_brightest(texel, refl, 0.1).astype(float)
    basis, size = make_bases(params_of(m)[None], np.array([-1]))
    start = np.zeros((T, basis.shape[1]))
    start[:, 0] = 1.0
    labels = np.zeros(T, np.int64)
    out = {}
    for ratio in (None, 3.0):
        n, *_ = fit_normals_chunk(texel, wi, wo, refl, fit_weight, labels, start, basis, size,
                                  tukey_c=2.0, peak_weight=np.ones(len(texel)), peak_ratio=ratio)
        out[ratio] = _angle(n, n_true)
    assert np.median(out[None][tilted]) > 15.0, np.median(out[None][tilted])   # the free fit is lost
    assert np.median(out[3.0][tilted]) < 6.0, np.median(out[3.0][tilted])     # held near the truth
    assert out[3.0][tilted].mean() < 0.7 * out[None][tilted].mean()
    # the clean texels: a few whose fitted weights dimmed the lobe without its peak are flagged
    # too (2 of 100 here), and held a few degrees off; the rest come out exactly as without the test
    changed = out[3.0][~tilted] != out[None][~tilted]
    assert np.count_nonzero(changed) <= 5, np.count_nonzero(changed)
    assert out[None][~tilted].mean() < 1.0 and out[3.0][~tilted].mean() < 1.0


def test_the_lobes_alone_slot_frees_a_texels_highlight_from_its_diffuse():
    """Texels whose highlight is 2.5x the material's with its diffuse unchanged: the paper's
    basis (rho_d and N raised together) cannot express that; with the material's lobes alone
    in the basis the projection must fit them to the noise."""
    texel, wi, wo, refl, n_true, m = _sharp_texels(tilt_deg=0.0)
    T = len(n_true)
    p = params_of(m)
    bright = p.copy()
    bright[:, 1:3] *= 2.5 ** (1 / p[:, 3:4])    # lobe 2.5x as strong (C scaled by 2.5^(1/N))
    t, z = lobe_geometry(wi, wo)
    truth = Lafortune(rho_d=p[:, 0], cx=bright[:, 1:2].T, cz=bright[:, 2:3].T, n=bright[:, 3:4].T)
    refl = truth.evaluate(wi, wo) * wi[:, 2:3]
    labels = np.zeros(T, np.int64)
    sse = {}
    for alone in (False, True):
        basis, size = make_bases(p[None], np.array([-1]), lobes_alone=alone)
        w, sse[alone] = project_chunk(texel, t, z, wi[:, 2], refl, np.ones(len(t)), labels, basis, size)
        assert w.shape == (T, basis.shape[1])
    assert sse[True].sum() < 1e-6 * sse[False].sum(), (sse[True].sum(), sse[False].sum())



def test_a_held_texels_interreflection_lobe_predicts_lights_it_did_not_see():
    """The mirror image of the first test (a weaker copy of the highlight about a normal 20 deg
    off, as a mirror-like object's image of itself). With every flagged texel held
    (``peak_compare=False``) the texels with the image must come out near the truth (median
    < 6 deg), and each held texel's axis must be exactly its free fit's normal (the fit without
    the peak test). About the true normals, a lobe about the image's axis (``axis_lobes``), its
    weight fitted with the projection's (``extra``) on 3 of every 4 lights, must predict the 4th
    (lights no fit saw) with under a tenth of the squared error of the projection alone."""
    texel, wi, wo, refl, n_true, m = _sharp_texels(rho_d=0.0, exponent=60.0)
    T = len(n_true)
    tilted = np.arange(T) < T // 2
    fake = n_true + np.tan(np.radians(20.0)) * np.cross(n_true, [0.0, 1.0, 0.0])
    fake /= np.linalg.norm(fake, axis=1, keepdims=True)
    frames = tangent_frames(fake)[texel]
    u, v = to_local(wi, frames), to_local(wo, frames)
    image = Lafortune(rho_d=0.0, cx=m.cx, cz=m.cz, n=m.n).evaluate(u, v) * u[:, 2:3] * (u[:, 2:3] > 0) * (v[:, 2:3] > 0)
    refl = refl + 0.6 * image * tilted[texel, None]
    s = np.arange(len(texel)) % 4 != 0   # the lights the fits see
    basis, size = make_bases(params_of(m)[None], np.array([-1]), lobes_alone=True)
    start = np.zeros((T, basis.shape[1]))
    start[:, 0] = 1.0
    labels = np.zeros(T, np.int64)
    fit = {}
    for ratio in (None, 3.0):
        fit[ratio] = fit_normals_chunk(texel[s], wi[s], wo[s], refl[s], _below_brightest(texel[s], refl[s], 0.1) * 1.0,
                                       labels, start, basis, size, tukey_c=2.0, peak_weight=np.ones(s.sum()),
                                       peak_ratio=ratio, peak_compare=False, return_axes=True)
    n, axes = fit[3.0][0], fit[3.0][4]
    held = np.isfinite(axes[:, 0])
    assert held[tilted].mean() > 0.8 and np.median(_angle(n[held & tilted], n_true[held & tilted])) < 6.0
    np.testing.assert_array_equal(axes[held], fit[None][0][held])
    assert np.all(np.isnan(fit[None][4]))
    frames = tangent_frames(n_true)[texel]
    u, v = to_local(wi, frames), to_local(wo, frames)
    t, z = lobe_geometry(u, v)
    cos_i = np.where((u[:, 2] > 0) & (v[:, 2] > 0), u[:, 2], 0.0)
    extra = axis_lobes(texel, wi, wo, np.where(tilted[:, None], fake, np.nan), labels, basis[:, size[0] - 1, None])
    out = ~s & tilted[texel]
    sse = {}
    for with_lobe in (False, True):
        res = project_chunk(texel[s], t[s], z[s], cos_i[s], refl[s], np.ones(s.sum()), labels, basis, size,
                            select=True, extra=extra[s] if with_lobe else None)
        pred = np.einsum("sbc,sb->sc", basis_values(t, z, cos_i, texel, labels, basis, size), res[0][texel])
        if with_lobe:
            pred = pred + np.einsum("se,sec->sc", res[2][texel], extra)
        sse[with_lobe] = np.sum((pred[out] - refl[out]) ** 2)
    assert sse[True] < sse[False] / 10, sse


def test_a_held_texels_diffuse_term_about_its_input_normal_predicts_the_light_the_object_sends_it():
    """A metal's sharp lobe about the true normal plus broad light from the object about the
    texel's input normal (its frame's +z, 20 deg off; the truth: 0.3 x a diffuse BRDF of colour
    (1.2, 1, 0.8) there), on the tilted half (the held texels, their axis the input normal
    rotated 20 deg). Projected about the true normals on 3 of every 4 lights, with the
    inter-reflection lobe, the diffuse term (``held_extras`` with a colour, as
    ``interreflection_diffuse`` does) must predict the 4th with under a fifth of the squared
    error without it, its weight within 5 % of the truth's 0.3 x pi (the noise is 0.002); the
    untilted texels (no axis) get no diffuse column, and ``Interreflection.predict`` must give
    the projection's own prediction."""
    texel, wi, wo, refl, n_true, m = _sharp_texels(rho_d=0.0, exponent=60.0)
    T = len(n_true)
    tilted = np.arange(T) < T // 2
    colour = np.array([1.2, 1.0, 0.8])
    lit = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    refl = refl + 0.3 * colour * (np.where(lit, wi[:, 2], 0.0) * tilted[texel])[:, None]
    basis, size = make_bases(params_of(m)[None], np.array([-1]), lobes_alone=True)
    labels = np.zeros(T, np.int64)
    axes = np.where(tilted[:, None], to_world(np.tile([np.sin(0.35), 0.0, np.cos(0.35)], (T, 1)),
                                              tangent_frames(n_true)), np.nan)
    frames = tangent_frames(n_true)[texel]
    u, v = to_local(wi, frames), to_local(wo, frames)
    t, z = lobe_geometry(u, v)
    cos_i = np.where((u[:, 2] > 0) & (v[:, 2] > 0), u[:, 2], 0.0)
    lobes = basis[:, size[0] - 1, None]
    s = np.arange(len(texel)) % 4 != 0
    out = ~s & tilted[texel]
    sse, res = {}, {}
    for diffuse in (None, colour[None]):
        extra = held_extras(texel, wi, wo, axes, labels, lobes, diffuse)
        r = project_chunk(texel[s], t[s], z[s], cos_i[s], refl[s], np.ones(s.sum()), labels, basis, size,
                          select=True, extra=extra[s])
        pred = np.einsum("sbc,sb->sc", basis_values(t, z, cos_i, texel, labels, basis, size), r[0][texel]) + \
            np.einsum("se,sec->sc", r[2][texel], extra)
        sse[diffuse is not None], res[diffuse is not None] = np.sum((pred[out] - refl[out]) ** 2), (r, pred, extra)
    assert sse[True] < sse[False] / 5, sse
    r, pred, extra = res[True]
    np.testing.assert_allclose(np.median(r[2][tilted, 1]), 0.3 * np.pi, rtol=0.05)
    assert np.all(extra[~tilted[texel], 1] == 0)
    own = Interreflection(axes, r[2], labels, lobes, colour[None]).predict(texel, wi, wo)
    np.testing.assert_allclose(own, np.einsum("se,sec->sc", r[2][texel], extra))


def test_cast_shadows_left_out_of_the_normal_fit_no_longer_tilt_it():
    """A glossy diffuse material (rho_d 0.6, exponent 30), frames 10 deg off the true normals;
    on every second texel the lights on one side (u_x > 0.2 in the true frame, ~40 % of its
    samples) are hidden by another part of the object: those samples hold noise only. Tilting
    the normal to put those lights below its horizon explains them as an attached shadow, and
    Tukey's loss (2 sigma, brightest 10 % out, as on imported sets) does not undo that: measured
    mean 7.4 deg on the shadowed texels. Left out where below a tenth of the texel's median
    (``shadow_ratio`` 0.1): 0.65 deg. The shadowed texels must come out under a third of
    their error without it, and the unshadowed ones (no sample that dark) exactly as without."""
    texel, wi, wo, refl, n_true, m = _sharp_texels(rho_d=0.6, exponent=30.0, tilt_deg=10.0)
    T = len(n_true)
    shadowed = np.arange(T) % 2 == 0
    u = to_local(wi, tangent_frames(n_true)[texel])
    cast = shadowed[texel] & (u[:, 0] > 0.2)
    refl = np.where(cast[:, None], np.abs(np.random.default_rng(1).normal(0, 0.002, refl.shape)), refl)
    dark = ~_not_dark(texel, refl, 0.1)
    assert np.all(dark <= cast) and dark[cast].mean() > 0.9   # measured 0.93
    basis, size = make_bases(params_of(m)[None], np.array([-1]), lobes_alone=True)
    start = np.zeros((T, basis.shape[1]))
    start[:, 0] = 1.0
    weight = _below_brightest(texel, refl, 0.1) * 1.0
    err = {}
    for drop in (False, True):
        n, *_ = fit_normals_chunk(texel, wi, wo, refl, weight * ~dark if drop else weight, np.zeros(T, np.int64),
                                  start, basis, size, tukey_c=2.0)
        err[drop] = _angle(n, n_true)
    assert err[False][shadowed].mean() > 3.0, err[False][shadowed].mean()   # the tilt is there to undo
    assert err[True][shadowed].mean() < err[False][shadowed].mean() / 3, err[True][shadowed].mean()
    np.testing.assert_array_equal(err[True][~shadowed], err[False][~shadowed])


@pytest.mark.parametrize("setting, message", [
    ({"peak_ratio": 0.0}, "peak_ratio must be > 0 or None, got 0.0"),
    ({"peak_ratio": float("nan")}, "peak_ratio must be > 0"),
    ({"lm_stall": (0, 1e-4)}, r"lm_stall must be \(window: an integer >= 1, rtol in \(0, 1\)\) or None, got \(0, 0.0001\)"),
    ({"lm_stall": (20, 1.5)}, "lm_stall must be"),
    ({"lm_stall": 20}, "lm_stall must be .* got 20"),
    ({"undo_ratio": 0.9}, r"undo_ratio must be >= 1 \(inf: never undo\), got 0.9"),
    ({"interreflection_lobe": True, "peak_ratio": 3.0}, "interreflection_lobe needs lobes_alone=True"),
    ({"texel_undo": True}, r"texel_undo needs interreflection_lobe=True"),
    ({"undo_margin": 0.5}, "undo_margin must be >= 1, got 0.5"),
    ({"interreflection_diffuse": True}, r"interreflection_diffuse needs interreflection_lobe=True"),
    ({"shadow_ratio": 1.0}, r"shadow_ratio must be a share of the texel's median in \(0, 1\) or None, got 1.0"),
    ({"shadow_ratio": float("nan")}, "shadow_ratio must be a share"),
    ({"undo_tukey": 3.0}, r"undo_tukey must be > 0 robust sigmas, with texel_undo=True, or None; got "
                          r"undo_tukey=3.0, texel_undo=False"),
])
def test_bad_settings_name_themselves(setting, message):
    with pytest.raises(SvbrdfError, match=message):
        SvbrdfOptions(**setting)
