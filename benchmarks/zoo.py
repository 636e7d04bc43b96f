"""The appearance methods on the test zoo: reflectance made outside the repository (issue 24).

Prints, in one run:

1. Reflectance sharing, Zickler et al. Sect. 5.1: per material, 10 orthographic sphere images
   (``--size`` px, theta_d stratified over [0, pi/2]) in, 21 held out; the median and pooled
   relative RMS radiance error over the held-out images of
   - the homogeneous RBF fit as it is (log values over the polar form of (u, v, w), m_w chosen
     on held-out inputs; ``--angular-weight none``: over (u, v, w) itself) and as the paper
     wrote it (f_r values, m_w = 0.5: ``log_values=False, m_w=0.5, angular_weight=None``),
   - the best of 1, 2 and 3-lobe Lafortune fits and the best Ward fit of the same samples,
   - the floor: a perfect table of the truth in the form its data are stored
     (``perfect_table``: f_r on 90 x 90 x 180 nodes, ``TabulatedIsotropic``; for an RGL file,
     whose tables hold f_r cos theta_light and are not reciprocal, f_r cos theta_i on
     90 x 90 x 360, ``TabulatedCosine``), and the reciprocal floor: the images of the reciprocal
     BRDF nearest the truth (``NearestReciprocal``; 0 for a reciprocal truth), below which no
     reciprocal model (the RBF, Lafortune, Ward, a MERL table) can come;
   for the analytic zoo (sharp: Ashikhmin-Shirley, GGX over Oren-Nayar; smooth: retro, sheen)
   and measured materials (NBRDF fits of MERL / Nielsen, RGL files). ``--profile NAME``
   instead prints one material's highlight along theta_h at held-out theta_d (truth, and the
   fit's ratio to it with and without the polar form, at phi_d 90 and 0 deg); ``--rgl``
   prints why the two RGL rows miss (their asymmetry, floors, where the held-out error lies,
   the fit fed the nearest reciprocal BRDF's images, the fit with near pairs merged, each per
   held-out image); ``--merge-radius R``: the table's RBF with near pairs merged.
2. Passive reflectometry, Romeiro et al. Fig. 6: per MERL material (every ``--every``-th from
   ``--offset``), one ``--sphere`` px image of a sphere under Grace Cathedral (``--env-height``
   rows), the prior learned from the *other* MERL materials (leave-one-out, as the paper did):
   their modes of variation in log space (``--prior modes``, ``learn_modes``) or Eq. 6's
   derivative variances (``--prior smoothness``); the recovered BRDF's Eq. 1 error beside that
   of the material's own 32 x 32 bivariate reduction, in both readings of Eq. 1 (per-sample
   relative, and pooled: RMS difference over RMS value), per-sample over the nodes the
   environment constrains (``Adequacy.constrained``) and per-sample with both directions
   within 80 deg of the normal; materials sorted by the reduction's error (the paper's order);
   written as ``passive_fig6.png`` in ``--out``. ``--lam`` overrides the prior's weight
   (``cv``: cross-validated, derivative prior only). ``--hemisphere N``: instead of the
   image's pixels, the paper's observations (N normals uniform on the visible hemisphere, those
   beyond 80 deg dropped); ``--reweight K``: K reweighted solves under the modes prior (each
   pixel's noise grown by its misfit); ``--exemplars K|loo``: the unconstrained nodes filled
   from the K nearest library exemplars (``passive_exemplars``; ``loo``: K by leave-one-out on
   the library); ``--oracle``: per material also the oracle split (the recovered table with the
   truth's own reduction put in at node groups, and the best single library exemplar at the
   unconstrained nodes, chosen with the truth); ``--exemplar-loo``: instead, each MERL material
   left out, how well its own seen nodes predict its unseen ones through its nearest exemplars
   and through the modes prior's conditional mean; ``--replot LOG...``: summarise and draw from
   the rows earlier runs printed (the two halves of a run split by ``--every 2 --offset
   0|1``).

Needs ``../shared/data/brdfs`` and ``../shared/data/probes``. Run with
``OPENBLAS_NUM_THREADS=1`` on a shared machine. ``--quick``: small sizes, few materials.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

# benchmarks/calibration.py would shadow the calibration package: drop this script's folder
sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import re  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402

from reconstruct.brdf import Bivariate, TabulatedIsotropic  # noqa: E402
from reconstruct.brdf.rgl import RglBRDF  # noqa: E402
from reconstruct.brdf.tabulated import TabulatedCosine  # noqa: E402
from reconstruct.coords import halfway_difference  # noqa: E402
from reconstruct.brdf.zoo import (NearestReciprocal, analytic_zoo, load_measured,  # noqa: E402
                                  measured_files)
from reconstruct.distant import shade_distant, sphere_normals  # noqa: E402
from reconstruct.envmap import EnvironmentMap  # noqa: E402
from reconstruct.lensch import fit_lafortune  # noqa: E402
from reconstruct.passive import (PassiveWarning, bivariate_error, passive_reflectometry,  # noqa
                                 visible_hemisphere_normals)
from reconstruct.passive_exemplars import ExemplarLibrary, nearest_exemplars, node_weights  # noqa
from reconstruct.passive_modes import learn_modes  # noqa: E402
from reconstruct.passive_prior import learn_prior  # noqa: E402
from reconstruct.sharing import fit_isotropic, samples_from_images  # noqa: E402
from reconstruct.sharing.isotropic import ANGULAR_WEIGHT  # noqa: E402
from reconstruct.sharing.baselines import fit_ward  # noqa: E402
from sims.distant_scenes import VIEW, render_distant, stratified, theta_d_lights  # noqa: E402

DATA = Path(os.environ.get("GONIO_SHARED_DATA",
                           Path(__file__).resolve().parents[2] / "shared" / "data"))
CAMERA_TO_PROBE = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
#: the measured materials of the sharing table: a matte paper, a matte wall paint, a metallic
#: paint, a colour-shift paint, a glossy phenolic, a glossy vinyl film
SHARING_MEASURED = ("nielsen/yellowpaper", "rgl/colodur_napoli_4f_rgb", "merl/gold-metallic-paint",
                    "merl/color-changing-paint2", "merl/specular-red-phenolic",
                    "rgl/vch_golden_yellow_rgb")
SHARP = ("ashikhmin-shirley n=1000", "ggx a=0.08 over oren-nayar")
#: ``--rgl``'s merged variant: near the best for the vinyl at m_w 0.25 (0.005 / 0.0075 / 0.01 /
#: 0.015: 5.29 / 5.28 / 5.30 / 5.51 %, docs/zoo.md)
RGL_MERGE_RADIUS = 0.0075
#: The fourth reading of Eq. 1 leaves out samples with a direction within this many degrees of
#: the horizon: where MERL has no data (the NBRDF fits fall to 1e-6 1/sr there) and beyond the
#: paper's own 80 deg observation limit.
GRAZING = 10


def per_image_errors(pred, truth):
    """Relative RMS error of each image of (K, P, 3) stacks: (K,)."""
    return np.sqrt(((pred - truth) ** 2).sum(axis=(1, 2))
                   / np.maximum((truth ** 2).sum(axis=(1, 2)), 1e-300))


def held_out_errors(pred, truth):
    """(pooled, median of per-image) relative RMS errors of (K, P, 3) stacks; images with no
    lit pixel are left out of the median."""
    per = per_image_errors(pred, truth)
    lit = truth.max(axis=(1, 2)) > 0
    return float(np.sqrt(((pred - truth) ** 2).sum() / (truth ** 2).sum())), \
        float(np.median(per[lit]))


def perfect_table(truth):
    """The truth tabulated in the form its data are stored: an RGL file's tables hold
    f_r cos theta_light and are not reciprocal (Mitsuba's ``measured`` plugin reads them so,
    ``tests/reconstruct/test_rgl_mitsuba.py``), so a table of f_r folded by reciprocity and
    divided by cos theta_light near the horizon would be a floor of our own making."""
    if isinstance(truth, RglBRDF):
        return TabulatedCosine.from_brdf(truth)
    return TabulatedIsotropic.from_brdf(truth)


def sharing_row(truth, size: int, angular_weight, merge_radius: float = 0.0):
    """Held-out (pooled, median) errors of each method on one material, and the fit's m_w."""
    train = render_distant(truth, size, theta_d_lights(stratified(10)))
    test = render_distant(truth, size, theta_d_lights(stratified(21)))
    s = samples_from_images(train.normals, train.radiance, train.directions)

    def err(brdf):
        return held_out_errors(render_distant(brdf, size, test.directions).radiance,
                               test.radiance)

    t0 = time.perf_counter()
    fit = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, groups=s.image,
                        angular_weight=angular_weight, merge_radius=merge_radius)
    t_fit = time.perf_counter() - t0
    old = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, log_values=False, m_w=0.5,
                        angular_weight=None, reciprocal=True)
    k = s.valid & (s.wi[:, 2] > 0.05)
    laf = min((err(fit_lafortune(s.wi[k], s.wo[k], s.brdf[k] * s.wi[k, 2:3], n_lobes=n).model)
               for n in (1, 2, 3)), key=lambda e: e[1])
    ward = err(fit_ward(s.wi, s.wo, s.brdf, valid=s.valid).brdf)
    return {"rbf": err(fit.brdf), "rbf (before)": err(old.brdf), "lafortune": laf,
            "ward": ward, "table": err(perfect_table(truth)),
            "reciprocal": err(NearestReciprocal(truth))}, fit.m_w, t_fit


def load_truth(name: str):
    zoo = analytic_zoo()
    return zoo[name] if name in zoo else load_measured(measured_files(DATA / "brdfs")[name])


def sharing_section(names, size: int, angular_weight, merge_radius: float = 0.0) -> None:
    print(f"== reflectance sharing, Sect. 5.1: {size} x {size} sphere, 10 images in (theta_d "
          f"stratified), 21 held out; angular weight {angular_weight}; merge radius "
          f"{merge_radius:g}; relative RMS radiance error, median / pooled ==")
    cols = ("rbf", "rbf (before)", "lafortune", "ward", "table", "reciprocal")
    print(f"{'material':34s}" + "".join(f"{c:>17s}" for c in cols) + f"{'m_w':>6s}{'fit':>7s}")
    for name in names:
        row, m_w, t_fit = sharing_row(load_truth(name), size, angular_weight, merge_radius)
        kind = "sharp" if name in SHARP else ("matte" if "paper" in name or "colodur" in name
                                              else "")
        print(f"{name[:27] + (' ' + kind if kind else ''):34s}"
              + "".join(f"{100 * row[c][1]:8.2f}/{100 * row[c][0]:7.2f}" for c in cols)
              + f"{m_w:6.2g}{t_fit:6.1f}s", flush=True)


def rgl_section(size: int, merge_radius: float) -> None:
    """Why the RGL rows miss their targets: per file, how far f(a, b) and f(b, a) differ
    (median over random pairs, by the larger elevation and by theta_h), the floors (the f_r
    table folded by reciprocity, the f_r cos theta_i table, the nearest reciprocal BRDF), where
    in the five median held-out images the RBF's and the reciprocal floor's squared error lies
    (light or view beyond 80 deg; theta_h < 10 deg), and the RBF fed the nearest reciprocal
    BRDF's images instead (no conflicting orderings), the RBF with near pairs merged
    (``merge_radius``), and each of these per held-out image (which image is the median); and
    first the reciprocity check and the default fit, which is not reciprocal where the check
    finds the data are not (``sharing.reciprocity``)."""
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(2, 200_000, 3))
    a[:, 2], b[:, 2] = np.abs(a[:, 2]), np.abs(b[:, 2])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    elevation = np.degrees(np.arccos(np.minimum(a[:, 2], b[:, 2])))
    theta_h = np.degrees(halfway_difference(a, b)[0])
    for name in [n for n in SHARING_MEASURED if n.startswith("rgl/")]:
        truth = load_truth(name)
        f, g = truth.evaluate(a, b).mean(axis=1), truth.evaluate(b, a).mean(axis=1)
        asym = np.abs(f - g) / (0.5 * (f + g) + 1e-12)
        print(f"== {name}: |f(a, b) - f(b, a)| / mean, median over 200,000 random pairs: "
              f"{100 * np.median(asym):.1f} % ==")
        print("  by the larger elevation (deg): " + ", ".join(
            f"{lo}-{hi}: {100 * np.median(asym[(elevation >= lo) & (elevation < hi)]):.1f} %"
            for lo, hi in ((0, 30), (30, 50), (50, 65), (65, 75), (75, 85), (85, 90))))
        low, th_low = asym[elevation < 65], theta_h[elevation < 65]
        print("  both within 65 deg, by theta_h (deg): " + ", ".join(
            f"{lo}-{hi}: {100 * np.median(low[(th_low >= lo) & (th_low < hi)]):.1f} %"
            for lo, hi in ((0, 2), (2, 5), (5, 10), (10, 20), (20, 40), (40, 90))))
        train = render_distant(truth, size, theta_d_lights(stratified(10)))
        test = render_distant(truth, size, theta_d_lights(stratified(21)))
        nearest = NearestReciprocal(truth)
        rec = render_distant(nearest, size, test.directions).radiance
        floors = {"f_r table 90x90x180": TabulatedIsotropic.from_brdf(truth),
                  "f_r cos table 90x90x360": TabulatedCosine.from_brdf(truth)}
        for label, model in floors.items():
            pooled, median = held_out_errors(
                render_distant(model, size, test.directions).radiance, test.radiance)
            print(f"  floor, {label}: {100 * median:.2f} / {100 * pooled:.3g} %")
        pooled, median = held_out_errors(rec, test.radiance)
        print(f"  floor, nearest reciprocal: {100 * median:.2f} / {100 * pooled:.2f} %")
        s = samples_from_images(train.normals, train.radiance, train.directions)
        default = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, groups=s.image)
        own = held_out_errors(render_distant(default.brdf, size, test.directions).radiance,
                              test.radiance)[1]
        print(f"  samples {default.reciprocity.report()}; the default fit (m_w "
              f"{default.m_w:g}, un-doubled phi_d weight {default.brdf.asymmetry_weight}): "
              f"{100 * own:.2f} % median; reciprocal fits (reciprocal=True) below")
        fit = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, groups=s.image, reciprocal=True)
        pred = render_distant(fit.brdf, size, test.directions).radiance
        per = per_image_errors(pred, test.radiance)
        lit = np.flatnonzero(test.radiance.max(axis=(1, 2)) > 0)
        middle = lit[np.argsort(per[lit])][len(lit) // 2 - 2:len(lit) // 2 + 3]
        view = np.asarray(VIEW, float)  # towards the camera, as the light directions
        cos_v = test.normals @ view
        for label, image in (("RBF", pred), ("reciprocal floor", rec)):
            sq = ((image[middle] - test.radiance[middle]) ** 2).sum(axis=2)
            cos_l = test.normals @ test.directions[middle].T  # (P, 5)
            half = test.directions[middle] + view
            half /= np.linalg.norm(half, axis=1, keepdims=True)
            grazing = (cos_l.T > 0) & ((cos_l.T < np.cos(np.radians(80)))
                                       | (cos_v < np.cos(np.radians(80)))[None])
            peak = (test.normals @ half.T).T > np.cos(np.radians(10))
            print(f"  {label}: the five median held-out images' squared error: "
                  f"{sq[grazing].sum() / sq.sum():.0%} at pixels with light or view beyond "
                  f"80 deg, {sq[peak].sum() / sq.sum():.0%} at theta_h < 10 deg")
        print(f"  RBF (m_w {fit.m_w:g}): {100 * np.median(per[lit]):.2f} % median")
        merged = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, groups=s.image,
                               merge_radius=merge_radius, reciprocal=True)
        train_rec = render_distant(nearest, size, theta_d_lights(stratified(10)))
        s = samples_from_images(train_rec.normals, train_rec.radiance, train_rec.directions)
        fed = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, groups=s.image)
        pred_fed = render_distant(fed.brdf, size, test.directions).radiance
        print(f"  RBF fed the nearest reciprocal BRDF's images (m_w {fed.m_w:g}): "
              f"{100 * held_out_errors(pred_fed, test.radiance)[1]:.2f} % median off the truth, "
              f"{100 * held_out_errors(pred_fed, rec)[1]:.2f} % off the reciprocal images")
        pred_merged = render_distant(merged.brdf, size, test.directions).radiance
        print(f"  RBF with near pairs merged (merge_radius {merge_radius:g}, m_w {merged.m_w:g}): "
              f"{100 * held_out_errors(pred_merged, test.radiance)[1]:.2f} % median off the "
              f"truth, {100 * held_out_errors(pred_merged, rec)[1]:.2f} % off the reciprocal "
              f"images")
        rows = {"floor (nearest reciprocal)": rec, "RBF": pred, "RBF, near pairs merged":
                pred_merged, "RBF fed reciprocal images": pred_fed}
        print("  per held-out image (% off the truth; * the median image), theta_d (deg): "
              + " ".join(f"{v:5.1f}" for v in np.degrees(stratified(21))))
        for label, image in rows.items():
            e = per_image_errors(image, test.radiance)
            middle = lit[np.argsort(e[lit])][len(lit) // 2]
            print(f"  {label:28s}" + " ".join(
                f"{100 * v:5.2f}" + ("*" if i == middle else " ") for i, v in enumerate(e)))
        e = per_image_errors(pred_fed, rec)
        print(f"  {'RBF fed, off reciprocal':28s}" + " ".join(f"{100 * v:5.2f} " for v in e))
        own = per_image_errors(render_distant(fed.brdf, size, train_rec.directions).radiance,
                               train_rec.radiance)
        print("  RBF fed the reciprocal images, off those input images, theta_d (deg): "
              + ", ".join(f"{np.degrees(t):.1f}: {100 * v:.2f} %"
                          for t, v in zip(stratified(10), own)), flush=True)


def highlight_profile(name: str, size: int, held_out=(10, 11, 12, 14)) -> None:
    """The truth's f_r (1/sr, red) along theta_h at the held-out images' theta_d, and the ratio
    of the fit's (the m_w chosen with the polar form) to it, with and without the polar form,
    for light and view across (phi_d 90 deg) and in (0 deg) the plane of the normal and h."""
    truth = load_truth(name)
    train = render_distant(truth, size, theta_d_lights(stratified(10)))
    s = samples_from_images(train.normals, train.radiance, train.directions)
    polar = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, groups=s.image)
    plain = fit_isotropic(s.wi, s.wo, s.brdf, valid=s.valid, m_w=polar.m_w, angular_weight=None)
    theta_h = np.radians([0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.5, 2.0, 3.0])
    h = np.stack([np.sin(theta_h), 0 * theta_h, np.cos(theta_h)], axis=1)
    across = {90: np.broadcast_to([0.0, 1.0, 0.0], h.shape),
              0: np.stack([np.cos(theta_h), 0 * theta_h, -np.sin(theta_h)], axis=1)}
    print(f"== {name}: f_r along theta_h (deg) " + " ".join(f"{v:6.2f}" for v in
                                                          np.degrees(theta_h))
          + f"; m_w {polar.m_w:g} ==")
    for theta_d in stratified(21)[list(held_out)]:
        for phi_d, t in across.items():
            wi = np.cos(theta_d) * h + np.sin(theta_d) * t
            wo = np.cos(theta_d) * h - np.sin(theta_d) * t
            f = truth.evaluate(wi, wo)[:, 0]
            print(f"theta_d {np.degrees(theta_d):4.1f} phi_d {phi_d:2d} truth        "
                  + " ".join(f"{v:6.3g}" for v in f))
            for label, fit in (("polar form", polar), ("(u, v, w)", plain)):
                print(f"{'':20s} {label:12s} " + " ".join(
                    f"{v:6.3f}" for v in fit.brdf.evaluate(wi, wo)[:, 0] / f))


def sphere_image(truth, env, size):
    normals, mask = sphere_normals(size)
    image = np.zeros(normals.shape)
    image[mask] = shade_distant(truth, normals[mask], *env.sources())
    return image, normals, mask


def hemisphere_image(truth, env, count):
    """The paper's observations: ``count`` normals uniform on the visible hemisphere, those
    beyond 80 deg of the view dropped (``visible_hemisphere_normals``), shaded; as a (1, M, 3)
    image with an all-True mask."""
    normals = visible_hemisphere_normals(count)[None]
    return shade_distant(truth, normals[0], *env.sources())[None], normals, \
        np.ones(normals.shape[:2], bool)


def observations(sphere: int, hemisphere: int, exemplars=None) -> str:
    """What the passive section observes (and, with ``exemplars``, how it fills the
    unconstrained nodes), in words."""
    return ((f"{hemisphere} normals uniform on the visible hemisphere (80 deg)" if hemisphere
             else f"one {sphere} x {sphere} sphere image")
            + ("" if exemplars is None else ", unconstrained nodes from the nearest exemplars ("
               + ("k by leave-one-out" if exemplars == "loo" else f"k = {exemplars}") + ")"))


#: The oracle split's node groups (deg): the truth's reduction put in at all unconstrained
#: nodes, at all constrained ones, and at the unconstrained ones of three bands.
ORACLE_GROUPS = {
    "truth at unseen": lambda seen, th, td: ~seen,
    "at seen": lambda seen, th, td: seen,
    "theta_h < 2": lambda seen, th, td: ~seen & (th < 2),
    "theta_d > 80": lambda seen, th, td: ~seen & (td > 80),
    "theta_d < 10": lambda seen, th, td: ~seen & (td < 10),
}
#: The best single exemplar is searched among this many library members nearest the truth at
#: the unconstrained nodes (RMS log difference), each scored by Eq. 1.
ORACLE_EXEMPLARS = 8


def oracle_split(fit, reduction, truth, library: ExemplarLibrary, error_grid) -> dict:
    """Eq. 1 per-sample (fraction) of the recovered table with the truth's own reduction put in
    at each of ``ORACLE_GROUPS``, and with the unconstrained nodes taken from the one library
    member (fitted at the constrained nodes as ``nearest_exemplars`` fits) that comes closest,
    chosen with the truth: what no exemplar prior can beat."""
    n_t, n_s = fit.brdf.table.shape[:2]
    f = fit.brdf.table.reshape(-1, 3)
    true = reduction.table.reshape(-1, 3)
    seen = fit.adequacy.constrained.ravel()
    t, s = np.meshgrid(np.linspace(0, 1, n_t), np.linspace(0, 1, n_s), indexing="ij")
    th, td = (t ** 2 * 90).ravel(), (s * 90).ravel()

    def err(table):
        return bivariate_error(Bivariate(table.reshape(n_t, n_s, 3)), truth, shape=error_grid)

    out = {}
    for label, group in ORACLE_GROUPS.items():
        g = f.copy()
        at = group(seen, th, td)
        g[at] = true[at]
        out[label] = err(g)
    x = np.log(np.maximum(f, 0).T + library.offset)
    ex = nearest_exemplars(x, node_weights(fit.adequacy.coverage, fit.adequacy.constrained),
                           library.x, len(library.x))
    x_true = np.log(true.T + library.offset)
    closeness = np.sqrt(np.mean((ex.fitted[:, :, ~seen] - x_true[:, ~seen]) ** 2, axis=(1, 2)))
    best = np.inf
    for m in np.argsort(closeness)[:ORACLE_EXEMPLARS]:
        g = f.copy()
        g[~seen] = np.maximum(np.exp(ex.fitted[m][:, ~seen].T) - library.offset, 0.0)
        best = min(best, err(g))
    out["best exemplar"] = best
    return out


def passive_section(out: Path, sphere: int, env_height: int, every: int, error_grid,
                    lam, prior_kind: str, offset: int = 0, n_modes: int = 40,
                    hemisphere: int = 0, reweight=None, reverse: bool = False,
                    exemplars=None, oracle: bool = False) -> None:
    env = EnvironmentMap.load(DATA / "probes" / "grace.hdr",
                              rotation=CAMERA_TO_PROBE).resized(env_height)
    files = {k: p for k, p in measured_files(DATA / "brdfs").items() if k.startswith("merl/")}
    models = {k: load_measured(p) for k, p in files.items()}
    t0 = time.perf_counter()
    reductions = {k: Bivariate.from_brdf(m, 32, 32) for k, m in models.items()}
    observed = observations(sphere, hemisphere, exemplars)
    print(f"\n== passive reflectometry, Fig. 6: {observed} under Grace "
          f"({env_height} x {2 * env_height} texels) per MERL material, prior learned from the "
          f"other {len(models) - 1} (leave-one-out), lam {lam}, reweight {reweight}, exemplars "
          f"{exemplars}; Eq. 1 error on a {error_grid} "
          f"grid, per-sample / pooled reading / per-sample where the environment constrains "
          f"the BRDF (reductions: {time.perf_counter() - t0:.0f} s) ==")
    rows = []
    names = list(models)[offset::every]
    for name in names[::-1] if reverse else names:
        truth = models[name]
        image, normals, mask = (hemisphere_image(truth, env, hemisphere) if hemisphere else
                                sphere_image(truth, env, sphere))
        names_lib = [k for k in reductions if k != name]
        library = [reductions[k] for k in names_lib]
        prior = (learn_modes(library, (32, 32), n_modes=n_modes, name="merl-loo-modes")
                 if prior_kind == "modes" else learn_prior(library, (32, 32), name="merl-loo"))
        nearest = (ExemplarLibrary.from_brdfs(library, (32, 32),
                                              k=None if exemplars in (None, "loo") else exemplars)
                   if exemplars is not None or oracle else None)
        t1 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PassiveWarning)
            fit = passive_reflectometry(image, normals, mask, env, prior=prior, lam=lam,
                                        reweight=reweight if prior_kind == "modes" else None,
                                        exemplars=nearest if exemplars is not None else None)
        t_fit = time.perf_counter() - t1
        seen = fit.adequacy.constrained
        readings = ({}, {"pooled": True}, {"nodes": seen}, {"exclude_grazing_deg": GRAZING})
        e, ep, ec, eg = (bivariate_error(fit.brdf, truth, shape=error_grid, **kw)
                         for kw in readings)
        r, rp, rc, rg = (bivariate_error(reductions[name], truth, shape=error_grid, **kw)
                         for kw in readings)
        rows.append((name, e, r, ep, rp, ec, rc, eg, rg))
        print(f"{name[5:]:26s} recovered {e:8.1%} /{ep:6.1%} /{ec:7.1%} /{eg:7.1%}  reduction "
              f"{r:7.1%} /{rp:6.1%} /{rc:6.1%} /{rg:6.1%}  lam {fit.lam:5.0e} residual "
              f"{fit.residual.mean():6.2%} unconstrained {np.mean(~seen):4.0%}  {t_fit:4.0f} s"
              + ("" if fit.exemplars is None else
                 f"  k {len(fit.exemplars.index)}: " + ", ".join(
                     names_lib[j][5:] for j in fit.exemplars.index[:3])),
              flush=True)
        if oracle:
            split = oracle_split(fit, reductions[name], truth, nearest, error_grid)
            print("  oracle split: " + ", ".join(f"{k} {v:.1%}" for k, v in split.items()),
                  flush=True)
    summarise(rows)
    plot_fig6(out / "passive_fig6.png", rows, env_height, observed)


def exemplar_loo_section(env_height: int, sphere: int) -> None:
    """Can a MERL material's seen nodes predict its unseen ones better through its nearest
    exemplars than through the modes prior? Each of the 100 left out in turn, its own 32 x 32
    reduction given at the nodes one ``sphere`` px image under Grace constrains: the RMS log
    error (log(f + offset), the prior's space) at the other nodes of the mean of its k nearest
    exemplars among the other 99 (``nearest_exemplars``) and of the modes prior's conditional
    mean (``learn_modes`` of the other 99: mean_u - Q_uu^-1 Q_us (x_s - mean_s))."""
    env = EnvironmentMap.load(DATA / "probes" / "grace.hdr",
                              rotation=CAMERA_TO_PROBE).resized(env_height)
    files = {k: p for k, p in measured_files(DATA / "brdfs").items() if k.startswith("merl/")}
    reductions = [Bivariate.from_brdf(load_measured(p), 32, 32) for p in files.values()]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PassiveWarning)
        probe = passive_reflectometry(*sphere_image(reductions[0], env, sphere), env,
                                      prior=learn_modes(reductions[1:], (32, 32)))
    w = node_weights(probe.adequacy.coverage, probe.adequacy.constrained)
    seen, unseen = w > 0, w <= 0
    x = ExemplarLibrary.from_brdfs(reductions, (32, 32)).x
    ks = (1, 3, 5, 10, 20, 40)
    knn, cond = np.zeros((len(x), len(ks))), np.zeros(len(x))
    for j in range(len(x)):
        others = np.delete(x, j, axis=0)
        prior = learn_modes([b for i, b in enumerate(reductions) if i != j], (32, 32))
        Q = prior.precision()
        gain = np.linalg.solve(Q[np.ix_(unseen, unseen)], Q[np.ix_(unseen, seen)])
        pred = prior.mean[unseen] - (x[j][:, seen] - prior.mean[seen]) @ gain.T
        cond[j] = np.sqrt(np.mean((pred - x[j][:, unseen]) ** 2))
        ex = nearest_exemplars(x[j], w, others, max(ks))
        for i, k in enumerate(ks):
            mean = np.einsum("k,kcn->cn", ex.weights[:k] / ex.weights[:k].sum(),
                             ex.fitted[:k, :, unseen])
            knn[j, i] = np.sqrt(np.mean((mean - x[j][:, unseen]) ** 2))
    print(f"\n== the unseen nodes ({unseen.mean():.0%}) of each MERL material from its own seen "
          f"ones, leave-one-out; RMS log error, median / mean over the 100 ==")
    print(f"modes prior's conditional mean: {np.median(cond):.3f} / {cond.mean():.3f}")
    for i, k in enumerate(ks):
        print(f"mean of the {k:2d} nearest exemplars: {np.median(knn[:, i]):.3f} / "
              f"{knn[:, i].mean():.3f}; better than the conditional on "
              f"{np.sum(knn[:, i] < cond)} of 100", flush=True)


ROW = re.compile(r"^(\S+)\s+recovered" + r"\s*/?\s*([\d.]+)%" * 4 + r"\s+reduction"
                 + r"\s*/?\s*([\d.]+)%" * 4)


def rows_from_logs(paths) -> list:
    """The per-material rows ``passive_section`` printed, read back from its logs (e.g. the
    two halves of ``--every 2 --offset 0|1``, each also run ``--reverse``), to 0.1 point, one
    row per material: (name, e, r, ep, rp, ec, rc, eg,
    rg) as fractions."""
    rows, seen = [], set()
    for path in paths:
        for line in Path(path).read_text().splitlines():
            m = ROW.match(line)
            if m and m[1] not in seen:   # a material two processes both reached: the same row
                seen.add(m[1])
                v = [float(x) / 100 for x in m.groups()[1:]]
                rows.append(("merl/" + m[1], v[0], v[4], v[1], v[5], v[2], v[6], v[3], v[7]))
    if not rows:
        raise SystemExit(f"no passive rows in {', '.join(map(str, paths))}")
    return rows


def summarise(rows) -> None:
    """Per reading: the median material by recovered - 2 x reduction and how many are within
    the target (2x the reduction's error + 5 points)."""
    for label, i in (("per-sample", 1), ("pooled", 3), ("per-sample, constrained nodes", 5),
                     (f"per-sample, both directions within {90 - GRAZING} deg of the normal", 7)):
        rec, red = np.array([r[i] for r in rows]), np.array([r[i + 1] for r in rows])
        ok = rec <= 2 * red + 0.05
        mid = int(np.argsort(rec - 2 * red)[len(rows) // 2])
        print(f"{label}: median material (by recovered - 2 x reduction) {rows[mid][0]}: "
              f"recovered {rec[mid]:.1%} vs target {2 * red[mid] + 0.05:.1%}; {ok.sum()} of "
              f"{len(rows)} within 2x their reduction's error + 5 points; median recovered "
              f"{np.median(rec):.1%}, median reduction {np.median(red):.1%}")


def plot_fig6(path: Path, rows, env_height, observed: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = sorted(rows, key=lambda r: -r[2])  # decreasing reduction error, as Figs. 3 and 6
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(12, 4.5))
    ax.plot(x, [r[2] for r in rows], "g.-", label="bivariate reduction of the truth (Fig. 3)")
    ax.plot(x, [r[1] for r in rows], "r.-", label=f"recovered from {observed} under Grace "
                                                   f"({env_height} x {2 * env_height})")
    ax.plot(x, [r[5] for r in rows], "r--", lw=1, label="recovered, where the environment "
                                                        "constrains the BRDF")
    ax.plot(x, [2 * r[2] + 0.05 for r in rows], "k:", lw=1, label="target: 2 x reduction + 5 pts")
    ax.plot(x, [r[8] for r in rows], "g:", lw=1, label=f"reduction, directions within "
                                                        f"{90 - GRAZING} deg of the normal")
    ax.plot(x, [r[7] for r in rows], "m:", lw=1, label=f"recovered, directions within "
                                                        f"{90 - GRAZING} deg of the normal")
    ax.set_yscale("log")
    ax.set_xticks(x)
    ax.set_xticklabels([r[0][5:] for r in rows], rotation=90, fontsize=6)
    ax.set_ylabel("relative RMS BRDF error (Eq. 1)")
    ax.set_title("Passive reflectometry on the MERL materials (NBRDF fits), prior leave-one-out "
                 "(Romeiro et al. 2008, Fig. 6)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/zoo"))
    ap.add_argument("--size", type=int, default=100, help="sharing sphere images (px)")
    ap.add_argument("--sphere", type=int, default=48, help="passive sphere image (px)")
    ap.add_argument("--hemisphere", type=int, default=0, metavar="COUNT",
                    help="passive: observe COUNT normals uniform on the visible hemisphere (the "
                         "paper's 8000; 80 deg limit) instead of the --sphere image's pixels")
    ap.add_argument("--env-height", type=int, default=16, help="Grace probe rows (passive)")
    ap.add_argument("--every", type=int, default=1, help="passive: every k-th MERL material")
    ap.add_argument("--error-grid", default="90,90,180",
                    help="passive: (theta_h, theta_d, phi_d) nodes of the Eq. 1 grid")
    ap.add_argument("--lam", default="default",
                    help="passive: the prior's weight: the method's default, 'cv' "
                         "(cross-validated; smoothness prior only) or a number")
    ap.add_argument("--prior", choices=["modes", "smoothness"], default="modes",
                    help="passive: the library's modes of variation in log space (default), "
                         "or Eq. 6's derivative variances")
    ap.add_argument("--reweight", type=int, default=None,
                    help="passive, modes prior: reweighted solves (default MODES_REWEIGHT; 0: "
                         "the plain solve)")
    ap.add_argument("--modes", type=int, default=40, help="passive: modes kept")
    ap.add_argument("--exemplars", default=None, metavar="K|loo",
                    help="passive: fill the unconstrained nodes from the K nearest library "
                         "exemplars ('loo': K by leave-one-out on the library)")
    ap.add_argument("--exemplar-loo", action="store_true",
                    help="passive: the unseen nodes from the seen ones, exemplars against the "
                         "modes prior's conditional, each MERL material left out (instead of "
                         "Fig. 6)")
    ap.add_argument("--oracle", action="store_true",
                    help="passive: print each material's oracle split too")
    ap.add_argument("--offset", type=int, default=0,
                    help="passive: first MERL material (with --every: a second subset)")
    ap.add_argument("--only", choices=["sharing", "passive"])
    ap.add_argument("--angular-weight", default=str(ANGULAR_WEIGHT),
                    help="sharing: the polar form's angular weight, or 'none' for (u, v, w)")
    ap.add_argument("--merge-radius", type=float, default=0.0,
                    help="sharing: the RBF with near pairs merged (fit_isotropic's merge_radius; "
                         "--rgl: the variant it prints, default 0.0075)")
    ap.add_argument("--profile", metavar="NAME",
                    help="sharing: print NAME's highlight profile at held-out theta_d instead")
    ap.add_argument("--rgl", action="store_true",
                    help="sharing: why the RGL rows miss (asymmetry, floors, where the error is)")
    ap.add_argument("--reverse", action="store_true",
                    help="passive: the materials in reverse order (a second process on the same "
                         "subset from its other end; --replot keeps each material's first row)")
    ap.add_argument("--replot", nargs="+", type=Path, metavar="LOG",
                    help="passive: summarise and draw Fig. 6 from the rows earlier runs printed "
                         "(e.g. both halves' logs; --env-height as they ran) instead of running")
    ap.add_argument("--quick", action="store_true", help="small sizes, few materials")
    args = ap.parse_args()
    if not (DATA / "brdfs").is_dir() or not (DATA / "probes").is_dir():
        raise SystemExit(f"needs {DATA / 'brdfs'} and {DATA / 'probes'}")
    if args.quick:
        args.size, args.every = 48, 10
    names = list(analytic_zoo()) + list(SHARING_MEASURED)
    if args.replot:
        rows = rows_from_logs(args.replot)
        summarise(rows)
        plot_fig6(args.out / "passive_fig6.png", rows, args.env_height,
                  observations(args.sphere, args.hemisphere, args.exemplars))
        return
    if args.profile:
        highlight_profile(args.profile, args.size)
        return
    if args.exemplar_loo:
        exemplar_loo_section(args.env_height, args.sphere)
        return
    if args.rgl:
        rgl_section(args.size, args.merge_radius or RGL_MERGE_RADIUS)
        return
    if args.only != "passive":
        sharing_section(names[:3] if args.quick else names, args.size,
                        None if args.angular_weight == "none" else float(args.angular_weight),
                        args.merge_radius)
    if args.only != "sharing":
        grid = tuple(int(v) for v in args.error_grid.split(","))
        passive_section(args.out, args.sphere, args.env_height, args.every,
                        (45, 45, 90) if args.quick else grid,
                        None if args.lam == "default" else
                        args.lam if args.lam == "cv" else float(args.lam),
                        args.prior,
                        args.offset, args.modes, args.hemisphere, args.reweight, args.reverse,
                        None if args.exemplars is None else
                        args.exemplars if args.exemplars == "loo" else int(args.exemplars),
                        args.oracle)


if __name__ == "__main__":
    main()
