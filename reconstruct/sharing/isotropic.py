"""Homogeneous isotropic reflectance sharing (Zickler et al. 2005, Sect. 5, Eq. 5): f(u, v, w)
by greedy linear-RBF interpolation of reflectance samples.

Three choices the paper leaves open decide whether sharp lobes survive (measured on its sphere
experiment, 10 images of 100 x 100 px, 21 held out; ``benchmarks/zoo.py``):

- **Values: log(f_r + offset), not f_r.** A sharp lobe is a spike of 100-1000 x the diffuse
  level only ~20 pixels wide per image. The linear RBF (a biharmonic spline in 3-D) rings and
  smears such a spike whatever the centres: with f_r itself the held-out median error of an
  Ashikhmin-Shirley n = 1000 lobe stayed at 12-37 % for every centre budget (1000-3000),
  block spread (0-1) and w scale (0.03-0.5) tried, and the fit missed even its *own* samples
  (7 % median). In log space the lobe is a smooth bump (a Gaussian is a parabola) and the same
  fit reaches 3.9 %; the greedy residual is weighted by cos theta_i (f_r + offset) so that it
  stays a radiance residual (d f = (f + offset) d log).
- **The w scale of M (Eq. 4) per material.** It sets how strongly samples of neighbouring
  theta_d planes (images) talk to each other: a highlight that varies fast in (u, v) but slowly
  in theta_d wants a small m_w (Ashikhmin-Shirley: 0.25), a retro-reflective lobe that varies
  only with theta_d wants a large one (4: median 16 % at 0.5 -> 1.1 %), and a highlight only
  ~0.5 deg wide (MERL specular-red-phenolic) sags between the theta_d planes of the images
  unless they are brought within its width (0.0625: 23.6 % at 0.25 -> 9.4 %). No single value
  serves all, so ``m_w="auto"`` chooses it from ``M_W_CANDIDATES`` by holding out whole theta_d
  groups of the input (images), as the paper's held-out images are, and keeping the lowest
  error.
- **The metric in (u, v): polar, phi_d weighed less than theta_h** (``ANGULAR_WEIGHT``,
  ``models.polar_points``). An image samples a highlight narrower than its pixels at one to
  three pixels, at theta_h and phi_d that change from image to image (the pixel grid slides
  under the highlight as theta_d changes). Near theta_h = 0 an isotropic BRDF hardly depends on
  phi_d, but (u, v) = sin theta_h (cos 2 phi_d, sin 2 phi_d) puts two samples of equal theta_h
  up to 2 sin theta_h apart, as far as samples of different theta_h: the images' peak samples
  cannot pool into one profile along theta_h, and between the images' planes the peak came out
  low and broad, and not round (specular-red-phenolic, held-out theta_d 49.3 deg: 0.18 x the
  truth at theta_h = 0, 1.3 and 0.53 x at 0.8 deg for phi_d 90 and 0 deg, 4.9 x at the foot,
  1.2 deg; ``benchmarks/zoo.py --profile``). With distances around the disc weighed 0.1 x those
  along it the same fit is within 0.78-1.12 x over 0.4-1 deg at both phi_d (2.2 x at the foot)
  and the held-out median falls 9.4 -> 4.7 %; every other zoo row improves too (docs/zoo.md).
  A sqrt(theta_h) warp of u, v does the opposite (it weighs phi_d 2 x theta_h) and made it worse.

Data that are not reciprocal (``reciprocity``; in practice a gonio-photometer's tables) are
fitted over the points with the un-doubled phi_d too (``models.with_asymmetry``), with
``NON_RECIPROCAL_BUDGET`` x the centres, and the value is
h = f_r cos theta_i / (cos theta_i + min_cos), not f_r. Such tables store f_r cos theta_i, and
where the stored value stays finite to the horizon f_r grows as 1 / cos theta_i past the
terminator rule (``min_cos``), beyond the last sample: at theta_d 45 deg the measured RGL
matte paint keeps 0.0018-0.0014 of its 0.0044 (79-80 deg) at 87-90 deg, and log f_r's
extrapolation gave 0.2-0.8 x that radiance, 40-47 % off on those pixels and most of each
held-out image's error. h
is f_r well above the terminator and the radiance form near it, so its extrapolation holds the
radiance instead. (cos theta_i is no function of the reciprocal (u, v, w), so a reciprocal fit
keeps f_r.) The matte paint's held-out median: 2.75 -> 1.83 % (docs/zoo.md).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..coords import uvw_from_directions
from .fits import MIN_COS, _samples, _values, _w_varies, _weight
from .models import (ANGULAR_WEIGHT, ASYMMETRY_WEIGHT, RbfBRDF, _check_angular_weight,
                     angular_points, with_asymmetry)
from .rbf import RbfFit, SharingError, fit_rbf
from .reciprocity import ReciprocityCheck, check_reciprocity

#: log(f_r + offset) is interpolated with offset = LOG_OFFSET x the median f_r of the samples:
#: small enough that highlights are compressed, large enough that a nearly black channel's
#: noise is not blown up (0.01 and 0.1 gave the same held-out errors on the sharp lobes).
LOG_OFFSET = 0.01
#: w scales ``m_w="auto"`` chooses from (module docstring; 0.0625 and 0.125 for the narrowest
#: highlights).
M_W_CANDIDATES = (0.0625, 0.125, 0.25, 0.5, 1.0, 2.0, 4.0)
#: theta_d groups held out (one at a time, interior ones) when choosing m_w.
M_W_FOLDS = 3
#: Fewer samples than this are fitted with m_w = 0.5 (too few to hold a group out).
MIN_SAMPLES_FOR_CHOICE = 100
#: More distinct w values than this are not images: they are binned into this many groups.
MAX_GROUPS = 64
#: A fit that is not reciprocal gets this many times ``max_centers``: its domain is the
#: reciprocal one twice over (no swap fold), so the same density takes twice the centres.
NON_RECIPROCAL_BUDGET = 2


@dataclass(frozen=True)
class ScaleChoice:
    """How ``m_w="auto"`` chose: each candidate's held-out error.

    Attributes
    ----------
    candidates : tuple of float
        The m_w values tried.
    errors : tuple of float
        Median over the held-out groups of each group's relative RMS radiance error
        (unitless), one per candidate.
    m_w : float
        The winner.
    held_out : int
        Groups held out (one fit per group and candidate).
    """

    candidates: tuple
    errors: tuple
    m_w: float
    held_out: int


@dataclass(frozen=True, eq=False)
class IsotropicFit:
    """Result of :func:`fit_isotropic`.

    Attributes
    ----------
    brdf : RbfBRDF
        The recovered BRDF (f_r, 1/sr).
    fit : RbfFit
        The RBF fit over (u, v, w), or their ``polar_points`` when ``brdf.angular_weight`` is
        set (of log(v + offset) when ``brdf.log_offset`` is set; v is f_r, or
        f_r cos theta_i / (cos theta_i + ``brdf.horizon``) when that is set).
    n_used, n_dropped : int
        Samples used / dropped (terminator, invalid, below the horizon).
    m_w : float
        The w scale of M used.
    scale_choice : ScaleChoice or None
        With ``m_w="auto"``: the candidates' held-out errors.
    reciprocity : ReciprocityCheck or None
        With ``reciprocal="auto"`` and at least ``MIN_SAMPLES_FOR_CHOICE`` weighted samples: how
        far the samples' two orderings of a pair disagree, which decided whether ``brdf`` is
        reciprocal (None: too few to tell, so reciprocal).
    """

    brdf: RbfBRDF
    fit: RbfFit
    n_used: int
    n_dropped: int
    m_w: float
    scale_choice: ScaleChoice | None = None
    reciprocity: ReciprocityCheck | None = None

    def brdf_with(self, n_centers: int) -> RbfBRDF:
        """The BRDF refitted on the first ``n_centers`` greedy centres (error vs centre count)."""
        return RbfBRDF(self.fit.refit(n_centers), self.brdf.log_offset,
                       self.brdf.angular_weight, self.brdf.asymmetry_weight, self.brdf.horizon)

    def report(self) -> str:
        values = "f_r" if self.brdf.horizon is None else \
            f"f_r cos theta_i / (cos theta_i + {self.brdf.horizon:g})"
        if self.brdf.log_offset is not None:
            values = f"log({values} + {self.brdf.log_offset:.3g})"
        choice = "" if self.scale_choice is None else " (chosen by held-out images: " + ", ".join(
            f"{m:g}: {e:.2%}" for m, e in zip(self.scale_choice.candidates,
                                             self.scale_choice.errors)) + ")"
        space = ("(u, v, w)" if self.brdf.angular_weight is None else
                 f"(u, v, w) in polar form, angular weight {self.brdf.angular_weight:g}")
        if self.brdf.asymmetry_weight is not None:
            space += f" and the un-doubled phi_d, weight {self.brdf.asymmetry_weight:g}"
        if self.reciprocity is not None:
            space += f" (samples {self.reciprocity.report()})"
        return (f"isotropic RBF BRDF of {values} over {space} from {self.n_used} samples "
                f"({self.n_dropped} dropped), m_w {self.m_w:g}{choice}: " + self.fit.report())


def _groups(uvw: np.ndarray, groups) -> np.ndarray:
    """Integer group per sample: the caller's (e.g. image index), else one per distinct w (an
    image of the paper's experiment), else ``MAX_GROUPS`` quantile bins of w."""
    if groups is not None:
        return np.unique(np.asarray(groups), return_inverse=True)[1].reshape(-1)
    w = np.round(uvw[:, 2], 6)
    uniq, inverse = np.unique(w, return_inverse=True)
    if len(uniq) <= MAX_GROUPS:
        return inverse.reshape(-1)
    ranks = np.argsort(np.argsort(w, kind="stable"), kind="stable")
    return ranks * MAX_GROUPS // len(w)


def _scale(points: np.ndarray, m_w: float) -> tuple:
    """Diagonal of M for ``points`` whose last column is w: ones, then m_w."""
    return (1.0,) * (points.shape[1] - 1) + (m_w,)


def _choose_m_w(points, target, weight, factor, values, decode, groups, max_centers,
                rng, merge_radius) -> ScaleChoice:
    """Hold out interior theta_d groups one at a time; fit the rest with each m_w candidate
    (half the centre budget); score the relative radiance error on the held-out group.
    ``points``: the fit's points, w last; ``values`` (decoded ``target``) times ``factor`` is
    radiance."""
    n_groups = int(groups.max()) + 1
    by_w = np.argsort(np.bincount(groups, points[:, -1], n_groups) / np.bincount(groups, None,
                                                                                 n_groups))
    picks = np.unique(np.round(np.linspace(0, n_groups - 1, M_W_FOLDS + 2)[1:-1]).astype(int))
    held = [g for g in by_w[picks] if 0 < np.count_nonzero(groups == g) < len(groups)]
    budget = max(6, max_centers // 2)
    errors = []
    for m_w in M_W_CANDIDATES:
        per_group = []
        for g in held:
            test = groups == g
            model = fit_rbf(points[~test], target[~test], scale=_scale(points, m_w),
                            weight=weight[~test], max_centers=budget, rng=rng,
                            merge_radius=merge_radius).model
            pred = decode(model(points[test]))
            c = factor[test, None]
            per_group.append(np.sqrt(np.sum((c * (pred - values[test])) ** 2)
                                     / max(np.sum((c * values[test]) ** 2), 1e-300)))
        errors.append(float(np.median(per_group)))
    best = int(np.argmin(errors))
    return ScaleChoice(tuple(M_W_CANDIDATES), tuple(errors), M_W_CANDIDATES[best], len(held))


def fit_isotropic(wi, wo, brdf, *, max_centers: int = 1000, m_w="auto", log_values: bool = True,
                  angular_weight: float | None = ANGULAR_WEIGHT, groups=None, weight=None,
                  valid=None, min_cos: float = MIN_COS, tol=None, smoothing: float = 0.0, rng=0,
                  merge_radius: float = 0.0, reciprocal="auto",
                  progress: Callable[[int, int], None] | None = None) -> IsotropicFit:
    """Homogeneous isotropic BRDF f(u, v, w) by greedy linear-RBF interpolation (Sect. 5, Eq. 5).

    Parameters
    ----------
    wi, wo : array_like, (S, 3)
        Local unit directions to the light / camera (normal = +z).
    brdf : array_like, (S, 3) or (S,)
        f_r samples, 1/sr (negative values, from noise, count as 0 in the log domain).
    max_centers : int
        Centre budget (the paper: < 1000 suffice for 10 sphere images); a fit that is not
        reciprocal gets ``NON_RECIPROCAL_BUDGET`` x it.
    m_w : float or "auto"
        Scale of the w = 2 theta_d / pi axis, M = diag(1, 1, m_w) (Eq. 4; the paper's typical
        values 0.1-0.5), diag(1, 1, 1, m_w) over the polar points. "auto": chosen from
        ``M_W_CANDIDATES`` by held-out theta_d groups (module docstring; costs ``M_W_FOLDS`` x 7
        fits of half the budget). Needs at least three groups (images) and
        ``MIN_SAMPLES_FOR_CHOICE`` samples; with fewer, 0.5.
    log_values : bool
        Interpolate log(f_r + offset) (module docstring); False: f_r as the paper wrote it.
        (A fit that is not reciprocal interpolates h, below, in place of f_r.)
    angular_weight : float in (0, 1) or None
        Fit over ``polar_points(uvw, angular_weight)``: distances in phi_d at fixed theta_h
        weigh this much of distances in sin theta_h (module docstring); None: over (u, v, w)
        as the paper wrote it.
    groups : array_like of int, (S,), optional
        The image (or any theta_d group) of each sample, for ``m_w="auto"``; default: samples
        of one w value form a group.
    weight : array_like, (S,), optional
        Extra non-negative weight per sample (multiplies cos theta_i).
    valid : array_like of bool, (S,), optional
        False drops a sample (it may hold NaN).
    min_cos : float
        Samples with cos theta_i below this are dropped (``fits`` module docstring). A fit that
        is not reciprocal interpolates f_r cos theta_i / (cos theta_i + min_cos) (module
        docstring).
    tol, smoothing, rng, merge_radius, progress
        As :func:`reconstruct.sharing.fit_rbf` (``tol`` in the fitted values' units,
        ``merge_radius`` over the fit's scaled points; the held-out fits of ``m_w="auto"`` use
        it too). ``merge_radius`` > 0 is not the default: on the zoo it trades one row for
        another (docs/zoo.md, "The two RGL files").
    reciprocal : bool or "auto"
        True: f(wi, wo) = f(wo, wi) by construction, as the paper's (u, v, w). False: the points
        carry the un-doubled phi_d too (``models.with_asymmetry``, weight ``ASYMMETRY_WEIGHT``),
        so the fit can follow measured data whose two orderings differ. "auto": False only
        where ``reciprocity.check_reciprocity``, given at least ``MIN_SAMPLES_FOR_CHOICE``
        weighted samples, finds the samples' orderings disagree beyond
        their sampling and noise (a gonio-photometer's tables can; a physical surface seen by
        a camera should not).

    Returns
    -------
    IsotropicFit

    Raises
    ------
    SharingError
        Mis-shaped or non-finite input; all samples at one theta_d (one light/view pair: w is
        not sampled, the fit would be undetermined along it); too few samples; a bad ``m_w``
        or ``groups``; ``angular_weight`` outside (0, 1).
    """
    s = _samples(wi, wo, valid, min_cos)
    values = _values("brdf", brdf, len(s.wi), s.keep)
    w = _weight(s, weight)
    k = s.keep
    uvw = uvw_from_directions(s.wi[k], s.wo[k])
    if not _w_varies(uvw):
        raise SharingError("wi, wo: every sample has the same theta_d (one light/view pair), so "
                           "the w axis of (u, v, w) is not sampled; a homogeneous BRDF needs at "
                           "least two theta_d (use fit_spatial for the single-image case)")
    if not (m_w == "auto" or (isinstance(m_w, (int, float)) and m_w > 0)):
        raise SharingError(f"m_w must be > 0 or 'auto', got {m_w!r}")
    _check_angular_weight(angular_weight)
    if reciprocal not in (True, False, "auto"):
        raise SharingError(f"reciprocal must be True, False or 'auto', got {reciprocal!r}")
    if groups is not None and np.shape(groups) != (len(s.wi),):
        raise SharingError(f"groups must have shape ({len(s.wi)},), got {np.shape(groups)}")
    f = values[k]
    check = None
    voting = (f.mean(axis=1) > 0) & (w[k] > 0)   # the samples the fit weighs
    if reciprocal == "auto" and np.count_nonzero(voting) >= MIN_SAMPLES_FOR_CHOICE:
        check = check_reciprocity(s.wi[k][voting], s.wo[k][voting], f[voting])
    points = angular_points(uvw, angular_weight)
    cos_i = s.cos_i[k]
    factor = cos_i          # radiance under unit irradiance = factor x the interpolated value
    asymmetry = horizon = None
    budget = max_centers
    if reciprocal is False or (check is not None and not check.reciprocal):
        asymmetry = ASYMMETRY_WEIGHT
        points = with_asymmetry(points, s.wi[k], s.wo[k], asymmetry)
        budget = NON_RECIPROCAL_BUDGET * max_centers
        if min_cos > 0:
            horizon = min_cos
            factor = cos_i + horizon
            f = f * (cos_i / factor)[:, None]
    weight_q = w[k] * (factor / cos_i)
    if log_values:
        positive = f[f > 0]
        offset = LOG_OFFSET * (float(np.median(positive)) if positive.size else 1.0)
        clipped = np.maximum(f, 0.0)
        target = np.log(clipped + offset)
        fit_weight = weight_q * (clipped.mean(axis=1) + offset)

        def decode(g):
            return np.maximum(np.exp(np.minimum(g, 700.0)) - offset, 0.0)
    else:
        offset, target, fit_weight = None, f, weight_q

        def decode(g):
            return np.maximum(g, 0.0)
    choice = None
    if m_w == "auto":
        labels = _groups(uvw, None if groups is None else np.asarray(groups)[k])
        if labels.max() >= 2 and len(uvw) >= MIN_SAMPLES_FOR_CHOICE:
            choice = _choose_m_w(points, target, fit_weight, factor, f, decode, labels,
                                 budget, rng, merge_radius)
        m_w = choice.m_w if choice is not None else 0.5
    fit = fit_rbf(points, target, scale=_scale(points, m_w), weight=fit_weight,
                  max_centers=budget, tol=tol, smoothing=smoothing, rng=rng,
                  progress=progress, merge_radius=merge_radius)
    n_used = int(k.sum())
    return IsotropicFit(RbfBRDF(fit.model, offset, angular_weight, asymmetry, horizon), fit,
                        n_used, len(s.wi) - n_used, float(m_w), choice, check)
