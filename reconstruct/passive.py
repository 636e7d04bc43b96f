"""Passive reflectometry after Romeiro, Vasilyev and Zickler, ECCV 2008.

A homogeneous, isotropic BRDF, reduced to a bivariate function f(theta_h, theta_d) on a uniform
grid in s = 2 theta_d / pi, t = sqrt(2 theta_h / pi), recovered from one (or more) HDR images
of a known curved object under a known distant environment (a light probe); no active lighting.

1. Observations: ``n_normals`` pixels of the object, uniform over its visible surface area
   (pixel weight 1 / cos of the view angle), those more than ``max_view_angle_deg`` from the
   view dropped (low signal, unreliable normals). For a synthetic experiment the paper's own
   set, normals uniform on the visible hemisphere (``visible_hemisphere_normals``), passes as
   a (1, M, 3) image.
2. Lighting matrix (Eqs. 2-5, ``passive_lighting.lighting_matrix``): one row per observation,
   one column per node, per colour channel, from every texel of the environment map; built over
   blocks of observations and reduced to the normal equations block by block
   (``passive_lighting.lighting_sums``), so the rows are never held whole (but for ``lam="cv"``,
   whose folds are rows).
3. Eq. 6: non-negative least squares with spatially varying Tikhonov smoothness on the s- and
   t-differences, weighted by the inverse standard deviation learned per node from a BRDF
   library (``passive_prior``), solved twice (a diffuse-preferring and a gloss-preferring
   prior), keeping the lower residual. With the prior the problem is strictly convex, so an
   exact active-set solve replaces the paper's iterative one started from a Lambertian BRDF
   (that best constant BRDF is still reported: ``PassiveFit.lambertian``). Or, given a
   ``ModesPrior`` (a library's modes of variation in log space, the paper's named
   alternative; ``passive_modes``), the posterior mode under it; with ``reweight`` solved
   again with each pixel's noise grown by its misfit under the last solve (what the bivariate
   table cannot follow, a sharp lobe's highlight, counts for less).
4. Adequacy (Sect. 3.1): singular values and rank of L, per-node coverage against a uniform
   environment, the poorly observed parts of the domain (specular, retro, grazing), and
   warnings in words.

The data term is divided by the mean irradiance and the number of observations, so the one
regularisation weight ``lam`` of Eq. 6 serves environments of any brightness and any
observation count (the paper also kept one weight for all its results). A ``ModesPrior``'s
weight is instead ``MODES_NOISE`` / observations: a fixed relative noise per pixel, so that
more pixels weigh more against the prior, as in the paper's plain sum over pixels.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from .brdf import BRDF, Bivariate, TabulatedIsotropic
from .coords import from_halfway_difference
from .envmap import LUMINANCE, EnvironmentMap
from .passive_lighting import (check_grid, check_sources, lighting_matrix, lighting_predictions,
                               lighting_sums)
from .passive_exemplars import ExemplarLibrary, Exemplars, fill_unconstrained
from .passive_modes import ModesPrior, learn_modes, solve_modes
from .passive_prior import PRIOR_KINDS, SmoothnessPrior, default_prior, learn_prior

__all__ = ["passive_reflectometry", "PassiveFit", "Adequacy", "UnconstrainedBand", "PassiveInputError",
           "PassiveWarning", "lighting_matrix", "learn_prior", "learn_modes", "ModesPrior",
           "bivariate_error", "visible_hemisphere_normals", "ExemplarLibrary"]

#: Regularisation weight of Eq. 6 for the normalised data term when ``lam`` is a number: tuned
#: once with the analytic default priors, on materials and an environment outside the test and
#: benchmark sets (docs/architecture.md). ``lam="cv"`` chooses it per problem instead (not
#: the default: see ``passive_reflectometry``).
LAMBDA = 1e-6
#: Candidate weights of ``lam="cv"`` (one per decade) and its number of observation folds.
CV_LAMBDAS = 10.0 ** np.arange(-11, -3)
CV_FOLDS = 4
#: Noise of a ``ModesPrior``'s data term: the variance of a pixel's misfit over the data's mean
#: square (the bivariate approximation's, not the sensor's). Its weight is MODES_NOISE / the
#: observations, so that more pixels weigh more, as they should: a weight fixed per unit of the
#: data's mean square (1e-5 before) made the prior 4x stronger per pixel on a 96 px sphere
#: than on a 48 px one. 5e-3 (a 7 % misfit per pixel; 2.8e-6 at the 1,764 pixels of a 48 px
#: sphere) was chosen on every 10th MERL material under Grace: 1e-5 / 3e-6 / 1e-6 at 1,764
#: pixels put 4 / 4 / 2 of 10 within the Fig. 6 target, 3e-6 with the lower errors (docs/zoo.md).
#: Cross-validation over pixels cannot choose it: a weaker prior frees what only the
#: unobserved nodes feel, so held-out pixels prefer the weakest weights, where those nodes run
#: off by factors of 1e4 to 1e16.
MODES_NOISE = 5e-3
#: Reweighted solves after the first with a ``ModesPrior`` (``reweight``). Off by default: on a
#: 48 px sphere's pixels one pass lowers a sharp lobe's error (MERL blue-acrylic 58.5 -> 34.4 %)
#: but raises alum-bronze's 26.1 -> 28.0 % and takes one of test_passive_merl's two Fig. 6
#: materials out of its target; on the paper's uniform normals it leaves the moderate ones
#: within 1.6 points (docs/zoo.md).
MODES_REWEIGHT = 0
#: Maps with more texels are area-averaged to 2 x 181^2 (~65,000: the paper's 32,000 directions
#: per visible hemisphere); the lighting matrix costs time linear in the texel count.
MAX_TEXELS = 65536
#: A prior later in the list (less smooth: "glossy" after "diffuse") wins only with a residual
#: below this fraction of the current best. The paper keeps the lowest residual, but a weaker
#: prior always fits the data a little better, and on a matte material it does so by
#: inventing structure where the data are silent (Oren-Nayar under Ennis: residual 0.47 % vs
#: 0.48 %, Eq. 1 error 360 % vs 7 %); glossy materials win by factors of 3-20.
PRIOR_MARGIN = 0.8
#: Fewer usable observations than this is an error; fewer than ``FEW_NORMALS`` a warning.
MIN_NORMALS = 100
FEW_NORMALS = 1000
#: A node is poorly observed below this fraction of the light a uniform environment gives it.
POOR_COVERAGE = 0.1
#: Relative RMS residual above which the environment and the image disagree (probe rotated
#: against the object, wrong normals, a non-homogeneous object).
RESIDUAL_WARN = 0.05
#: Observations seeing more untrusted (``environment_weight`` < 1) hemisphere than this drop.
MAX_UNTRUSTED = 0.02
#: Effective rank below this fraction of the nodes warns (one orthographic image of a sphere
#: under real probes: Grace 328 / 1024 at 8000 normals; three point lights: ~10 %).
RANK_WARN = 0.25
#: Fewer sources than this carrying 95 % of the light is "a few point sources".
FEW_SOURCES = 30
#: The regions of Sect. 3.1: (t, s) masks on the node grid.
REGIONS = {
    "specular (theta_h < 5 deg)": lambda t, s: t < np.sqrt(5 / 90),
    "retro (theta_d < 10 deg)": lambda t, s: s < 10 / 90,
    "grazing (theta_d > 70 deg)": lambda t, s: s > 70 / 90,
}


class PassiveInputError(ValueError):
    """Bad input to passive reflectometry; the message names the argument."""


class PassiveWarning(UserWarning):
    """The recovered BRDF may be poorly constrained (see ``Adequacy.warnings``)."""


@dataclass(frozen=True)
class UnconstrainedBand:
    """Nodes of one theta_d band (deg, ``[lo, hi)``) the environment lit too little to constrain
    (coverage < ``POOR_COVERAGE`` or never observed): their theta_h ranges (deg, e.g. ``"0-4,
    61-90"``) and their share of the band's nodes (0-1)."""

    theta_d_deg: tuple[int, int]
    theta_h_deg: str
    poorly_lit_share: float


@dataclass(frozen=True, eq=False)
class Adequacy:
    """How well an environment and a shape pose the problem (Sect. 3.1).

    Attributes
    ----------
    singular_values : ndarray (n_t n_s,)
        Of the green channel's lighting matrix, scaled by the mean irradiance and sqrt(rows),
        descending (BRDF units: 1/sr of f give 1/sr of radiance / irradiance).
    effective_rank : int
        Singular values above 1e-3 of the largest.
    condition : float
        Largest / smallest singular value (inf when rank-deficient).
    coverage : ndarray (n_t, n_s)
        Light each node receives relative to a uniform environment on the same normals (1:
        as well observed as under a white sky; NaN: the shape never observes the node).
    poorly_observed : dict
        Region name -> fraction of its observable nodes with coverage < ``POOR_COVERAGE``.
    effective_sources : int
        How many of the brightest sources (texels) carry 95 % of the luminous flux: a few for
        isolated point lights; hundreds or more for a real probe, even one with bright lamps
        (Grace Cathedral at 64 x 128: lamps carry half the light, yet 95 % takes 3,222 texels).
    n_observations : int
    warnings : tuple of str
    """

    singular_values: np.ndarray
    effective_rank: int
    condition: float
    coverage: np.ndarray
    poorly_observed: dict
    effective_sources: int
    n_observations: int
    warnings: tuple = ()

    @property
    def constrained(self) -> np.ndarray:
        """(n_t, n_s) bool: nodes with coverage >= ``POOR_COVERAGE``, the part of the BRDF the
        environment observed; elsewhere the recovered values are the prior's extrapolation."""
        with np.errstate(invalid="ignore"):
            return self.coverage >= POOR_COVERAGE

    def unconstrained_bands(self) -> list["UnconstrainedBand"]:
        """Where the environment did not constrain the BRDF: per theta_d band of 10 deg that
        has nodes outside ``constrained``, their theta_h ranges (deg) and their share of the
        band's nodes."""
        n_t, n_s = self.coverage.shape
        theta_h = np.linspace(0, 1, n_t) ** 2 * 90
        theta_d = np.linspace(0, 1, n_s) * 90
        bad = ~self.constrained
        bands = []
        for lo in range(0, 90, 10):
            cols = (theta_d >= lo) & (theta_d < lo + 10 if lo < 80 else theta_d <= 90)
            rows = bad[:, cols].any(axis=1)
            if rows.any():
                bands.append(UnconstrainedBand((lo, lo + 10), _ranges(theta_h, rows),
                                               float(bad[:, cols].mean())))
        return bands

    def unconstrained_ranges(self) -> str:
        """:meth:`unconstrained_bands` in words."""
        parts = [f"theta_d {b.theta_d_deg[0]}-{b.theta_d_deg[1]}: theta_h {b.theta_h_deg}"
                 for b in self.unconstrained_bands()]
        return "; ".join(parts) if parts else "none"

    def report(self) -> str:
        """The headline figures and warnings, one per line."""
        regions = ", ".join(f"{k}: {v:.0%}" for k, v in self.poorly_observed.items())
        lines = [f"observations {self.n_observations}, rank {self.effective_rank}/"
                 f"{len(self.singular_values)}, condition {self.condition:.3g}, sources "
                 f"carrying 95 % of the light {self.effective_sources}",
                 f"poorly observed: {regions}",
                 f"not constrained by the environment ({np.mean(~self.constrained):.0%} of the "
                 f"nodes, prior only; deg): {self.unconstrained_ranges()}"]
        return "\n".join(lines + [f"warning: {w}" for w in self.warnings])


@dataclass(frozen=True, eq=False)
class PassiveFit:
    """Result of ``passive_reflectometry``.

    Attributes
    ----------
    brdf : Bivariate
        The recovered BRDF, f_r in 1/sr, table (n_t, n_s, 3); usable by the renderer.
    residual : ndarray (3,)
        Relative RMS residual ||I - L f|| / ||I|| per channel of the winning solve.
    prior : str
        Which prior won ("diffuse", "glossy", or a custom prior's name).
    residuals : dict
        Prior name -> (3,) residual of each solve.
    lambertian : ndarray (3,)
        The best constant BRDF (1/sr), the solves' starting point.
    adequacy : Adequacy
    converged : bool
        Every solve met its tolerance.
    lam : float
        Regularisation weight used (the cross-validated one for ``lam="cv"``).
    warnings : tuple of str
    exemplars : Exemplars or None
        With ``exemplars``: the library members whose mean filled the unconstrained nodes.
    """

    brdf: Bivariate
    residual: np.ndarray
    prior: str
    residuals: dict
    lambertian: np.ndarray
    adequacy: Adequacy
    converged: bool
    lam: float
    warnings: tuple = field(default=())
    exemplars: Exemplars | None = None

    def report(self) -> str:
        """Headline figures: residuals, prior, adequacy, warnings."""
        res = ", ".join(f"{k}: {np.mean(v):.3%}" for k, v in self.residuals.items())
        return (f"bivariate BRDF {self.brdf.table.shape[:2]}, prior {self.prior} "
                f"(residuals {res}), Lambertian albedo {np.round(self.lambertian * np.pi, 4)}"
                f", converged {self.converged}\n" + self.adequacy.report())


def bivariate_error(estimate: BRDF, truth: BRDF, *, shape=(90, 90, 180),
                    exclude_grazing_deg: float = 0.0, pooled: bool = False,
                    nodes=None) -> float:
    """Relative RMS BRDF error of ``estimate`` against ``truth`` (Romeiro et al. Eq. 1).

    Over the (theta_h, theta_d, phi_d) nodes of a MERL-layout grid of ``shape`` (theta_h
    square-root warped, ``TabulatedIsotropic``'s positions) where ``truth`` is defined and > 0,
    pooling the three channels. The extracted equation is garbled (one sum sign, a fraction
    whose denominator is f(theta_h, theta_d, phi_d)^2, no 1/N); it admits two readings:

    - ``pooled=False`` (default): sqrt(mean of ((f - f_est) / f)^2), every sample's relative
      difference counting alike. A few samples where the truth is tiny dominate it (an NBRDF
      fit near the horizon, where MERL has no data, falls to ~0.005).
    - ``pooled=True``: sqrt(sum (f - f_est)^2 / sum f^2), the RMS difference relative to the
      RMS value, "relative RMS" without a sample count; the highlight, where f is large,
      dominates it.

    Parameters
    ----------
    estimate, truth : BRDF
    shape : (int, int, int)
        Grid (n_theta_h, n_theta_d, n_phi_d); the MERL database's by default.
    exclude_grazing_deg : float
        Leave out samples with either direction within this many degrees of the horizon.
    pooled : bool
        Which reading (above).
    nodes : ndarray (n_t, n_s) bool, optional
        Keep only samples whose nearest bivariate node is True (e.g. ``Adequacy.constrained``:
        the error where the environment observed the BRDF, leaving out what only the prior
        says). The node grid is the passive one: t = sqrt(2 theta_h / pi), s = 2 theta_d / pi,
        both on [0, 1].

    Returns
    -------
    float
        Unitless (0.05 is 5 %).
    """
    if not (isinstance(estimate, BRDF) and isinstance(truth, BRDF)):
        raise PassiveInputError("estimate and truth must be reconstruct BRDFs")
    if not 0 <= exclude_grazing_deg < 90:
        raise PassiveInputError(f"exclude_grazing_deg must be in [0, 90), got "
                                f"{exclude_grazing_deg!r}")
    angles = TabulatedIsotropic(np.zeros((*shape, 3))).node_angles()
    th, td, pd = np.meshgrid(*angles, indexing="ij")
    wi, wo = from_halfway_difference(th, 0.0, td, pd)
    lo = np.sin(np.radians(exclude_grazing_deg))
    ok = truth.defined(wi, wo) & (wi[:, 2] > lo) & (wo[:, 2] > lo)
    if nodes is not None:
        keep = np.asarray(nodes)
        if keep.ndim != 2 or keep.dtype != bool or min(keep.shape) < 2:
            raise PassiveInputError(f"nodes must be a 2-D bool array (n_t, n_s), got "
                                    f"{keep.dtype} {keep.shape}")
        n_t, n_s = keep.shape
        i = np.rint(np.sqrt(th.ravel() / (np.pi / 2)) * (n_t - 1)).astype(int)
        j = np.rint(td.ravel() / (np.pi / 2) * (n_s - 1)).astype(int)
        ok &= keep[i, j]
    f = truth.evaluate(wi[ok], wo[ok])
    g = estimate.evaluate(wi[ok], wo[ok])
    pos = f > 0
    if not pos.any():
        raise PassiveInputError("truth is 0 or undefined everywhere on the grid")
    f, g = f[pos], g[pos]
    if pooled:
        return float(np.sqrt(np.sum((f - g) ** 2) / np.sum(f ** 2)))
    return float(np.sqrt(np.mean(((f - g) / f) ** 2)))


def visible_hemisphere_normals(count: int = 8000, *, view_dir=(0.0, 0.0, -1.0),
                               max_view_angle_deg: float = 80.0) -> np.ndarray:
    """The paper's observation set (Sect. 4): ``count`` normals uniform over the hemisphere
    facing the camera, those more than ``max_view_angle_deg`` from ``view_dir`` discarded.

    A Fibonacci lattice, uniform in area (equal steps of cos of the view angle, golden-angle
    azimuths), not the pixels of an image: an orthographic sphere's pixels are uniform in the
    image, i.e. ~cos of the view angle on the hemisphere, few near grazing (1,764 within 80 deg
    at 48 px). Pass them as a (1, M, 3) "image" of normals with an all-True mask.

    Parameters
    ----------
    count : int
        Normals on the whole visible hemisphere before the discard (the paper's 8,000); about
        ``count`` x (1 - cos ``max_view_angle_deg``) are returned (6,611 at 80 deg).
    view_dir : (3,)
        Unit direction from the surface to the camera (default (0, 0, -1): an orthographic
        camera looking along +z, OpenCV camera frame); the normals' frame.
    max_view_angle_deg : float
        In (0, 90).

    Returns
    -------
    ndarray (M, 3)
        Unit normals n with n . view_dir >= cos(``max_view_angle_deg``).
    """
    if not (isinstance(count, (int, np.integer)) and count >= 1):
        raise PassiveInputError(f"count must be a positive int, got {count!r}")
    if not 0 < max_view_angle_deg < 90:
        raise PassiveInputError(f"max_view_angle_deg must be in (0, 90), got "
                                f"{max_view_angle_deg!r}")
    v = np.asarray(view_dir, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or abs(np.linalg.norm(v) - 1) > 1e-3:
        raise PassiveInputError(f"view_dir must be a unit 3-vector, got {view_dir!r}")
    v = v / np.linalg.norm(v)
    i = np.arange(count) + 0.5
    cos_view = 1.0 - i / count                         # equal areas on the hemisphere
    keep = cos_view >= np.cos(np.radians(max_view_angle_deg))
    cos_view, i = cos_view[keep], i[keep]
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    r = np.sqrt(1.0 - cos_view ** 2)
    # an orthonormal frame (a, b, v) about the view direction
    a = np.cross(v, [1.0, 0, 0] if abs(v[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(v, a)
    return (r * np.cos(phi))[:, None] * a + (r * np.sin(phi))[:, None] * b + cos_view[:, None] * v


def passive_reflectometry(image, normals, mask, environment, *, view_dirs=None, grid=(32, 32),
                          n_normals=8000, max_view_angle_deg=80, prior=None, two_priors=True,
                          environment_weight=None, lam=None, reweight=None, exemplars=None,
                          rng=0, progress=None, map_blocks=None) -> PassiveFit:
    """Recover a bivariate BRDF from one HDR image of a known shape under a known environment.

    Parameters
    ----------
    image : ndarray (H, W, 3), or a sequence of them
        Linear radiance of a homogeneous object (units of the environment's radiance).
        Several images (e.g. views of the object turned on the turntable) are combined: pass
        sequences of the same length for ``normals``, ``mask`` and ``view_dirs`` (or None).
    normals : ndarray (H, W, 3)
        Unit normals inside ``mask`` (ignored outside), in the frame of the environment.
    mask : ndarray (H, W) bool
        The object's pixels that may be used (no background, no clipped or invalid pixels).
    environment : EnvironmentMap or (directions (K, 3), radiance (K, 3), solid_angle (K,))
        Distant illumination in the normals' frame; a map is used texel by texel (its own
        resolution and ``rotation``; above ``MAX_TEXELS`` area-averaged down to it); arrays are
        sources as for ``lighting_matrix``.
    view_dirs : ndarray (H, W, 3) or (3,), optional
        Unit directions from the surface to the camera; default (0, 0, -1) (orthographic
        camera looking along +z, OpenCV camera frame).
    grid : (int, int)
        Nodes (n_t, n_s) of the bivariate table.
    n_normals : int
        Observations to draw (all usable pixels when there are fewer).
    max_view_angle_deg : float
        Pixels whose normal is further than this from the view are dropped.
    prior : SmoothnessPrior or sequence of them, or ModesPrior, optional
        Custom smoothness prior(s) (``learn_prior``, Eq. 6); default the learned "diffuse" and
        "glossy" priors (both when ``two_priors``, else the glossy one). A ``ModesPrior``
        (``learn_modes``: a library's mean and modes of variation in log space) replaces Eq.
        6's derivative penalty by a Gaussian prior on log(f + offset) (``passive_modes``); with
        a MERL library it is the better prior (Fig. 6 on MERL, docs/zoo.md).
    two_priors : bool
        Solve with both default priors ("diffuse" first) and keep the lower residual (the
        paper's variant), "glossy" only if it is below ``PRIOR_MARGIN`` x the diffuse one.
    environment_weight : ndarray (H_env, W_env) or (K,), optional
        Trust in each texel / source in [0, 1] (a probe's blind cone: 0). Observations whose
        cosine-weighted hemisphere is more than ``MAX_UNTRUSTED`` (2 %) untrusted are dropped;
        the rest use the weighted radiance.
    lam : float or "cv", optional
        Regularisation weight of Eq. 6 (for the normalised data term), default ``LAMBDA``;
        for a ``ModesPrior`` the prior's weight, default ``MODES_NOISE`` / observations ("cv" is refused:
        see there). ``"cv"`` (smoothness priors):
        chosen from ``CV_LAMBDAS`` by ``CV_FOLDS``-fold cross-validation over the observations
        (pixels): each candidate is fitted, per prior, to the green channel of all folds but one
        (without the f >= 0 bound, a Cholesky solve) and scored by its residual on the held-out
        fold; the weight with the lowest summed held-out residual is used for every prior and
        channel. The data's own noise (sensor, bivariate approximation, discretisation) thus
        sets the weight, not a figure tuned on some materials: a prior whose derivative
        variances are large (MERL's metals) needs a smaller one than the analytic priors
        (MERL leave-one-out under Grace: 1e-11 to 1e-8; Eq. 1 error of hematite 358 -> 65 %).
        Not the default because held-out pixels cannot see the nodes that no pixel observes
        well: on noise-free images it drives the weight down until those nodes are free (an
        Oren-Nayar sphere with the analytic priors: 1e-11, Eq. 1 error 12 % -> 333 %; the
        one-standard-error rule picks the same). Costs 4 folds x 8 weights x priors Cholesky
        solves of the node count.
    reweight : int, optional
        With a ``ModesPrior``: solves after the first in which each observation's noise
        variance is the plain solve's plus its squared misfit under the previous solve
        (iteratively reweighted least squares; default ``MODES_REWEIGHT``; 0: the plain solve).
        Smoothness priors take none.
    exemplars : ExemplarLibrary, optional
        After the solve, the nodes the environment did not constrain (``Adequacy.constrained``)
        are replaced by the mean of the library's nearest exemplars (``passive_exemplars``:
        matched at the constrained nodes in log space, a slope and offset fitted per channel,
        k chosen by leave-one-out on the library unless the library fixes it); the residual
        is that of the filled table. Not the default: on MERL under Grace it puts 30 of 100
        within the Fig. 6 target, the modes prior's own extrapolation 34 (docs/zoo.md).
    rng : int or numpy.random.Generator
        Observation sampling.
    progress : callable, optional
        ``progress(done, total)``: lighting-matrix normals, then the solves.
    map_blocks : callable(fn, list of argument tuples) -> list, optional
        Runs the lighting matrix's per-block tasks (``passive_lighting.lighting_sums``):
        default here, one after the other; the pipeline passes its executor's.

    Returns
    -------
    PassiveFit

    Raises
    ------
    PassiveInputError
        Bad shapes or values (naming the argument), or fewer than ``MIN_NORMALS`` usable
        observations.

    Warns
    -----
    PassiveWarning
        When the adequacy checks find the problem poorly posed (see ``PassiveFit.warnings``).
    """
    n_t, n_s = _grid(grid)
    images = _as_images(image, normals, mask, view_dirs)
    d, E, omega, trust = _sources(environment, environment_weight)
    if not 0 < max_view_angle_deg < 90:
        raise PassiveInputError(f"max_view_angle_deg must be in (0, 90), got "
                                f"{max_view_angle_deg!r}")
    if not (isinstance(n_normals, (int, np.integer)) and n_normals >= 1):
        raise PassiveInputError(f"n_normals must be a positive int, got {n_normals!r}")
    if lam is not None and not (isinstance(lam, str) and lam == "cv") and not (
            isinstance(lam, (int, float, np.floating)) and lam >= 0):
        raise PassiveInputError(f"lam must be a number >= 0, 'cv' or None, got {lam!r}")
    priors = _priors(prior, two_priors, (n_t, n_s))
    if reweight is not None and not (isinstance(reweight, (int, np.integer)) and reweight >= 0):
        raise PassiveInputError(f"reweight must be an int >= 0 or None, got {reweight!r}")
    if reweight and not isinstance(priors[0], ModesPrior):
        raise PassiveInputError("reweight is for a ModesPrior: the smoothness priors' solve "
                                "takes no observation weights")
    if isinstance(priors[0], ModesPrior) and isinstance(lam, str):
        raise PassiveInputError("lam='cv' is for smoothness priors: held-out pixels cannot see "
                                "the nodes a ModesPrior extrapolates (MODES_NOISE)")
    if exemplars is not None:
        if not isinstance(exemplars, ExemplarLibrary):
            raise PassiveInputError(f"exemplars must be an ExemplarLibrary, got "
                                    f"{type(exemplars).__name__}")
        if exemplars.grid != (n_t, n_s):
            raise PassiveInputError(f"exemplars were tabulated on grid {exemplars.grid}, not "
                                    f"{(n_t, n_s)}")
    gen = np.random.default_rng(rng)

    n, v, I = _observations(images, max_view_angle_deg, n_normals, gen)
    if trust is not None:
        keep = _untrusted_fraction(n, d[trust < 1], (1 - trust[trust < 1]) * omega[trust < 1]) \
            <= MAX_UNTRUSTED
        n, v, I = n[keep], (v[keep] if v.ndim == 2 else v), I[keep]
    if len(n) < MIN_NORMALS:
        raise PassiveInputError(f"only {len(n)} usable normals in mask (need >= {MIN_NORMALS} "
                                f"facing the camera within {max_view_angle_deg} deg, with "
                                f"finite, non-negative radiance)")
    total = len(n) + len(priors)
    report = None if progress is None else (lambda k, _: progress(k, total))
    sums = lighting_sums(n, I, d, E, omega, view_dirs=v, grid=(n_t, n_s), map_blocks=map_blocks,
                         progress=report)
    irr = sums.column.sum(axis=1) / len(n)                        # mean irradiance per channel
    if not np.all(irr > 0):
        raise PassiveInputError("environment gives no light to the observed normals")
    scale = 1.0 / (irr * np.sqrt(len(n)))
    G = [sums.gram[c] * scale[c] ** 2 for c in range(3)]   # of the scaled rows A = scale L, b = scale I
    h = [sums.rhs[c] * scale[c] ** 2 for c in range(3)]
    bb = sums.value_sq * scale ** 2
    lamb = np.array([h[c].sum() / G[c].sum() for c in range(3)])  # best constant f
    if isinstance(priors[0], ModesPrior):
        lam = MODES_NOISE / len(n) if lam is None else lam
        Q = priors[0].precision()
        sols = [solve_modes(priors[0], G[c], h[c], bb[c], lam, precision=Q) for c in range(3)]
        for _ in range(MODES_REWEIGHT if reweight is None else reweight):
            sols = _reweighted(priors[0], Q, sols, lam, bb, scale, n, I, d, E, omega, v,
                               (n_t, n_s), map_blocks)
        f = np.stack([s.f for s in sols], axis=1)
        res = _residuals(f, G, h, bb)
        priors, converged = priors[:1], all(s.converged for s in sols)
        solutions, residuals = {priors[0].name: f}, {priors[0].name: res}
        if progress is not None:
            progress(total, total)
    else:
        green = None if not isinstance(lam, str) else (   # the folds are rows: held for "cv"
            lighting_matrix(n, d, E, omega, view_dirs=v, grid=(n_t, n_s))[1].astype(np.float64) * scale[1],
            I[:, 1] * scale[1])
        solutions, residuals, converged, lam = _solve_smoothness(
            priors, green, G, h, bb, lam, gen, (n_t, n_s), progress, len(n), total)
    best = next(iter(residuals))  # a later (less smooth) prior must fit clearly better
    for name, res in residuals.items():
        if res.mean() < PRIOR_MARGIN * residuals[best].mean():
            best = name
    adequacy = _adequacy(sums.column, G[1], n, v, d, E, omega, (n_t, n_s), residuals[best])
    f, nearest = solutions[best], None
    if exemplars is not None:
        f, nearest = fill_unconstrained(f, adequacy.coverage, adequacy.constrained, exemplars)
        residuals[best] = _residuals(f, G, h, bb)
    for w in adequacy.warnings:
        warnings.warn(w, PassiveWarning, stacklevel=2)
    return PassiveFit(Bivariate(f.reshape(n_t, n_s, 3)), residuals[best], best, residuals, lamb,
                      adequacy, converged, float(lam), adequacy.warnings, nearest)


def _reweighted(prior, Q, sols, lam, bb, scale, n, I, d, E, omega, v, grid, map_blocks):
    """One more solve per channel with each observation's noise variance sigma^2 + r_i^2:
    sigma^2 = ``lam`` bb, the per-pixel noise of the plain solve, and r_i that pixel's misfit
    under the last solve (``sols``), so that pixels the bivariate table cannot follow count
    for less (the paper's "3D vs bivariate" error source, docs/zoo.md). Scaled units
    (``scale`` per channel) as in ``passive_reflectometry``; started from the last solve."""
    f = np.stack([s.f for s in sols], axis=1)
    pred = lighting_predictions(n, f, d, E, omega, view_dirs=v, grid=grid, map_blocks=map_blocks)
    sigma2 = lam * bb
    w = sigma2 / (sigma2 + ((pred - I) * scale) ** 2)
    sums = lighting_sums(n, I, d, E, omega, view_dirs=v, grid=grid, weights=w,
                         map_blocks=map_blocks)
    bbw = sums.value_sq * scale ** 2
    # the same noise scale as the plain solve: lam bb = lam' bbw
    return [solve_modes(prior, sums.gram[c] * scale[c] ** 2, sums.rhs[c] * scale[c] ** 2, bbw[c],
                        lam * bb[c] / bbw[c], precision=Q, start=sols[c].f) for c in range(3)]


def _residuals(f, G, h, bb) -> np.ndarray:
    """|A_c f_c - b_c| / |b_c| per channel (3,) from the normal equations' terms (G = A^T A,
    h = A^T b, bb = b . b): no rows needed."""
    sq = [f[:, c] @ G[c] @ f[:, c] - 2.0 * f[:, c] @ h[c] + bb[c] for c in range(3)]
    return np.sqrt(np.maximum(sq, 0.0) / bb)


def _solve_smoothness(priors, green, G, h, bb, lam, gen, grid, progress, done, total):
    """Eq. 6 with each ``SmoothnessPrior``: solutions (n, 3) and residuals (3,) by prior
    name, whether every solve converged, and the weight used. ``green``: the green channel's
    scaled rows and values (A, b), for ``lam="cv"``'s folds (None otherwise)."""
    n_t, n_s = grid
    roughness = [D.T @ D for D in (p.difference_operators() for p in priors)]
    if isinstance(lam, str):
        lam = _cross_validated_lambda(*green, roughness, gen)
    elif lam is None:
        lam = LAMBDA
    solutions, residuals, converged = {}, {}, True
    for k, p in enumerate(priors):
        R = lam * roughness[k]
        f = np.empty((n_t * n_s, 3))
        free = None  # the channels share most of their active set: each starts from the last
        for c in range(3):
            f[:, c], ok, free = _nnls_quadratic(G[c] + R, h[c], free)
            converged &= ok
        solutions[p.name], residuals[p.name] = f, _residuals(f, G, h, bb)
        if progress is not None:
            progress(done + k + 1, total)
    return solutions, residuals, converged, lam


# -- input checks and observations ---------------------------------------------------------------

def _grid(grid):
    try:
        return check_grid(grid)
    except ValueError as err:
        raise PassiveInputError(str(err)) from None


def _check_image_inputs(image, normals, mask, view_dirs):
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3:
        raise PassiveInputError(f"image must have shape (H, W, 3), got {img.shape}")
    nrm = np.asarray(normals, dtype=np.float64)
    if nrm.shape != img.shape:
        raise PassiveInputError(f"normals must have the image's shape {img.shape}, got "
                                f"{nrm.shape}")
    msk = np.asarray(mask)
    if msk.shape != img.shape[:2] or msk.dtype != bool:
        raise PassiveInputError(f"mask must be a bool array of shape {img.shape[:2]}, got "
                                f"{msk.dtype} {msk.shape}")
    if view_dirs is None:
        views = np.array([0.0, 0.0, -1.0])
    else:
        views = np.asarray(view_dirs, dtype=np.float64)
        if views.shape not in ((3,), img.shape):
            raise PassiveInputError(f"view_dirs must have shape (3,) or {img.shape}, got "
                                    f"{views.shape}")
    vm = views if views.ndim == 1 else views[msk]
    if not np.all(np.isfinite(vm)) or np.any(np.abs(np.linalg.norm(vm, axis=-1) - 1) > 1e-3):
        raise PassiveInputError("view_dirs must be finite unit vectors (inside the mask)")
    nm = nrm[msk]
    if not np.all(np.isfinite(nm)) or np.any(np.abs(np.linalg.norm(nm, axis=-1) - 1) > 1e-3):
        raise PassiveInputError("normals must be finite unit vectors inside the mask")
    return img, nrm, msk, views


def _sources(environment, weight):
    if isinstance(environment, EnvironmentMap):
        H, W = environment.shape
        if weight is not None and np.shape(weight) != (H, W) and np.size(weight) != H * W:
            raise PassiveInputError(f"environment_weight must have the map's shape {(H, W)}, "
                                    f"got {np.shape(weight)}")
        if H * W > MAX_TEXELS:  # a high-resolution probe: area-average it (keeps the flux)
            height = int(np.sqrt(MAX_TEXELS / 2))
            if weight is not None:
                w3 = np.repeat(np.asarray(weight, np.float32).reshape(H, W, 1), 3, axis=2)
                weight = EnvironmentMap(np.clip(w3, 0, 1)).resized(height).image[..., 0]
            environment = environment.resized(height)
        d, E, omega = environment.sources()
    else:
        try:
            d, E, omega = environment
        except (TypeError, ValueError):
            raise PassiveInputError("environment must be an EnvironmentMap or (directions, "
                                    "radiance, solid_angle)") from None
    try:
        d, E, omega = check_sources(d, E, omega)
    except ValueError as err:
        raise PassiveInputError(f"environment: {err}") from None
    if weight is None:
        return d, E, omega, None
    w = np.asarray(weight, dtype=np.float64).reshape(-1)
    if w.shape != (len(d),) or not np.all((w >= 0) & (w <= 1)):
        raise PassiveInputError(f"environment_weight must hold {len(d)} values in [0, 1] (one "
                                f"per texel / source), got shape {np.shape(weight)}")
    return d, E * w[:, None], omega, w


def _as_images(image, normals, mask, view_dirs):
    """One image's arrays, or equally long sequences of them (several images), validated:
    a list of (image, normals, mask, views)."""
    if isinstance(image, (list, tuple)):
        k = len(image)
        views = [None] * k if view_dirs is None else view_dirs
        for name, seq in (("normals", normals), ("mask", mask), ("view_dirs", views)):
            if not isinstance(seq, (list, tuple)) or len(seq) != k:
                raise PassiveInputError(f"{name} must be a sequence of {k} arrays, one per "
                                        f"image, when image is a sequence")
        if k == 0:
            raise PassiveInputError("image is an empty sequence")
        return [_check_image_inputs(*args) for args in zip(image, normals, mask, views)]
    return [_check_image_inputs(image, normals, mask, view_dirs)]


def _observations(images, max_angle_deg, n_normals, gen):
    """Pixels inside the masks facing their camera within ``max_angle_deg``, drawn uniformly
    over surface area (probability ~ 1 / cos of the view angle, a pixel's area on the
    surface), ``n_normals`` in all. Returns normals (M, 3), view directions (3,) when one
    image has one, else (M, 3), and radiance (M, 3)."""
    ns, vs, Is = [], [], []
    for img, nrm, msk, views in images:
        rows, cols = np.nonzero(msk)
        ns.append(nrm[rows, cols])
        vs.append(np.broadcast_to(views, ns[-1].shape) if views.ndim == 1 else
                  views[rows, cols])
        Is.append(img[rows, cols])
    n, v, I = np.concatenate(ns), np.concatenate(vs), np.concatenate(Is)
    cos = np.einsum("ij,ij->i", n, v)
    ok = (cos >= np.cos(np.radians(max_angle_deg))) & np.all(np.isfinite(I), axis=1) & \
        np.all(I >= 0, axis=1)
    idx = np.flatnonzero(ok)
    if len(idx) > n_normals:
        p = 1.0 / cos[idx]
        idx = np.sort(gen.choice(idx, n_normals, replace=False, p=p / p.sum()))
    one_view = len(images) == 1 and images[0][3].ndim == 1
    return n[idx], (images[0][3] if one_view else v[idx]), I[idx]


def _untrusted_fraction(n, d, omega):
    """Fraction of each normal's cosine-weighted hemisphere (pi sr) covered by the untrusted
    solid angles ``omega`` (K,) in directions ``d`` (K, 3)."""
    out = np.zeros(len(n))
    for s in range(0, len(n), 4096):
        out[s:s + 4096] = np.maximum(n[s:s + 4096] @ d.T, 0.0) @ omega / np.pi
    return out


def _priors(prior, two_priors, grid):
    if prior is None:
        kinds = PRIOR_KINDS if two_priors else ("glossy",)
        return [default_prior(k, grid) for k in kinds]
    if isinstance(prior, ModesPrior):
        if prior.grid != tuple(grid):
            raise PassiveInputError(f"prior {prior.name!r} was learned on grid {prior.grid}, "
                                    f"not {grid}")
        return [prior]
    ps = [prior] if isinstance(prior, SmoothnessPrior) else list(prior)
    for k, p in enumerate(ps):
        if not isinstance(p, SmoothnessPrior):
            raise PassiveInputError(f"prior[{k}] must be a SmoothnessPrior, got "
                                    f"{type(p).__name__}")
        if p.grid != tuple(grid):
            raise PassiveInputError(f"prior {p.name!r} was learned on grid {p.grid}, not {grid}")
    return ps


# -- the solve ----------------------------------------------------------------------------------

def _cross_validated_lambda(A, b, roughness, gen) -> float:
    """The weight of ``CV_LAMBDAS`` with the lowest held-out residual: ``CV_FOLDS`` random
    folds of the rows of ``A`` (M, n) / ``b`` (M,) (one channel, scaled as in the solve), each
    candidate solved unconstrained on the other folds (their Gram matrix rescaled to the full
    count, so that a weight means the same as in the full solve) with each prior's
    ``roughness`` (n, n) matrix, summed over folds and priors."""
    fold = gen.permutation(len(b)) % CV_FOLDS
    score = np.zeros(len(CV_LAMBDAS))
    for k in range(CV_FOLDS):
        train, test = fold != k, fold == k
        G = A[train].T @ A[train] * (CV_FOLDS / (CV_FOLDS - 1))
        h = A[train].T @ b[train] * (CV_FOLDS / (CV_FOLDS - 1))
        for R in roughness:
            for j, lam in enumerate(CV_LAMBDAS):
                try:
                    f = cho_solve(cho_factor(G + lam * R), h)
                except np.linalg.LinAlgError:  # too weak to make the system definite
                    score[j] = np.inf
                    continue
                score[j] += np.sum((A[test] @ f - b[test]) ** 2)
    return float(CV_LAMBDAS[int(np.argmin(score))])


def _nnls_quadratic(Q, h, free=None, *, max_iter=200):
    """argmin_{x >= 0} x^T Q x / 2 - h^T x for symmetric positive definite ``Q`` (n, n).

    Block principal pivoting (Kim and Park 2011, after Judice and Pires 1994): solve the
    equality-constrained problem on the free set by Cholesky, move every variable that violates
    the KKT conditions (a negative free value, a negative gradient at a bound) to the other set,
    and fall back to one exchange at a time (the largest index) when a block exchange does not
    reduce the violations for three rounds, which guarantees termination. A BRDF is positive
    over most of its domain, so a few rounds of O(n^3 / 3) suffice. ``free`` (n,) bool: the
    starting free set (default all). Returns (x, converged, final free set).
    """
    n = len(h)
    free = np.ones(n, bool) if free is None else free.copy()
    tol = 1e-12 * max(float(np.abs(h).max()), 1e-300)
    best, backup = n + 1, 3
    x = np.zeros(n)
    for _ in range(max_iter):
        x = np.zeros(n)
        if free.any():
            x[free] = cho_solve(cho_factor(Q[np.ix_(free, free)]), h[free])
        g = Q @ x - h
        bad = (free & (x < -tol)) | (~free & (g < -tol))
        count = int(bad.sum())
        if count == 0:
            return x, True, free
        if count < best:
            best, backup = count, 3
            free ^= bad
        elif backup > 0:
            backup -= 1
            free ^= bad
        else:
            free[np.flatnonzero(bad)[-1]] ^= True
    return np.maximum(x, 0.0), False, free


# -- adequacy ------------------------------------------------------------------------------------

def _adequacy(column, gram_green, n, v, d, E, omega, grid, residual):
    """``column`` (3, P): the lighting matrix's column sums; ``gram_green``: L^T L of the green
    channel (scaled as in the solve), whose singular values stand for the luminance's (green
    carries 72 % of it) without another product."""
    n_t, n_s = grid
    sv = np.sqrt(np.clip(np.linalg.eigvalsh(gram_green)[::-1], 0, None))
    rank = int(np.sum(sv > 1e-3 * sv[0]))
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    # coverage against a uniform sky of the same total light, on (a subset of) the normals
    sub = slice(None, None, max(1, len(n) // 300))
    vs = v if v.ndim == 1 else v[sub]
    white_d = _fibonacci_sphere(16384)
    white = lighting_matrix(n[sub], white_d, np.ones((len(white_d), 3)),
                            np.full(len(white_d), 4 * np.pi / len(white_d)), view_dirs=vs,
                            grid=grid)[1].astype(np.float64).sum(axis=0)
    seen = LUMINANCE @ column
    with np.errstate(invalid="ignore", divide="ignore"):
        coverage = (seen / seen.sum()) / (white / white.sum())
    coverage[white <= 1e-9 * white.max()] = np.nan
    coverage = coverage.reshape(n_t, n_s)
    t, s = np.meshgrid(np.linspace(0, 1, n_t), np.linspace(0, 1, n_s), indexing="ij")
    poor = {}
    for name, region in REGIONS.items():
        cov = coverage[region(t, s) & np.isfinite(coverage)]
        poor[name] = float(np.mean(cov < POOR_COVERAGE)) if cov.size else 1.0
    w = np.sort((E * omega[:, None]) @ LUMINANCE)[::-1]
    n_eff = int(np.searchsorted(np.cumsum(w), 0.95 * w.sum()) + 1) if w.sum() > 0 else 0
    msgs = []
    if len(n) < FEW_NORMALS:
        msgs.append(f"only {len(n)} observations (the paper used ~8000): the BRDF is poorly "
                    f"constrained")
    if n_eff < FEW_SOURCES:
        msgs.append(f"the environment is dominated by {n_eff} point-like sources: each "
                    f"normal sees few (theta_h, theta_d) pairs, so most of the BRDF domain comes "
                    f"from the prior, not the image")
    if rank < RANK_WARN * n_t * n_s:
        msgs.append(f"lighting matrix has effective rank {rank} of {n_t * n_s} nodes: the "
                    f"environment constrains only part of the BRDF")
    for name, frac in poor.items():
        if frac > 0.5:
            msgs.append(f"{name} poorly observed ({frac:.0%} of its nodes get < "
                        f"{POOR_COVERAGE:.0%} of a uniform sky's light): that part of the "
                        f"BRDF is extrapolated by the prior")
    if np.max(residual) > RESIDUAL_WARN:
        msgs.append(f"relative residual {np.max(residual):.1%} > {RESIDUAL_WARN:.0%}: the image "
                    f"is not explained by a homogeneous bivariate BRDF under this environment "
                    f"(probe rotated against the object, wrong normals or mask, spatially "
                    f"varying material)")
    return Adequacy(sv, rank, cond, coverage, poor, n_eff, len(n), tuple(msgs))


def _ranges(values, mask) -> str:
    """Runs of True in ``mask`` as "a-b" ranges of ``values`` (rounded; a run whose ends round
    alike: "a"), comma-separated."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    ends = [(f"{values[a]:.0f}", f"{values[b - 1]:.0f}") for a, b in zip(edges[::2], edges[1::2])]
    return ", ".join(lo if lo == hi else f"{lo}-{hi}" for lo, hi in ends)


def _fibonacci_sphere(k: int) -> np.ndarray:
    """``k`` near-uniform unit directions (K, 3) on the sphere."""
    i = np.arange(k) + 0.5
    z = 1 - 2 * i / k
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
