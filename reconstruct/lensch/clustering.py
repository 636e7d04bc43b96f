"""Split-recluster-fit clustering of lumitexels into materials (Lensch et al. 2003, Sec. 7).

Samples are given by their lobe geometry (t, z), cos(theta_i), reflectance (S, 3), weight and the
texel (0..T-1) they belong to; clusters are per-channel Lafortune parameter arrays (3, P).

Beyond the paper, the number of materials can be decided from the data (``n_materials=None``):
each texel's samples are dealt into two halves; a split is kept only if labelling the texels by
their error on one half lowers the error on the *other* half, against the parent and against each
child used alone: the mean over texels of the bounded
relative gain (E_parent - E_child) / (E_parent + E_child) must exceed ``min_gain`` (0.05: about
10 % less held-out error) and ``z_min`` standard errors. The errors let each texel scale a model's
diffuse and specular parts (as the projection of Sec. 8 will), so texture and gloss strength are
not materials. Noise alone gives no held-out gain (a texel labelled by noise is as likely to get
the worse model), so splits that only chase noise are refused, while two materials that differ in
colour, exponent, or only the lobe's shape C_x/C_z give a clear gain (0.07-0.75 on the synthetic
tests). On real photographs the test's first version (raw errors, 0.02) split every object into
the cap of 12: shading errors of the normals and texture pass it (DiLiGenT bear, one glaze: raw
gain 0.12; with the per-texel scales 0.04, refused). Once the splitting stops, the same test
between every pair of final clusters decides which clusters are one material
(:meth:`_Clusterer.materials`): a split judged against a mixture can leave clusters that no
held-out test tells apart once the reclusterings have moved the texels. The paper's starts lie
along the parent fit's parameter covariance, in which two well-pinned diffuse colours hardly
vary: where that split is refused it is tried once more from the texels' chromaticities,
against a stricter bar (:data:`RETRY_GAIN`). And a split that gains little but surely (a first
split that peels one material off a mixture of several) is kept when a split of one of its
halves, looked at up to :data:`LOOK_AHEAD` levels down, passes that stricter bar.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from .lafortune_fit import N_MAX, N_MIN, LafortuneFit, fit_geometry, model_and_jacobian

#: Samples a clustering fit uses at most (texels drawn at random from the cluster): 13 parameters
#: per channel are pinned long before that, and fitting every sample of every clustering texel
#: in each of the split and recluster rounds was where a 5000-texel fit spent ~600 s.
FIT_SAMPLES = 20_000
#: Most rounds of the split's redistribute-refit loop (Sec. 7.3); labels settle in a few, but
#: cutting it to 8 left the bumpy object's sharpest material mixed with its neighbours (N 42, not 48).
SPLIT_ROUNDS = 25
#: The split's loop also stops once a round lowers the split's error (each member under its
#: better child) by less than this share: its fits draw their texels at random (FIT_SAMPLES), so
#: on DiLiGenT bear (one glaze) 0.4-2 % of 4000 texels swapped sides every round and all 25
#: rounds ran (50 fits of 20k samples, 40 of the fit's 70 s of CPU).
SPLIT_PROGRESS = 1e-3
#: Two member sets are the same cluster for the refused-split memory when they share this
#: fraction of their texels (a recluster after another split moves a few texels of every cluster).
SAME_CLUSTER = 0.95

#: Held-out gain a split from the colour start (:meth:`_Clusterer.colour_start`) must pass: a
#: second look at a cluster whose split was refused is a second comparison, so it passes a
#: stricter bar than the first (``min_gain``, 0.05). Two materials of other colours that the
#: covariance's starts missed (the full demo's blue and yellow at clusterings 1, 2, 4) gain
#: 0.35-0.36; a bumpy-object cluster of blue texels and texels blending blue with their
#: neighbours gains 0.14 and, kept, costs that object's held-out error 0.514 -> 0.542.
RETRY_GAIN = 0.2
#: Levels a split that is small but sure (gain under ``min_gain``, z over ``z_min``) looks down
#: its halves' splits (each a second look, judged against :data:`RETRY_GAIN`) before it is
#: refused: a first split that peels one material off a mixture can gain little while the
#: splits beyond it gain much (five random materials: 0.047, z 4.9, then 0.30-0.41; 1 of 5
#: found without looking). On real photographs nearly every refused split is sure (DiLiGenT, one
#: glaze each: z 23-30), so each level costs every object its looks: one level costs bear and
#: goblet 6-7 s of CPU, two levels 24-26 s (goblet's fit 54 -> 81 s). Two levels would also find
#: a four-material set that one level misses (0.038, z 18; then 0.166; then 0.454). 0: off.
LOOK_AHEAD = 1

#: Albedo bound of the clustering's lobes (1/sr units): only a guard against runaway fits. They
#: only group texels; the materials are refitted under MAX_LOBE_ALBEDO before predicting
#: anything; with the physical bound here the split decisions changed and one bumpy-object
#: material ended split across two clusters (47 % of its texels in the main one).
CLUSTERING_ALBEDO = 1e3


def sample_errors(params: np.ndarray, t, z, cos_i, reflectance, *, intensity_weight: float = 1.0,
                  relative: bool = False):
    """Per-sample error of Eq. 6 for one model (3, P): s * I + D, (S,), in (1/sr)^2 (unitless
    with ``relative``).

    With the residual e = f_r cos(theta_i) - r per channel and its channel mean e_bar,
    I = 3 e_bar^2 is the intensity difference and D = sum_c (e_c - e_bar)^2 the colour
    difference; with ``intensity_weight`` s = 1, I + D is the squared RGB error. With
    ``relative`` (multiplicative noise, the fits' ``noise="relative"``) it is divided by the
    model's squared value (:func:`relative_error`): else the noise of a highlight's samples
    swamps a difference in diffuse colour.
    """
    f, _ = model_and_jacobian(params, t, z, cos_i, want_jac=False)
    e = f - reflectance.T
    mean = e.mean(axis=0)
    err = intensity_weight * 3 * mean ** 2 + ((e - mean) ** 2).sum(axis=0)
    return relative_error(err, f.mean(axis=0), params) if relative else err


def relative_error(err, model, params) -> np.ndarray:
    """Squared errors ``err`` (S,) of samples whose model value (channel mean, 1/sr) is ``model``
    (S,) under multiplicative noise: divided by model^2, floored at 1 % of the model's diffuse
    level rho_d / pi (the model's own scale, not the samples', so the result does not depend on
    how samples are chunked; at least 1e-6 1/sr, for a model without a diffuse part). Samples
    the model predicts dark (below the horizon of a fitted normal: every model predicts 0 there)
    carry no relative information and count 0. Between two models of one shape and brightness
    a < b, the label boundary lies at 2ab / (a + b), below the mean: textured texels lean to the
    brighter model."""
    floor = 0.01 * max(float(np.mean(params[:, 0])) / np.pi, 1e-6)
    return np.where(model > 0, err / np.maximum(model, floor) ** 2, 0.0)


def texel_mean(values, texel, n_texels: int, weight, mask=None) -> np.ndarray:
    """Weighted mean of per-sample ``values`` over each texel's samples (T,); 0 where it has none."""
    w = weight if mask is None else weight * mask
    num = np.bincount(texel, values * w, minlength=n_texels)
    den = np.bincount(texel, w, minlength=n_texels)
    return np.divide(num, den, out=np.zeros(n_texels), where=den > 0)


def _bounds(P: int) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.full(P, -np.inf), np.full(P, np.inf)
    lo[0] = 0.0
    lo[3::3], hi[3::3] = N_MIN, N_MAX
    return lo, hi


@dataclass
class _Samples:
    """Samples of the texels taking part in clustering (a subset of all, re-indexed 0..n-1)."""

    t: np.ndarray
    z: np.ndarray
    cos_i: np.ndarray
    r: np.ndarray
    w: np.ndarray
    texel: np.ndarray
    n_texels: int
    half: np.ndarray  # (S,) 0/1: the half of its texel's samples a sample is dealt into

    def take(self, keep: np.ndarray):
        return self.t[keep], self.z[keep], self.cos_i[keep], self.r[keep], self.w[keep]

    def errors(self, params, mask=None, *, s: float = 1.0) -> np.ndarray:
        """Eq. 6 per texel (n_texels,) of a model (3, P) over all samples or those in ``mask``."""
        sel = slice(None) if mask is None else mask
        e = sample_errors(params, self.t[sel], self.z[sel], self.cos_i[sel], self.r[sel],
                          intensity_weight=s)
        return texel_mean(e, self.texel[sel], self.n_texels, self.w[sel])

    def projected_half_errors(self, params) -> tuple[np.ndarray, np.ndarray]:
        """Per texel, the model's diffuse and specular parts scaled by non-negative weights
        (shared by the channels) fitted on all of its samples: the mean squared RGB error on
        half 0 and on half 1, (2, n_texels).

        The weights come from both halves because fitting two of them to half a texel's samples
        (4-5 on the paper's lumitexels) overfits: a half without a highlight sample leaves the
        specular weight to the noise, and the other half's error then varies by orders of
        magnitude either way; a held-out gain from such weights was noise (its per-texel
        quartiles -0.7 and +0.6 on three Phong materials of exponents 36/48/60). Parent and
        children get the same two weights per texel, so the test stays fair; what is held out
        is the choice of material.
        """
        f, _ = model_and_jacobian(params, self.t, self.z, self.cos_i, want_jac=False)
        d = params[:, :1] / np.pi * self.cos_i          # (3, S) diffuse part
        sp = f - d                                      # (3, S) the lobes
        r = self.r.T
        terms = {"dd": (d, d), "ds": (d, sp), "ss": (sp, sp), "dr": (d, r), "sr": (sp, r),
                 "rr": (r, r)}
        sums = [{k: np.bincount(self.texel, self.w * (self.half == h) * (x * y).sum(axis=0),
                                minlength=self.n_texels) for k, (x, y) in terms.items()}
                for h in (0, 1)]
        m = {k: sums[0][k] + sums[1][k] for k in terms}

        def sse(m, a1, a2):
            return (a1 * a1 * m["dd"] + 2 * a1 * a2 * m["ds"] + a2 * a2 * m["ss"]
                    - 2 * a1 * m["dr"] - 2 * a2 * m["sr"] + m["rr"])
        det = m["dd"] * m["ss"] - m["ds"] ** 2
        ok = det > 1e-9 * np.maximum(m["dd"] * m["ss"], 1e-300)
        a1 = np.where(ok, (m["ss"] * m["dr"] - m["ds"] * m["sr"]) / np.where(ok, det, 1), -1)
        a2 = np.where(ok, (m["dd"] * m["sr"] - m["ds"] * m["dr"]) / np.where(ok, det, 1), -1)
        # outside the non-negative quadrant: the better of the one-part solutions
        d_only = np.maximum(m["dr"], 0) / np.maximum(m["dd"], 1e-300)
        s_only = np.maximum(m["sr"], 0) / np.maximum(m["ss"], 1e-300)
        use_d = sse(m, d_only, 0.0) <= sse(m, 0.0, s_only)
        inside = (a1 >= 0) & (a2 >= 0)
        a1 = np.where(inside, a1, np.where(use_d, d_only, 0.0))
        a2 = np.where(inside, a2, np.where(use_d, 0.0, s_only))
        return np.stack([np.maximum(sse(sums[h], a1, a2), 0.0)
                         / np.maximum(self._half_weight(h), 1e-300) for h in (0, 1)])

    def _half_weight(self, h: int) -> np.ndarray:
        return np.bincount(self.texel, self.w * (self.half == h), minlength=self.n_texels)


def deal_halves(texel: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Deal each texel's samples alternately into halves 0 and 1 in random order, (S,) int."""
    perm = rng.permutation(len(texel))
    order = perm[np.argsort(texel[perm], kind="stable")]
    sorted_texel = texel[order]
    first = np.searchsorted(sorted_texel, sorted_texel, side="left")
    half = np.empty(len(texel), np.int64)
    half[order] = (np.arange(len(texel)) - first) % 2
    return half


@dataclass(frozen=True)
class Clustering:
    """Outcome of :func:`split_recluster_fit` on the clustering texels.

    ``fits`` the Lafortune fit per cluster; ``labels`` (n,) the cluster of each clustering texel;
    ``history`` one line per split tried (for reports); ``single`` the one average BRDF fitted to
    all of them before any split; ``material`` (K,) the material of each cluster, 0..M-1 in order
    of first appearance (:meth:`_Clusterer.materials`; each cluster its own where the count was
    given).
    """

    fits: tuple
    labels: np.ndarray
    history: tuple
    single: LafortuneFit
    material: np.ndarray


class _Clusterer:
    def __init__(self, smp: _Samples, *, n_lobes, intensity_weight, min_texels, min_gain, z_min,
                 noise, rng, fit_samples=FIT_SAMPLES):
        self.smp = smp
        self.rng = rng
        self.fit_texels = max(2 * min_texels, int(fit_samples * smp.n_texels / max(len(smp.texel), 1)))
        self.noise = noise
        self.n_lobes = n_lobes
        self.s = intensity_weight
        self.min_texels = min_texels
        self.min_gain = min_gain
        self.z_min = z_min
        self.lo, self.hi = _bounds(1 + 3 * n_lobes)
        self.stall = None

    def fit(self, members: np.ndarray, init=None, rng=None) -> LafortuneFit:
        """The cluster's BRDF on (at most :data:`FIT_SAMPLES` samples of) its ``members``, drawn
        with ``rng`` (default the clusterer's)."""
        if len(members) > self.fit_texels:
            members = np.sort((rng or self.rng).choice(members, self.fit_texels, replace=False))
        keep = np.isin(self.smp.texel, members) if len(members) < self.smp.n_texels else \
            np.ones(len(self.smp.texel), bool)
        t, z, c, r, w = self.smp.take(keep)
        return fit_geometry(t, z, c, r, w, n_lobes=self.n_lobes, init=init, noise=self.noise,
                            max_albedo=CLUSTERING_ALBEDO, stall=self.stall)

    def _clip(self, params):
        return np.clip(params, self.lo, self.hi)

    def colour_start(self, fit: LafortuneFit, members: np.ndarray):
        """A start pair from the texels' colours: the members' chromaticities (each texel's
        summed reflectance over its channels' sum) split at their mean along their principal
        direction; both sides start from the parent's model."""
        sums = np.stack([np.bincount(self.smp.texel, self.smp.w * self.smp.r[:, c], self.smp.n_texels)
                         for c in range(3)], axis=1)[members]
        chroma = sums / np.maximum(sums.sum(axis=1, keepdims=True), 1e-300)
        x = chroma - chroma.mean(axis=0)
        _, _, vt = np.linalg.svd(x, full_matrices=False)
        a = fit.channel_params
        return a, a, x @ vt[0] > 0

    def split(self, fit: LafortuneFit, members: np.ndarray, rng=None):
        """Split one cluster (Sec. 7.2-7.3): start models a +- tau * e along the covariance's
        principal directions, redistribute by Eq. 6, refit (drawing with ``rng``, default the
        clusterer's), until the labels stop changing.
        Returns (fit1, fit2, in_first (len(members),) bool) or None."""
        a = fit.channel_params  # (3, P)
        P = a.shape[1]
        # the covariance in relative units, so rho_d, C and N compete on equal terms
        scale = np.maximum(np.abs(fit.params), 1e-3)
        rel = fit.covariance / np.outer(scale, scale)
        vals, vecs = np.linalg.eigh(rel)
        E = self.smp.errors(a, s=self.s)[members]
        best = None
        for k in np.argsort(vals)[::-1][:3]:  # the paper's principal eigenvector, and two more
            e = vecs[:, k] * scale / np.max(np.abs(vecs[:, k]))
            for tau in (0.05, 0.15, 0.4):
                d = (tau * e).reshape(P, 3).T
                p1, p2 = self._clip(a + d), self._clip(a - d)
                e1, e2 = self.smp.errors(p1, s=self.s)[members], self.smp.errors(p2, s=self.s)[members]
                score = np.minimum(e1, e2).sum()
                if best is None or score < best[0]:
                    best = (score, p1, p2, e1 < e2)
        if best is None or best[0] >= E.sum():
            return None
        _, p1, p2, first = best
        return self.split_from(members, (p1, p2, first), rng=rng)

    def split_from(self, members, start, rng=None):
        """Sec. 7.3 from a start pair (p1, p2, in_first): redistribute by Eq. 6 and refit (drawing
        with ``rng``, default the clusterer's) until the labels stop changing."""
        p1, p2, first = start
        f1 = f2 = None
        last = np.inf
        for _ in range(SPLIT_ROUNDS):
            if min(first.sum(), (~first).sum()) < self.min_texels:
                return None
            f1 = self.fit(members[first], init=p1, rng=rng)
            f2 = self.fit(members[~first], init=p2, rng=rng)
            p1, p2 = f1.channel_params, f2.channel_params
            e1 = self.smp.errors(p1, s=self.s)[members]
            e2 = self.smp.errors(p2, s=self.s)[members]
            new, error = e1 < e2, np.minimum(e1, e2).sum()
            settled = np.array_equal(new, first) or error > (1 - SPLIT_PROGRESS) * last
            first, last = new, error
            if settled:
                break
        return f1, f2, first

    def held_out_gain(self, parent: LafortuneFit, f1: LafortuneFit, f2: LafortuneFit,
                      members: np.ndarray) -> tuple[float, float]:
        """Held-out gain of a split and its z-score over texels.

        Each texel may scale a model's diffuse and specular parts on its own (the projection of
        Sec. 8 gives it that freedom anyway, see :meth:`_Samples.projected_half_errors`); the
        texel is labelled by its error on one half of its samples and scored on the other half. So a split that
        only sorts texels by albedo or gloss strength (texture, shading error of the normals)
        gains nothing; one between materials of other colour or lobe shape does. Per texel the
        gain g = (E_parent - E_child) / (E_parent + E_child) is in [-1, 1]: bounded, so a few
        texels whose highlight sits in the wrong place cannot outweigh the rest, as they would in
        a mean of raw errors. Both ways round, averaged.

        The gain is taken against each of the parent and the two children used alone for every
        texel, and the least counts: a child can be a better model of the *same* material than a
        parent fitted without the per-texel scales (on a textured single material the parent's
        exponent came out 41.6 for 40, the children's 40.0 and 40.3), and a split that gains only
        that is refused.
        """
        e0, e1, e2 = (self.smp.projected_half_errors(f.channel_params)[:, members]
                      for f in (parent, f1, f2))
        counts = [np.bincount(self.smp.texel, (self.smp.half == h) * self.smp.w,
                              minlength=self.smp.n_texels)[members] for h in (0, 1)]
        both = (counts[0] > 0) & (counts[1] > 0)
        if np.count_nonzero(both) < 2:
            return 0.0, 0.0
        # label from half a, scored on the other half
        child = [np.where(e1[a] < e2[a], e1[1 - a], e2[1 - a]) for a in (0, 1)]
        worst = None
        for ref in (e0, e1, e2):  # the split must beat each of its models used alone
            gain = sum((ref[1 - a] - child[a]) / np.maximum(ref[1 - a] + child[a], 1e-300)
                       for a in (0, 1))[both] / 2
            z = gain.mean() / max(gain.std(ddof=1) / np.sqrt(len(gain)), 1e-300)
            if worst is None or gain.mean() < worst[0]:
                worst = (float(gain.mean()), float(z))
        return worst

    def materials(self, fits: list, labels: np.ndarray, history: list) -> tuple[np.ndarray, np.ndarray]:
        """The material of each cluster once the splitting has stopped, (K,) int, and the pair
        gains (K, K) it was decided from (inf: the pair passes, two materials).

        Each split passed the held-out test against the cluster it split, but the global
        reclusterings after it move texels between all clusters, and what a split separated
        can end up as clusters no held-out test tells apart. Every pair of final clusters is
        tested again (:meth:`held_out_gain` on the pair's texels, against one BRDF fitted to both
        and each used alone); pairs that fail are one material, and clusters join a material only
        if every pair across passes as one (complete linkage, so no chain of look-alikes joins two
        distinct materials). On the bumpy object the clusters so joined are texels that saw a
        highlight through a normal a few degrees off (the lobe about the mesh normal misplaces
        it) and the rest of their material: the gap a normal fit closes, not a material (Lensch
        et al. 2003, Sec. 7.4: more clusters than materials compensate for "slightly wrong
        normals"; Sec. 9 fits the normals after the clustering).
        """
        K = len(fits)
        gain = np.full((K, K), -np.inf)
        rng = copy.deepcopy(self.rng)   # judging the clusters leaves the fit's later draws as they were
        counts = np.bincount(labels, minlength=K)
        for a in range(K):
            for b in range(a + 1, K):
                if max(counts[a], counts[b]) < self.min_texels:   # nothing to judge on: told apart
                    gain[a, b] = gain[b, a] = np.inf
                    continue
                members = np.flatnonzero((labels == a) | (labels == b))
                both = self.fit(members, init=fits[a].channel_params, rng=rng)
                g, z = self.held_out_gain(both, fits[a], fits[b], members)
                # a pair that passes never joins; a failed one joins at its gain (least first)
                gain[a, b] = gain[b, a] = np.inf if (g > self.min_gain and z > self.z_min) else g
                if np.isfinite(gain[a, b]):
                    history.append(f"clusters {a} and {b}: held-out gain {g:.3f}, z = {z:.1f}, one material")
        return _linked(gain), gain

    def recluster(self, fits: list, labels: np.ndarray, *, max_rounds: int = 10, tol: float = 0.005):
        """Global reclustering (Eq. 10): every texel to its best cluster, refit, repeat."""
        for _ in range(max_rounds):
            E = np.stack([self.smp.errors(f.channel_params, s=self.s) for f in fits])
            new = np.argmin(E, axis=0)
            counts = np.bincount(new, minlength=len(fits))
            if np.any(counts < self.min_texels):  # a cluster emptied by others: drop it
                keep = np.flatnonzero(counts >= self.min_texels)
                fits = [fits[k] for k in keep]
                new = np.argmin(E[keep], axis=0)
            changed = np.mean(new != labels) if len(fits) == len(E) else 1.0
            labels = new
            fits = [self.fit(np.flatnonzero(labels == k), init=f.channel_params)
                    for k, f in enumerate(fits)]
            if changed < tol:
                break
        return fits, labels


def _linked(gain: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """Materials (K,) from pair gains (K, K): complete linkage over the pairs that failed (finite
    gain), the least gain first, from single clusters or from the groups of ``start`` (K,)
    materials; numbered in order of first appearance."""
    K = len(gain)
    groups = [[k] for k in range(K)] if start is None else \
        [list(np.flatnonzero(start == m)) for m in np.unique(start)]
    while len(groups) > 1:
        link = [(max(gain[a, b] for a in groups[i] for b in groups[j]), i, j)
                for i in range(len(groups)) for j in range(i + 1, len(groups))]
        g, i, j = min(link)
        if not np.isfinite(g):
            break
        groups[i] += groups.pop(j)
    material = np.empty(K, np.int64)
    for m, g in enumerate(sorted(groups, key=min)):
        material[g] = m
    return material


def judge_materials(smp: _Samples, fits, labels: np.ndarray, *, n_lobes: int = 1,
                    min_texels: int = 10, min_gain: float = 0.05, z_min: float = 4.0,
                    intensity_weight: float = 1.0, noise: str = "absolute", rng=0,
                    stall: tuple[int, float] | None = None, history: list | None = None,
                    earlier: np.ndarray | None = None) -> np.ndarray:
    """The material of each of the clusters ``fits`` (K,) int, by the held-out pair test of
    :meth:`_Clusterer.materials` on the samples ``smp`` as they are now: e.g. about the normals
    fitted after the clustering (Sec. 9), where clusters that only stood for "slightly wrong
    normals" (Sec. 7.4) should no longer be told apart. ``labels`` (texels of ``smp``) give each
    cluster's members (a pair with fewer than ``min_texels`` in both is not judged, so not joined;
    a cluster the relabelling about the fitted normals emptied is judged on its partner's texels,
    which its own lobe does not fit better: it joins); the pairs' lines are appended to
    ``history``. With ``earlier`` (K,), an earlier judgement's materials (``Clustering.material``),
    the clusters start in those groups: this judgement can only join them."""
    cl = _Clusterer(smp, n_lobes=n_lobes, intensity_weight=intensity_weight,
                    min_texels=min_texels, min_gain=min_gain, z_min=z_min, noise=noise,
                    rng=np.random.default_rng(rng))
    cl.stall = stall
    gain = cl.materials(list(fits), np.asarray(labels), [] if history is None else history)[1]
    # only joins: what the first judgement (``earlier``) made one material stays one (a normal
    # fitted with each cluster's own lobe can make its cluster look apart)
    return _linked(gain, None if earlier is None else np.asarray(earlier))


def split_recluster_fit(smp: _Samples, *, n_materials: int | None, n_lobes: int = 1,
                        max_materials: int = 12, intensity_weight: float = 1.0,
                        min_texels: int = 10, min_gain: float = 0.05, z_min: float = 4.0,
                        noise: str = "absolute", rng=0, progress=None,
                        stall: tuple[int, float] | None = None) -> Clustering:
    """Cluster the texels of ``smp`` into materials (Sec. 7, Fig. 7).

    Start from one cluster holding everything; repeatedly split the cluster with the largest
    error E(C) (Eq. 8) by :meth:`_Clusterer.split`, then recluster globally (Eq. 10). With
    ``n_materials`` given, stop once that many clusters exist (the paper's termination, Sec. 7.4);
    with None, keep a split only when its held-out gain passes ``min_gain`` and ``z_min`` (see the
    module docstring; a refused split is tried once more from the members' colours, and kept
    only past :data:`RETRY_GAIN`, drawing from a copy of the generator so that a retry that
    fails leaves the fit as it was; a refused split whose z passes is kept when a split of its
    halves passes :data:`RETRY_GAIN`, :data:`LOOK_AHEAD` levels down, drawing the same way) and
    stop when no cluster's split passes, or at
    ``max_materials`` clusters;
    then the final clusters that no held-out test tells apart are one material
    (:meth:`_Clusterer.materials`). ``stall`` ends each Lafortune fit early where it crawls
    (:func:`~reconstruct.lensch.lafortune_fit.fit_geometry`).
    """
    cl = _Clusterer(smp, n_lobes=n_lobes, intensity_weight=intensity_weight,
                    min_texels=min_texels, min_gain=min_gain, z_min=z_min, noise=noise,
                    rng=np.random.default_rng(rng))
    cl.stall = stall
    everyone = np.arange(smp.n_texels)
    single = cl.fit(everyone)
    fits = [single]
    labels = np.zeros(smp.n_texels, np.int64)
    history = []
    target = max_materials if n_materials is None else n_materials
    refused: list = []  # member sets whose split was refused (not tried again while unchanged)

    def judge(parent, name, members, out, bar, how) -> tuple[bool, float]:
        """Keep the split ``out`` of ``parent``? (its held-out gain against ``bar``; logged), and
        the split's z-score."""
        f1, f2, first = out
        gain, z = cl.held_out_gain(parent, f1, f2, members)
        ok = n_materials is not None or (gain > bar and z > z_min)
        history.append(f"{name} ({len(members)} texels){how} -> {first.sum()} + {(~first).sum()}: "
                       f"held-out gain {gain:.3f}, z = {z:.1f} {'kept' if ok else 'refused'}")
        return ok, z

    def a_half_splits(members, out, depth, rng=None) -> bool:
        """Look ahead: does a split of either half of ``out``, or (``depth`` levels down) of the
        halves of a half's split that is small but sure, pass :data:`RETRY_GAIN`?"""
        if rng is None:
            rng = copy.deepcopy(cl.rng)  # a look that finds nothing leaves the fit as it was
        for fit, part in ((out[0], members[out[2]]), (out[1], members[~out[2]])):
            if len(part) < 2 * min_texels:
                continue
            sub = cl.split(fit, part, rng=rng)
            if sub is None:
                continue
            ok, z = judge(fit, "  " * (LOOK_AHEAD - depth + 1) + "a half", part, sub, RETRY_GAIN, "")
            if ok or (depth > 1 and z > z_min and a_half_splits(part, sub, depth - 1, rng)):
                return True
        return False

    def was_refused(members):
        return any(len(np.intersect1d(members, r, assume_unique=True))
                   >= SAME_CLUSTER * max(len(members), len(r)) for r in refused)
    while len(fits) < target:
        E = np.stack([smp.errors(f.channel_params) for f in fits])
        cluster_error = np.array([E[k, labels == k].sum() for k in range(len(fits))])  # Eq. 8
        done = False
        for k in np.argsort(cluster_error)[::-1]:
            members = np.flatnonzero(labels == k)
            if len(members) < 2 * min_texels or was_refused(members):
                continue
            out = cl.split(fits[k], members)
            if out is None:
                refused.append(members)
                history.append(f"cluster {k} ({len(members)} texels): no split possible")
                continue
            name = f"cluster {k}"
            ok, z = judge(fits[k], name, members, out, min_gain, "")
            if not ok:   # the covariance's starts can miss two colours (full demo, clustering 1)
                colour = cl.split_from(members, cl.colour_start(fits[k], members), rng=copy.deepcopy(cl.rng))
                ok = colour is not None and judge(fits[k], name, members, colour, RETRY_GAIN, " by colour")[0]
                out = colour if ok else out
            # small but sure: look beyond the covariance's split (a refused colour split's z is
            # not asked: the look judges the split the paper's procedure chose)
            if not ok and n_materials is None and z > z_min and LOOK_AHEAD:
                ok = a_half_splits(members, out, LOOK_AHEAD)
                if ok:
                    history.append(f"{name}: its split kept after all: a split of a half passes")
            if not ok:
                refused.append(members)
                continue
            f1, f2, first = out
            fits[k] = f1
            fits.append(f2)
            labels[members[~first]] = len(fits) - 1
            fits, labels = cl.recluster(fits, labels)
            done = True
            break
        if progress is not None:
            progress(len(fits), target)
        if not done:
            break
    material = np.arange(len(fits)) if n_materials is not None else \
        cl.materials(fits, labels, history)[0]
    return Clustering(fits=tuple(fits), labels=labels, history=tuple(history), single=single,
                      material=material)
