"""Spatially varying BRDF and normal map from lumitexels (Lensch et al. 2003, Secs. 7-9).

:func:`fit_svbrdf` runs the whole method: highlight-favouring texel selection (Sec. 7.1),
split-recluster-fit clustering (7.2-7.4), labelling of every texel (Eq. 10), projection into
per-cluster bases (Sec. 8) with optional PFA (Eq. 13), optional normal fitting (Sec. 9) followed by
refitting the cluster BRDFs and projecting again. Per-texel steps run over chunks of texels
through the pure functions of :mod:`~reconstruct.lensch.projection` and
:mod:`~reconstruct.lensch.normals`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..brdf import Lafortune
from ..frames import normalize, tangent_frames, to_local, to_world
from .clustering import _Samples, deal_halves, split_recluster_fit
from .lafortune_fit import (MAX_LOBE_ALBEDO, LafortuneFitError, albedo_unit, check_samples,
                            fit_geometry, lobe_geometry, model_of, params_of)
from .normals import fit_normals_chunk
from .projection import (basis_values, cluster_errors, cluster_residuals, make_bases, pfa_refine,
                         project_chunk)


class SvbrdfError(LafortuneFitError):
    """Inputs :func:`fit_svbrdf` cannot use; the message names the argument."""


#: Keys of :attr:`SvbrdfFit.rms`, the columns of the paper's Table II.
RMS_COLUMNS = ("single", "cluster", "projection", "pfa", "normal_fit")


@dataclass(frozen=True)
class SvbrdfFit:
    """Result of :func:`fit_svbrdf` for T texels, K clusters, B basis slots.

    Attributes
    ----------
    labels : ndarray (T,) int
        Material (cluster) index of every texel: the cluster whose BRDF fits its samples best
        (Eq. 10); also a best guess for flagged texels.
    materials : tuple of Lafortune
        The cluster BRDFs, ``materials[k]`` for label k (``rho_d`` = pi x the paper's rho_d).
    material_covariance : tuple of ndarray (P, P)
        Covariance of each material's flat parameters (layout of
        :class:`~reconstruct.lensch.LafortuneFit`).
    basis : tuple of tuple of Lafortune
        Projection basis per cluster (Sec. 8.1): the cluster's BRDF, rho_d and N raised / lowered,
        the most similar other cluster (after PFA when it ran).
    weights : ndarray (T, B)
        Non-negative weights of each texel over its cluster's basis, shared by the colour channels
        (Eqs. 11-12); slots beyond ``len(basis[k])`` are 0.
    normals : ndarray (T, 3) or None
        Fitted unit normals (Sec. 9) in the frame of the ``normals`` given to :func:`fit_svbrdf`
        (object frame for lumitexels), or in each texel's local frame if none were given.
    normals_local : ndarray (T, 3) or None
        The same in each texel's input local frame (+z = the mesh normal).
    rms : dict
        The paper's Table II columns over all samples and channels, 1/sr: ``single`` (one average
        BRDF), ``cluster`` (per-cluster BRDFs), ``projection``, ``pfa`` (None unless ``pfa``),
        ``normal_fit`` (None unless ``fit_normals``).
    relative_rms : dict
        The same divided by the RMS of the measured reflectance.
    too_few_samples : ndarray (T,) bool
        Texels with fewer than ``min_samples`` samples (label and weights are guesses; normal kept).
    no_highlight : ndarray (T,) bool
        No sample of the texel reached 10 % of its material's lobe peak: its specular part is
        extrapolated from the cluster, not measured (Sec. 11).
    n_samples : ndarray (T,) int
        Samples per texel.
    history : tuple of str
        The clustering's split decisions, then any normal-fitting round that was undone.
    """

    labels: np.ndarray
    materials: tuple
    material_covariance: tuple
    basis: tuple
    weights: np.ndarray
    normals: np.ndarray | None
    normals_local: np.ndarray | None
    rms: dict
    relative_rms: dict
    too_few_samples: np.ndarray
    no_highlight: np.ndarray
    n_samples: np.ndarray
    history: tuple = field(default=())

    @property
    def n_materials(self) -> int:
        return len(self.materials)

    def brdf(self, texels=None) -> Lafortune:
        """The per-texel BRDFs as one Lafortune model with per-sample parameters (for the renderer).

        A weighted sum of Lafortune BRDFs is a Lafortune BRDF with all their lobes:
        t max(0, C.x)^N = max(0, t^(1/N) C.x)^N. Returns parameters for ``texels`` (int array,
        default all): ``rho_d`` (n, 3), lobes ``cx``, ``cz``, ``n`` (B L, n, 3); evaluate it with
        one (wi, wo) pair per texel in the texel's local frame (``normals_local`` when fitted).
        """
        texels = np.arange(len(self.labels)) if texels is None else np.asarray(texels, np.int64)
        K = len(self.basis)
        B = self.weights.shape[1]
        P = 1 + 3 * self.materials[0].n_lobes
        table = np.zeros((K, B, 3, P))
        table[..., 3::3] = 1.0  # unused basis slots (weight 0; a lone material has no neighbour)
        for k, models in enumerate(self.basis):
            for b, m in enumerate(models):
                table[k, b] = params_of(m)
        par = table[self.labels[texels]]  # (n, B, 3, P)
        w = self.weights[texels]  # (n, B)
        rho = np.einsum("nb,nbc->nc", w, par[..., 0])
        N = par[..., 3::3]  # (n, B, 3, L)
        scale = np.where(w[:, :, None, None] > 0,
                         np.maximum(w, 1e-300)[:, :, None, None] ** (1.0 / N), 0.0)
        cx, cz = par[..., 1::3] * scale, par[..., 2::3] * scale

        def lobes(a):  # (n, B, 3, L) -> (B L, n, 3)
            return a.transpose(1, 3, 0, 2).reshape(-1, len(texels), 3)
        return Lafortune(rho_d=rho, cx=lobes(cx), cz=lobes(cz), n=lobes(N))

    def predict(self, texel, wi, wo) -> np.ndarray:
        """Reflectance f_r cos(theta_i) (S, 3) the fit predicts for samples of its texels.

        ``texel`` (S,), ``wi`` / ``wo`` (S, 3) in the texels' *input* local frames (as the fit was
        given them); fitted normals, when present, are applied (point-based rendering of the
        recovered SVBRDF and normal map, as the paper displays its results, Sec. 10).
        """
        texel = np.asarray(texel, np.int64)
        wi = np.asarray(wi, float)
        wo = np.asarray(wo, float)
        if self.normals_local is not None:
            frames = tangent_frames(self.normals_local)[texel]
            wi, wo = to_local(wi, frames), to_local(wo, frames)
        return self.brdf(texel).evaluate(wi, wo) * np.maximum(wi[:, 2:3], 0.0)

    def report(self) -> str:
        cols = "  ".join(f"{k}={'-' if v is None else f'{v:.4g}'}" for k, v in self.rms.items())
        rel = "  ".join(f"{k}={'-' if v is None else f'{v:.4f}'}" for k, v in self.relative_rms.items())
        return (f"Lensch SVBRDF: {len(self.labels)} texels, {self.n_materials} materials, "
                f"{self.weights.shape[1]} basis slots\n  RMS (1/sr): {cols}\n  relative RMS: {rel}\n"
                f"  flagged: {int(self.too_few_samples.sum())} with too few samples, "
                f"{int(self.no_highlight.sum())} without a highlight")


def _check_texel(texel, S, normals):
    tx = np.asarray(texel)
    if tx.shape != (S,):
        raise SvbrdfError(f"texel must have shape ({S},) (one per sample), got {tx.shape}")
    if not np.issubdtype(tx.dtype, np.integer):
        raise SvbrdfError(f"texel must hold integers, got dtype {tx.dtype}")
    if S and tx.min() < 0:
        raise SvbrdfError("texel must be >= 0")
    T = int(tx.max()) + 1 if S else 0
    if normals is not None:
        nr = np.asarray(normals, dtype=np.float64)
        if nr.ndim != 2 or nr.shape[1] != 3 or len(nr) < T:
            raise SvbrdfError(f"normals must have shape (T, 3) with T > max(texel) = {T - 1}, got {nr.shape}")
        if not np.all(np.isfinite(nr)) or np.any(np.abs(np.linalg.norm(nr, axis=1) - 1) > 1e-3):
            raise SvbrdfError("normals must be finite unit vectors")
        T = len(nr)
    return tx.astype(np.int64), T


def _highlight_score(t, z, texel, T):
    """max over a texel's samples of a broad synthetic highlight cos^10(alpha) (Sec. 7.1), (T,)."""
    score = np.zeros(T)
    np.maximum.at(score, texel, np.maximum(z - t, 0.0) ** 10)
    return score


def _no_highlight(t, z, wi, w, texel, T, labels, mats):
    """True where no sample with weight > 0 (held-out samples do not count) reached 10 % of the
    lobe's peak for its light direction, (T,) bool.

    For light u the lobe base C_x (u_x v_x + u_y v_y) + C_z u_z v_z peaks over v at
    |(C_x u_x, C_x u_y, C_z u_z)|; the ratio of a sample's base to that, to the power N, is how far
    up the highlight it sits. ``mats`` (K, 3, P) per-channel parameters (channel mean used).
    """
    seen = np.zeros(len(t))
    cl = labels[texel]
    for k, m in enumerate(mats):
        sel = np.flatnonzero((cl == k) & (w > 0))
        p = m.mean(axis=0)
        for l in range((len(p) - 1) // 3):
            cx, cz, N = p[1 + 3 * l:4 + 3 * l]
            peak = np.sqrt(cx ** 2 * (wi[sel, 0] ** 2 + wi[sel, 1] ** 2) + cz ** 2 * wi[sel, 2] ** 2)
            base = cx * t[sel] + cz * z[sel]
            frac = np.where(base > 0, (np.maximum(base, 0) / np.maximum(peak, 1e-300)) ** N, 0.0)
            seen[sel] = np.maximum(seen[sel], frac)
    return np.bincount(texel, seen >= 0.1, minlength=T) == 0


def fit_svbrdf(texel, wi, wo, reflectance, *, n_materials: int | None = None, n_lobes: int = 1,
               normals=None, fit_normals: bool = False, pfa: bool = False, rng=0, progress=None,
               weight=None, noise: str = "absolute", max_materials: int = 12,
               cluster_texels: int = 4000, cluster_samples: int = 50_000, fit_texels: int = 20000,
               fit_samples: int = 50_000,
               min_samples: int = 3,
               normal_rounds: int = 2, weight_prior: float = 1e-3,
               select_projection: bool = True, robust_samples: bool = False,
               chunk_texels: int = 100_000) -> SvbrdfFit:
    """Fit a spatially varying BRDF (and optionally a normal map) to lumitexels after Lensch et al.

    Parameters
    ----------
    texel : array_like (S,) int
        Texel of each sample, 0..T-1.
    wi, wo : array_like (S, 3)
        Unit directions to the light / camera in the texel's local frame (normal = +z, away from
        the surface; :func:`reconstruct.frames.tangent_frames` of the texel's normal).
    reflectance : array_like (S, 3)
        f_r cos(theta_i), RGB, 1/sr.
    n_materials : int, optional
        Number of clusters; None: decided from the data (held-out split test, see
        :mod:`reconstruct.lensch.clustering`), at most ``max_materials``.
    n_lobes : int
        Lafortune lobes per material.
    normals : array_like (T, 3), optional
        The texels' (mesh) normals, any frame; fitted normals are returned in that frame.
    fit_normals : bool
        Fit a normal per texel (Sec. 9), then refit the cluster BRDFs and project again.
    pfa : bool
        Refine each cluster's basis by principal function analysis (Eq. 13).
    rng : int or numpy.random.Generator
        Seed for texel selection and the held-out halves.
    progress : callable, optional
        ``progress(done, total)`` after each stage (clustering splits, projection chunks, ...).
    weight : array_like (S,), optional
        Sample weights (default 1).
    noise : {"absolute", "relative"}
        Noise model of the BRDF fits (see :func:`~reconstruct.lensch.fit_lafortune`).
    max_materials : int
        Cap on clusters when ``n_materials`` is None.
    cluster_texels : int
        Texels used for clustering, chosen favouring likely highlights (Sec. 7.1).
    cluster_samples : int
        About the most samples those texels may have together (fewer texels where each has many
        samples: the paper's lumitexels have ~11, DiLiGenT's 70).
    fit_texels : int
        Most texels per cluster for the final fit of its BRDF.
    fit_samples : int
        About the most samples per cluster for that fit (fewer texels drawn where they have many
        samples each): 7 parameters per channel (2 lobes) are pinned long before 50,000 samples, and
        DiLiGenT's 5000 texels x 70 samples made each of the three refits ~20 s of CPU.
    min_samples : int
        Texels with fewer samples are flagged ``too_few_samples`` and keep their mesh normal.
    normal_rounds : int
        Rounds of normal fitting -> refit of the cluster BRDFs -> projection (Sec. 9: "can be
        iterated"); the first round's BRDFs were fitted with the mesh normals, whose errors
        broaden the lobes, so a second round sharpens both.
    weight_prior : float
        Ridge on the projection weights towards the cluster's BRDF (see
        :func:`~reconstruct.lensch.projection.project_chunk`); the default 1e-3 only stops a basis
        BRDF that is ~0 at a texel's samples from taking a weight of 10^5 (it would blow up under
        any other light); 0 = the paper's plain projection.
    select_projection : bool
        Keep a texel's projected weights only where their leave-one-out error over its own samples
        beats its cluster's BRDF alone (``select`` of ``project_chunk``); otherwise the texel gets
        the cluster's BRDF. Without it, texels whose highlight a single sample shows fit that
        sample exactly with a sharper / brighter basis BRDF and mispredict held-out lights.
    robust_samples : bool
        Before each round of normal fitting, leave out the samples the current per-texel BRDF
        misses by more than 3 robust standard deviations of its texel's residuals (plus 5 % of
        the prediction): cast shadows (dark where the model is lit) and inter-reflections
        (bright where it is not), which the paper's synthetic and mesh-shadowed data lack and
        which pull a normal towards the wrong side on real photographs. The BRDF refit of that
        round uses the same samples; the RMS columns still count every sample.
    chunk_texels : int
        Texels per chunk of the per-texel steps.

    Returns
    -------
    SvbrdfFit
    """
    wi, wo, r, w = check_samples(wi, wo, reflectance, weight, error=SvbrdfError)
    tx, T = _check_texel(texel, len(wi), normals)
    if n_materials is not None and (not isinstance(n_materials, (int, np.integer)) or n_materials < 1):
        raise SvbrdfError(f"n_materials must be None or an integer >= 1, got {n_materials!r}")
    if isinstance(n_lobes, bool) or not isinstance(n_lobes, (int, np.integer)) or n_lobes < 1:
        raise SvbrdfError(f"n_lobes must be an integer >= 1, got {n_lobes!r}")
    P = 1 + 3 * n_lobes
    if np.count_nonzero(w) < P:
        raise SvbrdfError(f"reflectance has {np.count_nonzero(w)} usable samples, fewer than the {P} "
                          "parameters per channel of one material")
    rng = np.random.default_rng(rng)
    order = np.argsort(tx, kind="stable")  # samples sorted by texel: chunks are contiguous
    tx, wi, wo, r, w = tx[order], wi[order], wo[order], r[order], w[order]
    counts = np.bincount(tx, minlength=T)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    t, z = lobe_geometry(wi, wo)
    cos_i = wi[:, 2]
    # energy conservation, in the data's units: no lobe, and no texel's weighted mix of lobes,
    # may reflect more (a lobe unpinned by its samples otherwise explodes at held-out lights)
    max_albedo = MAX_LOBE_ALBEDO * albedo_unit(r, w)
    stages = 3 + int(pfa) + 2 * normal_rounds * int(fit_normals)
    stage = 0

    def tick():
        nonlocal stage
        stage += 1
        if progress is not None:
            progress(stage, stages)

    # Sec. 7.1: clustering texels, favouring those likely to show a highlight
    usable = np.flatnonzero(counts >= min_samples)
    if len(usable) < 2:
        usable = np.flatnonzero(counts > 0)
    score = _highlight_score(t, z, tx, T)[usable]
    per_texel = counts[usable].mean()
    n_pick = min(cluster_texels, len(usable), max(2, int(cluster_samples / per_texel)))
    prob = (0.25 + score) / (0.25 + score).sum()
    chosen = np.sort(rng.choice(usable, n_pick, replace=False, p=prob))
    smp = _subset(chosen, tx, t, z, cos_i, r, w, rng)
    # clustering fits in absolute units (cheaper); the final fits below use ``noise``
    clus = split_recluster_fit(smp, n_materials=n_materials, n_lobes=n_lobes,
                               max_materials=max_materials,
                               min_texels=max(3, min(10, len(chosen) // 20)), rng=rng)
    tick()

    # Eq. 10 for every texel, then each cluster's BRDF refit on (up to fit_texels of) its texels
    mats = np.stack([f.channel_params for f in clus.fits])
    labels, errors = _label(t, z, cos_i, r, w, tx, T, mats, offsets, chunk_texels)
    fits = _refit(mats, labels, tx, t, z, cos_i, r, w, n_lobes, noise, (fit_texels, fit_samples), rng,
                  max_albedo,
                  texels=_confident(errors))
    mats = np.stack([f.channel_params for f in fits])
    labels, errors = _label(t, z, cos_i, r, w, tx, T, mats, offsets, chunk_texels)
    tick()

    sq_total = float(np.sum(w[:, None] * r ** 2))
    n_res = 3 * float(w.sum())
    rms = dict.fromkeys(RMS_COLUMNS)

    def residual(labels_, materials_):  # sum of squares of the texels' cluster BRDFs, by chunks
        return sum(cluster_residuals(*_chunk(c, offsets, tx, t, z, cos_i, r, w), labels_[c],
                                     materials_).sum() for c in _chunks(T, chunk_texels))
    rms["single"] = _rms(residual(np.zeros(T, np.int64), clus.single.channel_params[None]), n_res)
    rms["cluster"] = _rms(residual(labels, mats), n_res)

    # Sec. 8: bases and projection
    similar = _most_similar(errors, labels, len(mats))
    basis, size = make_bases(mats, similar)
    weights, sse = _project(basis, size, labels, offsets, tx, t, z, cos_i, r, w, T, chunk_texels,
                                 weight_prior, select_projection, max_albedo)
    rms["projection"] = _rms(sse.sum(), n_res)
    tick()
    if pfa:  # Eq. 13 lowers the plain projection's error; kept if the selected one drops too
        trial = _pfa(basis, size, labels, tx, t, z, cos_i, r, w, fit_texels, rng)
        w_pfa, sse_pfa = _project(trial, size, labels, offsets, tx, t, z, cos_i, r, w, T,
                                  chunk_texels, weight_prior, select_projection, max_albedo)
        if sse_pfa.sum() < sse.sum():
            basis, weights, sse = trial, w_pfa, sse_pfa
        rms["pfa"] = _rms(sse.sum(), n_res)
        tick()

    normals_local = normals_out = None
    undone: list[str] = []
    if fit_normals:  # Sec. 9, then refit the clusters' BRDFs in the new frames and project again
        normals_local = np.tile([0.0, 0.0, 1.0], (T, 1))
        wi0, wo0 = wi, wo  # the samples in the mesh normals' frames
        for round_ in range(normal_rounds):
            # a round that raises the total error is undone and ends the fitting (on some
            # clusterings of the demo object a round's refit blew the training error up 10x)
            before = (normals_local, fits, mats, basis, size, weights, sse, wi, wo, t, z, cos_i)
            tilt = np.tile([0.0, 0.0, 1.0], (T, 1))  # relative to the current normals
            w_fit = w * _inliers(basis, size, labels, weights, offsets, tx, t, z, cos_i, r, T,
                                 chunk_texels) if robust_samples else w
            for c in _chunks(T, chunk_texels):
                s = slice(offsets[c.start], offsets[c.stop])
                tilt[c] = fit_normals_chunk(tx[s] - c.start, wi[s], wo[s], r[s], w_fit[s], labels[c],
                                            weights[c], basis, size, min_samples=min_samples)[0]
            normals_local = normalize(to_world(tilt, tangent_frames(normals_local)))
            tick()
            frames = tangent_frames(normals_local)[tx]
            wi, wo = normalize(to_local(wi0, frames)), normalize(to_local(wo0, frames))
            t, z = lobe_geometry(wi, wo)
            # a sample the tilted normal puts below the horizon is predicted dark (model 0)
            visible = (wi[:, 2] > 0) & (wo[:, 2] > 0)
            cos_i = np.where(visible, wi[:, 2], 0.0)
            fits = _refit(mats, labels, tx, t, z, cos_i, r, w_fit, n_lobes, noise, (fit_texels, fit_samples), rng,
                          max_albedo, keep=visible, texels=_confident(errors))
            mats = np.stack([f.channel_params for f in fits])
            basis, size = make_bases(mats, similar)
            if pfa:
                basis = _pfa(basis, size, labels, tx, t, z, cos_i, r, w, fit_texels, rng)
            weights, sse = _project(basis, size, labels, offsets, tx, t, z, cos_i, r, w, T, chunk_texels,
                                 weight_prior, select_projection, max_albedo)
            tick()
            if sse.sum() > 1.05 * before[6].sum():
                undone.append(f"normal-fitting round {round_ + 1} raised the error "
                              f"{sse.sum() / before[6].sum():.2f}x: undone")
                normals_local, fits, mats, basis, size, weights, sse, wi, wo, t, z, cos_i = before
                break
        rms["normal_fit"] = _rms(sse.sum(), n_res)
        if normals is not None:
            normals_out = to_world(normals_local, tangent_frames(np.asarray(normals, float)))
        else:
            normals_out = normals_local

    materials = tuple(model_of(m) for m in mats)
    rel = {k: None if v is None else v / max(np.sqrt(sq_total / n_res), 1e-300) for k, v in rms.items()}
    return SvbrdfFit(
        labels=labels, materials=materials, material_covariance=tuple(f.covariance for f in fits),
        basis=tuple(tuple(model_of(basis[k, b]) for b in range(size[k])) for k in range(len(mats))),
        weights=weights, normals=normals_out, normals_local=normals_local, rms=rms,
        relative_rms=rel, too_few_samples=counts < min_samples,
        no_highlight=_no_highlight(t, z, wi, w, tx, T, labels, mats), n_samples=counts,
        history=(*clus.history, *undone))


def fit_svbrdf_lumitexels(lt, **kw) -> SvbrdfFit:
    """:func:`fit_svbrdf` on a :class:`reconstruct.lumitexels.Lumitexels` (its sample weights and
    normals are used; fitted normals come back in the object frame)."""
    kw.setdefault("normals", lt.normal)
    kw.setdefault("weight", lt.weight)
    return fit_svbrdf(lt.texel, lt.wi, lt.wo, lt.reflectance, **kw)


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def _rms(sse, n_res):
    return float(np.sqrt(sse / max(n_res, 1e-300)))


def _chunks(T, size):
    return [slice(a, min(a + size, T)) for a in range(0, T, size)]


def _chunk(c: slice, offsets, tx, t, z, cos_i, r, w):
    """Samples of texels ``c`` with chunk-local texel indices (texel, t, z, cos_i, r, w)."""
    s = slice(offsets[c.start], offsets[c.stop])
    return tx[s] - c.start, t[s], z[s], cos_i[s], r[s], w[s]


def _sample_index(texels, tx) -> np.ndarray:
    """Indices of the samples of the (sorted, unique) ``texels``; ``tx`` the sorted sample texels."""
    return np.flatnonzero(np.isin(tx, texels))


def _subset(texels, tx, t, z, cos_i, r, w, rng) -> _Samples:
    idx = _sample_index(texels, tx)
    local = np.searchsorted(texels, tx[idx])
    return _Samples(t[idx], z[idx], cos_i[idx], r[idx], w[idx], local, len(texels), deal_halves(local, rng))


def _label(t, z, cos_i, r, w, tx, T, mats, offsets, chunk):
    """Eq. 10 labels (T,) and the errors (K, T) of every texel under every cluster."""
    E = np.zeros((len(mats), T))
    for c in _chunks(T, chunk):
        ct, ctt, cz, cc, cr, cw = _chunk(c, offsets, tx, t, z, cos_i, r, w)
        E[:, c] = cluster_errors(ctt, cz, cc, cr, cw, ct, c.stop - c.start, mats)
    return np.argmin(E, axis=0), E


def _some(members, limit, rng):
    """At most ``limit`` of the (sorted) ``members``, drawn at random, sorted."""
    return np.sort(rng.choice(members, limit, replace=False)) if len(members) > limit else members


def _confident(errors, ratio: float = 1.5, outlier: float = 3.0):
    """Texels a material's fit can trust, (T,) bool: the best cluster fits clearly better than
    the runner-up (second error > ``ratio`` x the best; a texel two materials explain alike would
    pull a fit toward the wrong one if mislabelled), and the best error is within ``outlier`` x
    its cluster's median (a texel whose normal is off shows its highlight in the wrong place)."""
    best = errors.min(axis=0)
    labels = errors.argmin(axis=0)
    median = np.array([np.median(best[labels == k]) if np.any(labels == k) else 0.0
                       for k in range(len(errors))])
    ok = best <= outlier * median[labels]
    if len(errors) >= 2:
        two = np.partition(errors, 1, axis=0)[:2]
        ok &= two[1] > ratio * two[0]
    return ok


def _refit(mats, labels, tx, t, z, cos_i, r, w, n_lobes, noise, limit, rng, max_albedo, keep=None,
           texels=None):
    """Each cluster's BRDF refit on (up to ``limit`` of) its texels (those in the ``texels`` mask
    when it leaves enough), samples in ``keep``; starts from ``mats`` (K, 3, P). ``limit`` is
    (texels, samples): the texels drawn are cut further so that their samples number about
    ``samples``."""
    fits = []
    n_per = np.bincount(tx)
    for k, m in enumerate(mats):
        members = np.flatnonzero(labels == k)
        if texels is not None and np.count_nonzero(texels[members]) >= max(10, len(members) // 10):
            members = members[texels[members]]
        most = min(limit[0], max(10, int(limit[1] * len(members) / max(n_per[members].sum(), 1))))
        idx = _sample_index(_some(members, most, rng), tx)
        if keep is not None:
            idx = idx[keep[idx]]
        if np.count_nonzero(w[idx]) < 1 + 3 * n_lobes:
            idx = np.flatnonzero(w > 0) if keep is None else np.flatnonzero((w > 0) & keep)
        fits.append(fit_geometry(t[idx], z[idx], cos_i[idx], r[idx], w[idx], n_lobes=n_lobes,
                                 init=m, noise=noise, max_albedo=max_albedo))
    return fits


def _inliers(basis, size, labels, weights, offsets, tx, t, z, cos_i, r, T, chunk,
             spread: float = 3.0) -> np.ndarray:
    """Samples the per-texel BRDFs explain, (S,) bool: |r - f cos| (RGB norm) within ``spread``
    robust standard deviations (1.4826 x median) of its texel's residuals, floored at the median
    texel's, plus 5 % of the prediction."""
    keep = np.ones(len(t), bool)
    for c in _chunks(T, chunk):
        s = slice(offsets[c.start], offsets[c.stop])
        ct = tx[s] - c.start
        n = c.stop - c.start
        A = basis_values(t[s], z[s], cos_i[s], ct, labels[c], basis, size)
        pred = np.einsum("sbc,sb->sc", A, weights[c][ct])
        e = np.linalg.norm(r[s] - pred, axis=1)
        order = np.lexsort((e, ct))
        counts = np.bincount(ct, minlength=n)
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        med = np.where(counts > 0, e[order][np.minimum(start + (counts - 1) // 2, len(e) - 1)], 0.0)
        sigma = 1.4826 * np.maximum(med, np.median(med[counts > 0]))
        keep[s] = e <= spread * sigma[ct] + 0.05 * np.linalg.norm(pred, axis=1)
    return keep


def _most_similar(errors, labels, K):
    """For each cluster the other cluster with the least error over its texels (-1 if K == 1)."""
    similar = np.full(K, -1)
    if K < 2:
        return similar
    for k in range(K):
        e = errors[:, labels == k].sum(axis=1)
        e[k] = np.inf
        similar[k] = int(np.argmin(e))
    return similar


def _project(basis, size, labels, offsets, tx, t, z, cos_i, r, w, T, chunk, prior, select, max_albedo):
    weights = np.zeros((T, basis.shape[1]))
    sse = np.zeros(T)
    for c in _chunks(T, chunk):
        ct, ctt, cz, cc, cr, cw = _chunk(c, offsets, tx, t, z, cos_i, r, w)
        weights[c], sse[c] = project_chunk(ct, ctt, cz, cc, cr, cw, labels[c], basis, size,
                                           prior=prior, select=select, max_albedo=max_albedo)
    return weights, sse


def _pfa(basis, size, labels, tx, t, z, cos_i, r, w, limit, rng):
    out = basis.copy()
    for k in range(len(basis)):
        members = _some(np.flatnonzero(labels == k), limit // 4, rng)
        if len(members) == 0:
            continue
        idx = _sample_index(members, tx)
        local = np.searchsorted(members, tx[idx])
        out[k, :size[k]] = pfa_refine(basis[k, :size[k]], local, t[idx], z[idx], cos_i[idx], r[idx], w[idx])
    return out
