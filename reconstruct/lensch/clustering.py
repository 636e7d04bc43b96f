"""Split-recluster-fit clustering of lumitexels into materials (Lensch et al. 2003, Sec. 7).

Samples are given by their lobe geometry (t, z), cos(theta_i), reflectance (S, 3), weight and the
texel (0..T-1) they belong to; clusters are per-channel Lafortune parameter arrays (3, P).

Beyond the paper, the number of materials can be decided from the data (``n_materials=None``):
each texel's samples are dealt into two halves; a split is kept only if labelling the texels by
their error on one half lowers the error on the *other* half: the mean over texels of the bounded
relative gain (E_parent - E_child) / (E_parent + E_child) must exceed ``min_gain`` and ``z_min``
standard errors. Noise alone gives no
held-out gain (a texel labelled by noise is as likely to get the worse model), so splits that only
chase noise are refused, while two materials that differ in any way the samples see (colour,
exponent, or only the lobe's shape C_x/C_z) give a clear gain.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .lafortune_fit import N_MAX, N_MIN, LafortuneFit, fit_geometry, model_and_jacobian

#: Albedo bound of the clustering's lobes (1/sr units): only a guard against runaway fits. They
#: only group texels; the materials are refitted under MAX_LOBE_ALBEDO before predicting
#: anything; with the physical bound here the split decisions changed and one bumpy-object
#: material ended split across two clusters (47 % of its texels in the main one).
CLUSTERING_ALBEDO = 1e3


def sample_errors(params: np.ndarray, t, z, cos_i, reflectance, *, intensity_weight: float = 1.0):
    """Per-sample error of Eq. 6 for one model (3, P): s * I + D, (S,).

    With the residual e = f_r cos(theta_i) - r per channel and its channel mean e_bar,
    I = 3 e_bar^2 is the intensity difference and D = sum_c (e_c - e_bar)^2 the colour
    difference; with ``intensity_weight`` s = 1, I + D is the squared RGB error.
    """
    f, _ = model_and_jacobian(params, t, z, cos_i, want_jac=False)
    e = f - reflectance.T
    mean = e.mean(axis=0)
    return intensity_weight * 3 * mean ** 2 + ((e - mean) ** 2).sum(axis=0)


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

    def half_errors(self, params, *, s: float = 1.0):
        """Eq. 6 per texel on each half of the samples: (2, n_texels)."""
        e = sample_errors(params, self.t, self.z, self.cos_i, self.r, intensity_weight=s)
        return np.stack([texel_mean(e, self.texel, self.n_texels, self.w, self.half == h)
                         for h in (0, 1)])


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
    all of them before any split.
    """

    fits: tuple
    labels: np.ndarray
    history: tuple
    single: LafortuneFit


class _Clusterer:
    def __init__(self, smp: _Samples, *, n_lobes, intensity_weight, min_texels, min_gain, z_min,
                 noise):
        self.smp = smp
        self.noise = noise
        self.n_lobes = n_lobes
        self.s = intensity_weight
        self.min_texels = min_texels
        self.min_gain = min_gain
        self.z_min = z_min
        self.lo, self.hi = _bounds(1 + 3 * n_lobes)

    def fit(self, members: np.ndarray, init=None) -> LafortuneFit:
        keep = np.isin(self.smp.texel, members) if len(members) < self.smp.n_texels else \
            np.ones(len(self.smp.texel), bool)
        t, z, c, r, w = self.smp.take(keep)
        return fit_geometry(t, z, c, r, w, n_lobes=self.n_lobes, init=init, noise=self.noise,
                            max_albedo=CLUSTERING_ALBEDO)

    def _clip(self, params):
        return np.clip(params, self.lo, self.hi)

    def split(self, fit: LafortuneFit, members: np.ndarray):
        """Split one cluster (Sec. 7.2-7.3): start models a +- tau * e along the covariance's
        principal directions, redistribute by Eq. 6, refit, until the labels stop changing.
        Returns (fit1, fit2, in_first (len(members),) bool) or None."""
        a = fit.channel_params  # (3, P)
        P = a.shape[1]
        # the covariance in relative units, so rho_d, C and N compete on equal terms
        scale = np.maximum(np.abs(fit.params), 1e-3)
        rel = fit.covariance / np.outer(scale, scale)
        vals, vecs = np.linalg.eigh(rel)
        E = self.smp.errors(a)[members]
        best = None
        for k in np.argsort(vals)[::-1][:3]:  # the paper's principal eigenvector, and two more
            e = vecs[:, k] * scale / np.max(np.abs(vecs[:, k]))
            for tau in (0.05, 0.15, 0.4):
                d = (tau * e).reshape(P, 3).T
                p1, p2 = self._clip(a + d), self._clip(a - d)
                e1, e2 = self.smp.errors(p1)[members], self.smp.errors(p2)[members]
                score = np.minimum(e1, e2).sum()
                if best is None or score < best[0]:
                    best = (score, p1, p2, e1 < e2)
        if best is None or best[0] >= E.sum():
            return None
        _, p1, p2, first = best
        f1 = f2 = None
        for _ in range(25):
            if min(first.sum(), (~first).sum()) < self.min_texels:
                return None
            f1 = self.fit(members[first], init=p1)
            f2 = self.fit(members[~first], init=p2)
            p1, p2 = f1.channel_params, f2.channel_params
            new = self.smp.errors(p1)[members] < self.smp.errors(p2)[members]
            if np.array_equal(new, first):
                break
            first = new
        return f1, f2, first

    def held_out_gain(self, parent: LafortuneFit, f1: LafortuneFit, f2: LafortuneFit,
                      members: np.ndarray) -> tuple[float, float]:
        """Held-out gain of a split and its z-score over texels.

        Per texel, labelled by its error on one half of its samples, the gain on the other half is
        g = (E_parent - E_child) / (E_parent + E_child), in [-1, 1]: bounded, so a few texels whose
        highlight sits in the wrong place (a bump the mesh lacks) cannot outweigh the rest, as
        they would in a mean of raw errors. Both ways round, averaged.
        """
        h0 = self.smp.half_errors(parent.channel_params, s=self.s)[:, members]
        h1 = self.smp.half_errors(f1.channel_params, s=self.s)[:, members]
        h2 = self.smp.half_errors(f2.channel_params, s=self.s)[:, members]
        counts = [np.bincount(self.smp.texel, (self.smp.half == h) * self.smp.w,
                              minlength=self.smp.n_texels)[members] for h in (0, 1)]
        both = (counts[0] > 0) & (counts[1] > 0)
        gains = []
        for a, b in ((0, 1), (1, 0)):  # label by one half, score on the other, both ways
            child = np.where(h1[a] < h2[a], h1[b], h2[b])
            gains.append((h0[b] - child) / np.maximum(h0[b] + child, 1e-300))
        gain = ((gains[0] + gains[1]) / 2)[both]
        if len(gain) < 2:
            return 0.0, 0.0
        z = gain.mean() / max(gain.std(ddof=1) / np.sqrt(len(gain)), 1e-300)
        return float(gain.mean()), float(z)

    def recluster(self, fits: list, labels: np.ndarray, *, max_rounds: int = 10, tol: float = 0.005):
        """Global reclustering (Eq. 10): every texel to its best cluster, refit, repeat."""
        for _ in range(max_rounds):
            E = np.stack([self.smp.errors(f.channel_params) for f in fits])
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


def split_recluster_fit(smp: _Samples, *, n_materials: int | None, n_lobes: int = 1,
                        max_materials: int = 12, intensity_weight: float = 1.0,
                        min_texels: int = 10, min_gain: float = 0.02, z_min: float = 4.0,
                        noise: str = "absolute", progress=None) -> Clustering:
    """Cluster the texels of ``smp`` into materials (Sec. 7, Fig. 7).

    Start from one cluster holding everything; repeatedly split the cluster with the largest
    error E(C) (Eq. 8) by :meth:`_Clusterer.split`, then recluster globally (Eq. 10). With
    ``n_materials`` given, stop once that many clusters exist (the paper's termination, Sec. 7.4);
    with None, keep a split only when its held-out gain passes ``min_gain`` and ``z_min`` (see the
    module docstring) and stop when no cluster's split passes, or at ``max_materials``.
    """
    cl = _Clusterer(smp, n_lobes=n_lobes, intensity_weight=intensity_weight,
                    min_texels=min_texels, min_gain=min_gain, z_min=z_min, noise=noise)
    everyone = np.arange(smp.n_texels)
    single = cl.fit(everyone)
    fits = [single]
    labels = np.zeros(smp.n_texels, np.int64)
    history = []
    target = max_materials if n_materials is None else n_materials
    refused: set = set()  # clusters (by member count signature) whose split was refused
    while len(fits) < target:
        E = np.stack([smp.errors(f.channel_params) for f in fits])
        cluster_error = np.array([E[k, labels == k].sum() for k in range(len(fits))])  # Eq. 8
        done = False
        for k in np.argsort(cluster_error)[::-1]:
            members = np.flatnonzero(labels == k)
            key = (len(members), int(members[:1].sum()) if len(members) else -1)
            if key in refused or len(members) < 2 * min_texels:
                continue
            out = cl.split(fits[k], members)
            if out is None:
                refused.add(key)
                history.append(f"cluster {k} ({len(members)} texels): no split possible")
                continue
            f1, f2, first = out
            gain, z = cl.held_out_gain(fits[k], f1, f2, members)
            ok = n_materials is not None or (gain > min_gain and z > z_min)
            history.append(f"cluster {k} ({len(members)} texels) -> {first.sum()} + {(~first).sum()}: "
                           f"held-out gain {gain:.3f}, z = {z:.1f} "
                           f"{'kept' if ok else 'refused'}")
            if not ok:
                refused.add(key)
                continue
            fits[k] = f1
            fits.append(f2)
            labels[members[~first]] = len(fits) - 1
            fits, labels = cl.recluster(fits, labels)
            refused = set()
            done = True
            break
        if progress is not None:
            progress(len(fits), target)
        if not done:
            break
    return Clustering(fits=tuple(fits), labels=labels, history=tuple(history), single=single)
