"""Do reflectance samples obey Helmholtz reciprocity, f(wi, wo) = f(wo, wi)?

Zickler et al.'s (u, v, w) build reciprocity in (phi_d is doubled, so a pair and its swap are
one point), and a physical surface obeys it. Measured tables need not: the RGL files store
f_r cos theta_light from a gonio-photometer whose light and sensor differ, and their two
orderings differ by 4 % (matte wall paint) and 18 % (glossy vinyl) median over random pairs
(docs/zoo.md, "Members"). A reciprocal fit of such data can come no closer to them than the
reciprocal BRDF nearest them, and where an image holds both orderings a pixel apart it goes
through whichever becomes a centre.

The check needs no model. An isotropic BRDF is a function of (cos theta_i, cos theta_o,
wi . wo), and swapping the directions swaps the first two; so for each sample the nearest
sample to its swap (``partner``) should carry the same value, up to the sampling step and the
noise. Those two are measured the same way, by the nearest sample to the sample itself that is
not its exact twin (``neighbour``; a sphere image holds each pair twice, mirrored about the
plane of the light and the view). The data are called non-reciprocal when the partners'
median log difference exceeds the neighbours' by ``RECIPROCITY_TOLERANCE``.

Measured on the zoo's sphere experiment (10 images of 100 x 100 px; ``benchmarks/zoo.py
--rgl``): gap 0.10 (vinyl) and 0.03 (matte paint), -0.009 to 0.000 on the MERL, Nielsen and
analytic members, the same with 2 % pixel noise (0.095, 0.022; at most -0.0004).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: Partners' median |log f difference| above the neighbours' by more than this: non-reciprocal.
RECIPROCITY_TOLERANCE = 0.01
#: Samples closer than this in (cos theta_i, cos theta_o, wi . wo) are one pair seen twice.
_TWIN = 1e-9
#: Nearest samples searched for one that is not the sample's twin (repeated captures repeat them).
_NEAREST = 16


@dataclass(frozen=True)
class ReciprocityCheck:
    """How far a sample set's two orderings of each pair disagree (:func:`check_reciprocity`).

    Attributes
    ----------
    partner : float
        Median over samples of |log f(wi, wo) - log f(s)|, s the sample nearest (wo, wi).
    neighbour : float
        Median of the same with s the nearest other sample: the sampling step and the noise.
    n_samples : int
        Samples compared: those with f > 0 that are not their own swap and have a neighbour that
        is not their twin (0: nothing to judge, called reciprocal).
    """

    partner: float
    neighbour: float
    n_samples: int

    @property
    def gap(self) -> float:
        """``partner`` - ``neighbour``: the disagreement the sampling and noise do not explain."""
        return self.partner - self.neighbour

    @property
    def reciprocal(self) -> bool:
        return not self.gap > RECIPROCITY_TOLERANCE

    def report(self) -> str:
        verdict = "reciprocal" if self.reciprocal else "not reciprocal"
        return (f"{verdict}: the two orderings of a pair differ by {self.partner:.1%} (median of "
                f"|log f| differences), neighbouring samples by {self.neighbour:.1%}, over "
                f"{self.n_samples} samples")


def check_reciprocity(wi, wo, brdf) -> ReciprocityCheck:
    """Compare each sample with the one nearest its swapped directions (module docstring).

    Parameters
    ----------
    wi, wo : array_like, (S, 3)
        Local unit directions to the light / camera (normal = +z).
    brdf : array_like, (S, 3) or (S,)
        f_r samples, 1/sr; channels are averaged, samples with a mean <= 0 left out.

    Raises
    ------
    ValueError
        Mismatched shapes, or fewer than three samples with f > 0.
    """
    wi, wo = np.asarray(wi, dtype=np.float64), np.asarray(wo, dtype=np.float64)
    f = np.asarray(brdf, dtype=np.float64)
    f = f.mean(axis=1) if f.ndim == 2 else f
    if wi.shape != wo.shape or wi.ndim != 2 or wi.shape[1] != 3 or f.shape != (len(wi),):
        raise ValueError(f"wi, wo must be (S, 3) and brdf (S,) or (S, 3); got {wi.shape}, "
                         f"{wo.shape}, {np.shape(brdf)}")
    ok = np.isfinite(f) & (f > 0)
    if ok.sum() < 3:
        raise ValueError(f"need at least 3 samples with f > 0 to check reciprocity, got "
                         f"{int(ok.sum())}")
    wi, wo, log_f = wi[ok], wo[ok], np.log(f[ok])
    x = np.column_stack([wi[:, 2], wo[:, 2], np.einsum("ij,ij->i", wi, wo)])
    tree = cKDTree(x)
    partner = tree.query(x[:, [1, 0, 2]], k=1)[1]
    dist, near = tree.query(x, k=min(_NEAREST, len(x)))
    far = dist > _TWIN                               # past the sample itself and its twins
    neighbour = near[np.arange(len(x)), np.argmax(far, axis=1)]
    # a sample that is its own swap (cos theta_i = cos theta_o within the sampling), or has no
    # other sample near it, says nothing either way
    told = far.any(axis=1) & (np.linalg.norm(x[partner] - x, axis=1) > _TWIN)
    if not told.any():
        return ReciprocityCheck(0.0, 0.0, 0)
    return ReciprocityCheck(float(np.median(np.abs(log_f - log_f[partner])[told])),
                            float(np.median(np.abs(log_f - log_f[neighbour])[told])),
                            int(told.sum()))
