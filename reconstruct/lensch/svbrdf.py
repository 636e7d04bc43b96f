"""Spatially varying BRDF and normal map from lumitexels (Lensch et al. 2003, Secs. 7-9).

:func:`fit_svbrdf` runs the whole method: highlight-favouring texel selection (Sec. 7.1),
split-recluster-fit clustering (7.2-7.4), labelling of every texel (Eq. 10), projection into
per-cluster bases (Sec. 8) with optional PFA (Eq. 13), optional normal fitting (Sec. 9) followed by
refitting the cluster BRDFs and projecting again. Per-texel steps run over chunks of texels
through the pure functions of :mod:`~reconstruct.lensch.projection` and
:mod:`~reconstruct.lensch.normals`.
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..brdf import Lafortune
from ..frames import normalize, tangent_frames, to_local, to_world
from ..lumitexels import pixel_neighbours
from .broadening import broadened_lobes, normal_turn_excess
from .clustering import _Samples, deal_halves, judge_materials, relative_error, split_recluster_fit
from .lafortune_fit import (MAX_LOBE_ALBEDO, albedo_unit, check_samples, fit_geometry, lobe_geometry,
                            model_of, params_of)
from .interreflection import Interreflection, axis_lobes, held_extras
from .normals import fit_normals_chunk, tukey_loss
from .options import SvbrdfError, SvbrdfOptions
from .projection import (basis_values, cluster_errors, cluster_residuals, make_bases, pfa_refine,
                         project_chunk)
from .texel_blocks import ArrayBlocks, SampleBlock, TexelBlocks


#: Keys of :attr:`SvbrdfFit.rms`, the columns of the paper's Table II.
RMS_COLUMNS = ("single", "cluster", "projection", "pfa", "normal_fit")


@dataclass(frozen=True)
class SvbrdfFit:
    """Result of :func:`fit_svbrdf` for T texels, K clusters, B basis slots.

    Attributes
    ----------
    labels : ndarray (T,) int
        Cluster index of every texel: the cluster whose BRDF fits its samples best (Eq. 10; with
        ``relabel_normals``, each about its own fitted normal); also a best guess for flagged
        texels. Its material is ``cluster_material[labels]``.
    materials : tuple of Lafortune
        The cluster BRDFs, ``materials[k]`` for label k (``rho_d`` = pi x the paper's rho_d).
    cluster_material : ndarray (K,) int
        The material of each cluster, 0 .. :attr:`n_materials` - 1: clusters that no held-out
        test tells apart are one material (:meth:`~reconstruct.lensch.clustering._Clusterer.materials`;
        judged again about the fitted normals, which can only join them,
        :func:`~reconstruct.lensch.clustering.judge_materials`; each cluster is its own material
        where ``n_materials`` was given). A material's clusters
        beyond its largest are its variants (:attr:`variant`).
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
    variant : ndarray (T,) bool
        Texels in a cluster that is not its material's largest: on relief the mesh lacks, the
        texels that saw a highlight through a normal a few degrees off, which the clustering
        grouped apart (a broader lobe about the mesh normal fits them) and the held-out test
        found to be the same material. Their cluster's BRDF still serves them (Sec. 7.4: extra
        clusters compensate for slightly wrong normals in the projection).
    mixed_footprint : ndarray (T,) bool
        Texels whose normal turns by more than ``max_footprint_spread_deg`` across their pixel
        footprint: left out of material discovery and the materials' fits, then labelled,
        projected and given a normal like the rest (all False when no spread was given).
    history : tuple of str
        The clustering's split decisions, then any normal-fitting round that was undone.
    discovery_texels : int
        The texels material discovery (clustering, the materials' fits) worked on: all of them,
        or a random subsample of ``SvbrdfOptions.discovery_texels``.
    lobe_variance : ndarray (T,) or None
        With ``SvbrdfOptions.normal_broadening``: the angular variance (rad^2) added to each of
        the texel's lobes when it predicts (:func:`~reconstruct.lensch.broadening.broadened_lobes`):
        its fitted normal's uncertainty. The projection weights and the Table II columns are
        those of the sharp lobes (the training samples pinned the normal they were fitted about).
    interreflection : Interreflection or None
        Each texel's inter-reflection lobe (``SvbrdfOptions.interreflection_lobe``), added to
        :meth:`predict`; None without one.
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
    mixed_footprint: np.ndarray
    cluster_material: np.ndarray
    history: tuple = field(default=())
    discovery_texels: int = 0
    lobe_variance: np.ndarray | None = None
    interreflection: Interreflection | None = None

    @property
    def n_materials(self) -> int:
        """Materials found (clusters that held-out tests tell apart), <= ``len(materials)``."""
        return int(self.cluster_material.max()) + 1 if len(self.cluster_material) else 0

    @property
    def variant(self) -> np.ndarray:
        """(T,) bool: texels outside their material's largest cluster (see the class's attributes)."""
        main = np.array([max(np.flatnonzero(self.cluster_material == m),
                             key=lambda k: np.count_nonzero(self.labels == k))
                         for m in range(self.n_materials)], np.int64)
        return main[self.cluster_material[self.labels]] != self.labels

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
        if self.lobe_variance is not None:
            cx, cz, N = broadened_lobes(cx, cz, N, self.lobe_variance[texels][:, None, None, None])

        def lobes(a):  # (n, B, 3, L) -> (B L, n, 3)
            return a.transpose(1, 3, 0, 2).reshape(-1, len(texels), 3)
        return Lafortune(rho_d=rho, cx=lobes(cx), cz=lobes(cz), n=lobes(N))

    def predict(self, texel, wi, wo) -> np.ndarray:
        """Reflectance f_r cos(theta_i) (S, 3) the fit predicts for samples of its texels.

        ``texel`` (S,), ``wi`` / ``wo`` (S, 3) in the texels' *input* local frames (as the fit was
        given them); fitted normals, when present, are applied (point-based rendering of the
        recovered SVBRDF and normal map, as the paper displays its results, Sec. 10), plus each
        texel's inter-reflection lobe where it has one (:attr:`interreflection`).
        """
        texel = np.asarray(texel, np.int64)
        wi = np.asarray(wi, float)
        wo = np.asarray(wo, float)
        other = 0.0 if self.interreflection is None else self.interreflection.predict(texel, wi, wo)
        if self.normals_local is not None:
            frames = tangent_frames(self.normals_local)[texel]
            wi, wo = to_local(wi, frames), to_local(wo, frames)
        return self.brdf(texel).evaluate(wi, wo) * np.maximum(wi[:, 2:3], 0.0) + other

    def report(self) -> str:
        cols = "  ".join(f"{k}={'-' if v is None else f'{v:.4g}'}" for k, v in self.rms.items())
        rel = "  ".join(f"{k}={'-' if v is None else f'{v:.4f}'}" for k, v in self.relative_rms.items())
        return (f"Lensch SVBRDF: {len(self.labels)} texels, {self.n_materials} materials in "
                f"{len(self.materials)} clusters, "
                f"{self.weights.shape[1]} basis slots (materials found on {self.discovery_texels} of "
                f"{len(self.labels)} texels)\n  RMS (1/sr): {cols}\n  relative RMS: {rel}\n"
                f"  flagged: {int(self.too_few_samples.sum())} with too few samples, "
                f"{int(self.no_highlight.sum())} without a highlight, "
                f"{int(self.mixed_footprint.sum())} whose footprint mixes normals (not in material discovery), "
                f"{int(self.variant.sum())} in a variant cluster of their material")


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


def _check_broadening(opt: SvbrdfOptions, neighbours, normals, T: int):
    """``neighbours`` as a (K, T) int array when ``normal_broadening`` is set (else None), or an
    :class:`SvbrdfError` saying what it lacks."""
    if opt.normal_broadening is None:
        return None
    if not opt.fit_normals or normals is None:
        raise SvbrdfError("normal_broadening needs fit_normals=True and the texels' normals (the fitted "
                          "normals' turn is measured against theirs)")
    if neighbours is None:
        raise SvbrdfError("normal_broadening needs neighbours (reconstruct.lumitexels.pixel_neighbours of the texels)")
    nb = np.asarray(neighbours)
    if nb.ndim != 2 or nb.shape[1] != T or not np.issubdtype(nb.dtype, np.integer) or (nb.size and (
            nb.min() < -1 or nb.max() >= T)):
        raise SvbrdfError(f"neighbours must be (K, {T}) integers in [-1, {T - 1}] (one column per texel), "
                          f"got shape {nb.shape}, dtype {nb.dtype}")
    return nb.astype(np.int64)


def _mixed_footprint(spread, T: int, limit: float) -> np.ndarray:
    """Texels whose footprint ``spread`` (T,) degrees exceeds ``limit``, (T,) bool (NaN: not)."""
    if spread is None:
        if np.isfinite(limit):   # a threshold with nothing to compare: say so, not ignore it
            raise SvbrdfError(f"max_footprint_spread_deg is {limit:g} but no footprint_spread was given "
                              "(reconstruct.lumitexels.footprint_normal_spread of the texels)")
        return np.zeros(T, bool)
    sp = np.asarray(spread, dtype=np.float64)
    if sp.shape != (T,):
        raise SvbrdfError(f"footprint_spread must have shape ({T},) (one per texel), got {sp.shape}")
    return np.nan_to_num(sp, nan=0.0) > limit


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


def fit_svbrdf(texel, wi, wo, reflectance, options: SvbrdfOptions | None = None, *, normals=None,
               weight=None, footprint_spread=None, neighbours=None, rng=0, progress=None, **settings) -> SvbrdfFit:
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
    options : SvbrdfOptions, optional
        How to fit (default ``SvbrdfOptions()``).
    normals : array_like (T, 3), optional
        The texels' (mesh) normals, any frame; fitted normals are returned in that frame.
    weight : array_like (S,), optional
        Sample weights (default 1).
    footprint_spread : array_like (T,), optional
        How much each texel's normal turns across its pixel footprint, degrees (NaN: unknown,
        kept); above ``max_footprint_spread_deg`` a texel takes no part in material discovery
        (:func:`reconstruct.lumitexels.footprint_normal_spread`).
    neighbours : array_like (K, T) int, optional
        Each texel's neighbour texels on the image (-1: none;
        :func:`reconstruct.lumitexels.pixel_neighbours`); needed by ``normal_broadening``.
    rng : int or numpy.random.Generator
        Seed for texel selection and the held-out halves.
    progress : callable, optional
        ``progress(done, total)`` after each stage (clustering, projection, normal rounds, ...).
    **settings
        Fields of :class:`SvbrdfOptions` by keyword (``fit_svbrdf(..., fit_normals=True)``),
        applied over ``options``.

    Returns
    -------
    SvbrdfFit
        The same as :func:`fit_svbrdf_blocks` on these samples in blocks of ``chunk_texels``.
    """
    opt = (options or SvbrdfOptions()).but(**settings)
    wi, wo, r, w = check_samples(wi, wo, reflectance, weight, error=SvbrdfError)
    tx, T = _check_texel(texel, len(wi), normals)
    return fit_svbrdf_blocks(ArrayBlocks(tx, wi, wo, r, w, n_texels=T, block_texels=opt.chunk_texels), opt,
                             normals=normals, footprint_spread=footprint_spread, neighbours=neighbours, rng=rng,
                             progress=progress)


def fit_svbrdf_blocks(blocks: TexelBlocks, options: SvbrdfOptions | None = None, *, normals=None,
                      footprint_spread=None, neighbours=None, rng=0, progress=None, map_blocks=None,
                      **settings) -> SvbrdfFit:
    """:func:`fit_svbrdf` over texel blocks: the global steps on a bounded subsample, the
    per-texel steps one block at a time.

    Material discovery (the clustering of Sec. 7 and each material's Lafortune fit, refitted
    after each round of normal fitting) works on at most ``options.discovery_texels`` texels
    drawn at random (all of them when there are no more; :attr:`SvbrdfFit.discovery_texels`
    says how many), whose samples are gathered in memory. Everything else runs block by block,
    each a pure function of (the model so far, one block's samples) -> per-texel arrays: the
    samples per texel and the highlight score (Sec. 7.1), the labels (Eq. 10) and the RMS
    columns, the projection (Sec. 8), the normal fitting (Sec. 9) and the no-highlight flags.
    Per-texel arrays (labels, weights, normals: tens of bytes a texel) are held whole. The
    result does not depend on the blocks (to rounding: per-block sums).

    Parameters
    ----------
    blocks : TexelBlocks
        The samples (validated: unit directions above the surface, finite values), in blocks.
    options, normals, footprint_spread, neighbours, rng, progress, settings
        As :func:`fit_svbrdf`'s.
    map_blocks : callable(fn, list of argument tuples) -> list, optional
        Runs the per-block tasks (module-level functions of ``blocks``, a block index and the
        model so far; results in order): default one after the other here; the pipeline passes
        its executor's (``capture.pipeline.cluster.Executor.map``) to run them on a cluster.
    """
    opt = (options or SvbrdfOptions()).but(**settings)
    T = blocks.n_texels
    mixed = _mixed_footprint(footprint_spread, T, opt.max_footprint_spread_deg)
    neighbours = _check_broadening(opt, neighbours, normals, T)
    P = 1 + 3 * opt.n_lobes
    run = map_blocks or _serial
    nb = range(len(blocks.ranges))
    stats = run(_block_stats, [(blocks, i) for i in nb])   # samples per texel, highlight score (Sec. 7.1), sums
    counts = np.concatenate([st[0] for st in stats]).astype(np.int64) if stats else np.zeros(0, np.int64)
    score = np.concatenate([st[1] for st in stats]) if stats else np.zeros(0)
    n_usable = sum(st[2] for st in stats)
    sq_total = sum(st[3] for st in stats)
    w_total = sum(st[4] for st in stats)
    if n_usable < P:
        raise SvbrdfError(f"reflectance has {n_usable} usable samples, fewer than the {P} "
                          "parameters per channel of one material")
    rng = np.random.default_rng(rng)
    # material discovery on a bounded random subsample (drawn only when it is one)
    if T <= opt.discovery_texels:
        disc = np.arange(T)
    else:
        disc = np.sort(rng.choice(np.flatnonzero(counts > 0), min(opt.discovery_texels,
                                                                   int(np.count_nonzero(counts))), replace=False))
    found = blocks.gather(disc)
    data, _ = _sorted(found, None, opt.chunk_texels)
    # energy conservation, in the data's units: no lobe, and no texel's weighted mix of lobes,
    # may reflect more (a lobe unpinned by its samples otherwise explodes at held-out lights)
    max_albedo = MAX_LOBE_ALBEDO * albedo_unit(data.r, data.w)
    stages = 3 + int(opt.pfa) + 2 * opt.normal_rounds * int(opt.fit_normals)
    stage = 0

    def tick():
        nonlocal stage
        stage += 1
        if progress is not None:
            progress(stage, stages)

    # Sec. 7.1: clustering texels, favouring those likely to show a highlight
    counts_d = counts[disc]
    usable = np.flatnonzero((counts_d >= opt.min_samples) & ~mixed[disc])
    if len(usable) < 2:
        usable = np.flatnonzero(counts_d > 0)
    score_d = score[disc][usable]
    n_pick = min(opt.cluster_texels, len(usable))
    prob = (0.25 + score_d) / (0.25 + score_d).sum()
    chosen = np.sort(rng.choice(usable, n_pick, replace=False, p=prob))
    # clustering fits in absolute units (cheaper); the final fits below use ``noise``, and every
    # label follows it (Eq. 6 relative under multiplicative noise)
    relative = opt.noise == "relative"
    clus = split_recluster_fit(data.subset(chosen, rng), n_materials=opt.n_materials,
                               n_lobes=opt.n_lobes, max_materials=opt.max_materials,
                               min_texels=max(3, min(10, len(chosen) // 20)), rng=rng, stall=opt.lm_stall)
    tick()

    # Eq. 10 for the discovered texels, then each cluster's BRDF refit on (up to fit_texels of) them
    mats = np.stack([f.channel_params for f in clus.fits])
    labels_d, errors_d = _label(data, mats, relative)
    fits = _refit(data, mats, labels_d, opt, rng, max_albedo, texels=_confident(errors_d) & ~mixed[disc])
    mats = np.stack([f.channel_params for f in fits])
    # ... and for every texel, block by block, with the RMS of one and of the clusters' BRDFs
    parts = run(_block_labels, [(blocks, i, mats, clus.single.channel_params[None], _within(disc, blocks.ranges[i]),
                                 relative) for i in nb])
    labels = np.concatenate([p[0] for p in parts])
    errors_d = np.concatenate([p[1] for p in parts], axis=1)
    similar_sums = sum(p[2] for p in parts)
    sse_single = sum(p[3] for p in parts)
    sse_cluster = sum(p[4] for p in parts)
    tick()

    n_res = 3 * w_total
    rms = dict.fromkeys(RMS_COLUMNS)
    rms["single"] = _rms(sse_single, n_res)
    rms["cluster"] = _rms(sse_cluster, n_res)

    # Sec. 8: bases and projection
    similar = _most_similar(similar_sums)
    basis, size = make_bases(mats, similar, lobes_alone=opt.lobes_alone)
    weights, sse, _ = _project(run, blocks, None, basis, size, labels, opt, max_albedo)
    rms["projection"] = _rms(sse.sum(), n_res)
    tick()
    if opt.pfa:  # Eq. 13 lowers the plain projection's error; kept if the selected one drops too
        trial = _pfa(data, basis, size, labels[disc], opt.fit_texels, rng)
        w_pfa, sse_pfa, _ = _project(run, blocks, None, trial, size, labels, opt, max_albedo)
        if sse_pfa.sum() < sse.sum():
            basis, weights, sse = trial, w_pfa, sse_pfa
        rms["pfa"] = _rms(sse.sum(), n_res)
        tick()

    normals_local = normals_out = None
    cluster_material = clus.material
    seen_in = None   # the normals (local) the samples are seen about; None: the mesh normals
    axes = np.full((T, 3), np.nan)   # inter-reflection axes (local; NaN: none)
    axis_w = None
    undone: list[str] = []
    if opt.fit_normals:  # Sec. 9, then refit the clusters' BRDFs in the new frames and project again
        normals_local = np.tile([0.0, 0.0, 1.0], (T, 1))
        for round_ in range(opt.normal_rounds):
            # a round that raises the total error is undone and ends the fitting (on some
            # clusterings of the demo object a round's refit blew the training error up 10x)
            before = (normals_local, seen_in, fits, mats, basis, size, weights, sse, data, labels, axes, axis_w)
            if opt.relabel_normals and len(mats) > 1:   # Eq. 10, each material about its own normal
                parts = run(_block_relabel, [(blocks, i, _part(seen_in, r), mats, opt.min_samples, relative)
                                             for i, r in enumerate(blocks.ranges)])
                labels = np.concatenate([p[0] for p in parts])
                normals_local = seen_in = normalize(to_world(np.concatenate([p[1] for p in parts]),
                                                             tangent_frames(normals_local)))
                weights, sse, axis_w = _project(run, blocks, seen_in, basis, size, labels, opt, max_albedo, axes)
            model = [(_part(seen_in, r), basis, size, labels[r[0]:r[1]], weights[r[0]:r[1]]) for r in blocks.ranges]
            floor = None
            if opt.robust_samples:   # the median over all texels of their median residual
                floor = float(np.median(np.concatenate(run(_block_residual_medians, [(blocks, i, *model[i]) for i in nb]))))
            parts = run(_block_normals, [(blocks, i, *model[i], floor, opt.robust_spread, opt.brightest_dropped,
                                          opt.min_samples, opt.tukey_cutoff, opt.peak_ratio, opt.peak_compare,
                                          opt.shadow_ratio if round_ == opt.normal_rounds - 1 else None)
                                         for i in nb])
            tilt = np.concatenate([p[0] for p in parts]) if T else np.zeros((0, 3))   # relative to the current normals
            if opt.interreflection_lobe and T:   # a newly held texel's axis: its free fit's normal
                new = np.concatenate([p[1] for p in parts])
                held = np.isfinite(new[:, 0])
                axes = axes.copy()
                axes[held] = normalize(to_world(new[held], tangent_frames(normals_local[held])))
            w_fit_d = data.w if floor is None else data.w * _inliers(
                data.chunk(slice(0, data.n_texels)), labels[disc], weights[disc], basis, size, floor, opt.robust_spread)
            if opt.brightest_dropped > 0:
                w_fit_d = w_fit_d * _below_brightest(data.tx, data.r, opt.brightest_dropped)
            normals_local = seen_in = normalize(to_world(tilt, tangent_frames(normals_local)))
            tick()
            # a sample the tilted normal puts below the horizon is predicted dark (model 0)
            data, visible = _sorted(found, normals_local[disc], opt.chunk_texels)
            trusted = [_confident(errors_d) & ~mixed[disc]]   # which texels the refits trust
            if opt.texel_undo and np.isfinite(axes[:, 0]).any():   # not a held texel its free normal fits better
                trusted = [trusted[0] & ~_free_fits_better(run, blocks, seen_in, axes, basis, size, labels, opt,
                                                           max_albedo)[0][disc]]
            if opt.refresh_confidence:   # judged about the new normals first; if that raises the error, the mesh's
                trusted.insert(0, _confident(_label(data, mats, relative)[1]) & ~mixed[disc])
            start = mats
            for trust in trusted:
                fits = _refit(dataclasses.replace(data, w=w_fit_d), start, labels[disc], opt, rng, max_albedo,
                              keep=visible, texels=trust)
                mats = np.stack([f.channel_params for f in fits])
                basis, size = make_bases(mats, similar, lobes_alone=opt.lobes_alone)
                if opt.pfa:
                    basis = _pfa(data, basis, size, labels[disc], opt.fit_texels, rng)
                weights, sse, axis_w = _project(run, blocks, seen_in, basis, size, labels, opt, max_albedo, axes)
                if sse.sum() <= opt.undo_ratio * before[7].sum():
                    break
            if opt.texel_undo and np.isfinite(axes[:, 0]).any():   # the same under the refitted BRDFs, per texel
                free, w_alt, sse_alt = _free_fits_better(run, blocks, seen_in, axes, basis, size, labels, opt,
                                                         max_albedo, (weights, sse, axis_w))
                normals_local = seen_in = np.where(free[:, None], axes, normals_local)
                axes = np.where(free[:, None], np.nan, axes)
                weights, sse = np.where(free[:, None], w_alt, weights), np.where(free, sse_alt, sse)
                axis_w = np.where(free[:, None], 0.0, axis_w)
                data, _ = _sorted(found, normals_local[disc], opt.chunk_texels)
            tick()
            if sse.sum() > opt.undo_ratio * before[7].sum():
                undone.append(f"normal-fitting round {round_ + 1} raised the error "
                              f"{sse.sum() / before[7].sum():.2f}x: undone")
                normals_local, seen_in, fits, mats, basis, size, weights, sse, data, labels, axes, axis_w = before
                break
        if opt.interreflection_diffuse and axis_w is not None:   # the held texels' projection, last
            weights, sse, axis_w = _with_held_diffuse(blocks, seen_in, axes, basis, size, labels, opt, max_albedo,
                                                      weights, sse, axis_w)
        rms["normal_fit"] = _rms(sse.sum(), n_res)
        if seen_in is not None and opt.n_materials is None and len(fits) > 1:
            # Sec. 7.4 / 9: clusters that stood for slightly wrong normals are judged again about
            # the fitted ones (quick demo, one clustering: red's texels that saw their highlight
            # through a tilted normal, fitted apart by a broader lobe, N 15 against 24)
            judged: list[str] = []
            material = judge_materials(
                data.subset(chosen, copy.deepcopy(rng)), fits, labels[disc][chosen], n_lobes=opt.n_lobes,
                min_texels=max(3, min(10, len(chosen) // 20)), rng=copy.deepcopy(rng), stall=opt.lm_stall,
                history=judged, earlier=clus.material)
            if material.max() < clus.material.max():
                undone.append(f"about the fitted normals the clusters make {material.max() + 1} "
                              f"material(s), not {clus.material.max() + 1}: " + "; ".join(judged))
            cluster_material = material
        if normals is not None:
            normals_out = to_world(normals_local, tangent_frames(np.asarray(normals, float)))
        else:
            normals_out = normals_local
    lobe_variance = None
    if opt.normal_broadening is not None:
        lobe_variance = opt.normal_broadening * normal_turn_excess(normals_out, normals, neighbours) ** 2

    no_highlight = np.concatenate(run(_block_no_highlight, [(blocks, i, _part(seen_in, r), labels[r[0]:r[1]], mats)
                                                            for i, r in enumerate(blocks.ranges)])) if T else np.zeros(0, bool)
    materials = tuple(model_of(m) for m in mats)
    rel = {k: None if v is None else v / max(np.sqrt(sq_total / n_res), 1e-300) for k, v in rms.items()}
    return SvbrdfFit(
        labels=labels, materials=materials, material_covariance=tuple(f.covariance for f in fits),
        basis=tuple(tuple(model_of(basis[k, b]) for b in range(size[k])) for k in range(len(mats))),
        weights=weights, normals=normals_out, normals_local=normals_local, rms=rms,
        relative_rms=rel, too_few_samples=counts < opt.min_samples, no_highlight=no_highlight,
        n_samples=counts, mixed_footprint=mixed, cluster_material=cluster_material, history=(*clus.history, *undone), discovery_texels=len(disc),
        lobe_variance=lobe_variance,
        interreflection=None if axis_w is None else Interreflection(
            axes, axis_w, labels, _lobes_alone(basis, size)[:, None],
            _diffuse_colours(basis) if opt.interreflection_diffuse else None))


def fit_svbrdf_lumitexels(lt, options: SvbrdfOptions | None = None, **kw) -> SvbrdfFit:
    """:func:`fit_svbrdf` on a :class:`reconstruct.lumitexels.Lumitexels` (its sample weights,
    normals and footprint spreads are used, and its pixel neighbours where ``normal_broadening``
    needs them; fitted normals come back in the object frame)."""
    kw.setdefault("normals", lt.normal)
    kw.setdefault("weight", lt.weight)
    kw.setdefault("footprint_spread", lt.footprint_spread_deg)
    if "neighbours" not in kw and kw.get("normal_broadening", getattr(options, "normal_broadening", None)) is not None:
        kw["neighbours"] = pixel_neighbours(lt)
    return fit_svbrdf(lt.texel, lt.wi, lt.wo, lt.reflectance, options, **kw)


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Sorted:
    """The samples sorted by texel: ``tx`` (S,) texel, lobe geometry ``t``, ``z``, ``cos_i``,
    reflectance ``r`` (S, 3), weight ``w``; ``offsets`` (T + 1,) where each texel's samples
    start; per-texel steps run over chunks of ``chunk_texels`` texels."""

    tx: np.ndarray
    t: np.ndarray
    z: np.ndarray
    cos_i: np.ndarray
    r: np.ndarray
    w: np.ndarray
    offsets: np.ndarray
    chunk_texels: int

    @property
    def n_texels(self) -> int:
        return len(self.offsets) - 1

    def chunks(self) -> list[slice]:
        T, size = self.n_texels, self.chunk_texels
        return [slice(a, min(a + size, T)) for a in range(0, T, size)]

    def samples(self, c: slice) -> slice:
        return slice(self.offsets[c.start], self.offsets[c.stop])

    def chunk(self, c: slice):
        """Samples of texels ``c`` with chunk-local texel indices (texel, t, z, cos_i, r, w)."""
        s = self.samples(c)
        return self.tx[s] - c.start, self.t[s], self.z[s], self.cos_i[s], self.r[s], self.w[s]

    def index(self, texels) -> np.ndarray:
        """Indices of the samples of the (sorted, unique) ``texels``."""
        return np.flatnonzero(np.isin(self.tx, texels))

    def subset(self, texels, rng) -> _Samples:
        """The samples of ``texels`` re-indexed 0..n-1, for clustering."""
        idx = self.index(texels)
        local = np.searchsorted(texels, self.tx[idx])
        return _Samples(self.t[idx], self.z[idx], self.cos_i[idx], self.r[idx], self.w[idx], local,
                        len(texels), deal_halves(local, rng))


def _rms(sse, n_res):
    return float(np.sqrt(sse / max(n_res, 1e-300)))


def _label(data: _Sorted, mats, relative: bool = False):
    """Eq. 10 labels (T,) and the errors (K, T) of every texel under every cluster (``relative``:
    Eq. 6 under multiplicative noise)."""
    E = np.zeros((len(mats), data.n_texels))
    for c in data.chunks():
        ct, ctt, cz, cc, cr, cw = data.chunk(c)
        E[:, c] = cluster_errors(ctt, cz, cc, cr, cw, ct, c.stop - c.start, mats, relative=relative)
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


def _refit(data: _Sorted, mats, labels, opt: SvbrdfOptions, rng, max_albedo, keep=None, texels=None):
    """Each cluster's BRDF refit on (up to ``opt.fit_texels`` of) its texels (those in the
    ``texels`` mask when it leaves enough), cut further so that their samples number about
    ``opt.fit_samples``; samples in ``keep``; starts from ``mats`` (K, 3, P)."""
    fits = []
    n_per = np.diff(data.offsets)
    for k, m in enumerate(mats):
        members = np.flatnonzero(labels == k)
        if texels is not None and np.count_nonzero(texels[members]) >= max(10, len(members) // 10):
            members = members[texels[members]]
        most = min(opt.fit_texels,
                   max(10, int(opt.fit_samples * len(members) / max(n_per[members].sum(), 1))))
        idx = data.index(_some(members, most, rng))
        if keep is not None:
            idx = idx[keep[idx]]
        if np.count_nonzero(data.w[idx]) < 1 + 3 * opt.n_lobes:
            idx = np.flatnonzero(data.w > 0) if keep is None else np.flatnonzero((data.w > 0) & keep)
        fits.append(fit_geometry(data.t[idx], data.z[idx], data.cos_i[idx], data.r[idx], data.w[idx],
                                 n_lobes=opt.n_lobes, init=m, noise=opt.noise, max_albedo=max_albedo,
                                 stall=opt.lm_stall))
    return fits


def _serial(fn, args):
    return [fn(*a) for a in args]


def _part(per_texel, r):
    """Rows ``r[0]:r[1]`` of a per-texel array (None stays None)."""
    return None if per_texel is None else per_texel[r[0]:r[1]]


def _within(disc, r) -> np.ndarray:
    """The (sorted) texels of ``disc`` inside block ``r``, numbered within it."""
    lo, hi = np.searchsorted(disc, r)
    return disc[lo:hi] - r[0]


# -- the per-block tasks: pure functions of (blocks, block index, the model so far) -------------
def _block_stats(blocks: TexelBlocks, i: int):
    """Samples per texel, the highlight score (Sec. 7.1), and the block's usable samples, sum of
    w r^2 and of w."""
    b = blocks.read(i)
    t, z = lobe_geometry(b.wi, b.wo)
    return (np.bincount(b.texel, minlength=b.n_texels), _highlight_score(t, z, b.texel, b.n_texels),
            int(np.count_nonzero(b.weight)), float(np.sum(b.weight[:, None] * b.reflectance ** 2)),
            float(b.weight.sum()))


def _block_labels(blocks: TexelBlocks, i: int, mats, single, disc, relative: bool = False):
    """Eq. 10 labels of the block's texels, the errors (K, len(disc)) of its discovery texels
    ``disc`` (numbered within the block), the errors of each label's texels under every cluster
    (K, K), and the residual sums of squares under one BRDF (``single``) and the clusters'."""
    b = blocks.read(i)
    _, _, ch, _ = _in_frames(b, None)
    E = cluster_errors(*ch[1:], ch[0], b.n_texels, mats, relative=relative)
    lab = np.argmin(E, axis=0)
    sums = np.stack([E[:, lab == k].sum(axis=1) for k in range(len(mats))])
    return (lab, E[:, disc], sums, float(cluster_residuals(*ch, np.zeros(b.n_texels, np.int64), single).sum()),
            float(cluster_residuals(*ch, lab, mats).sum()))


def _block_project(blocks: TexelBlocks, i: int, normals, basis, size, labels, prior, select, max_albedo, axes=None):
    """Sec. 8 projection of the block's texels: weights (n, B), SSE (n,) and, where ``axes``
    (n, 3) are given (NaN: none), the weights of each texel's inter-reflection lobe (n, 1) (else
    None)."""
    b = blocks.read(i)
    _, _, ch, _ = _in_frames(b, normals)
    if axes is None:
        return (*project_chunk(*ch, labels, basis, size, prior=prior, select=select, max_albedo=max_albedo), None)
    extra = axis_lobes(b.texel, b.wi, b.wo, axes, labels, _lobes_alone(basis, size)[:, None])
    return project_chunk(*ch, labels, basis, size, prior=prior, select=select, max_albedo=max_albedo, extra=extra)


def _lobes_alone(basis, size) -> np.ndarray:
    """Each cluster's lobes alone, (K, 3, P): its basis's last slot (``lobes_alone``)."""
    return basis[np.arange(len(basis)), size - 1]


def _diffuse_colours(basis) -> np.ndarray:
    """Each cluster's diffuse colour at mean 1 (grey where it has none), (K, 3): the colour of a
    held texel's diffuse inter-reflection term (``SvbrdfOptions.interreflection_diffuse``)."""
    rho = basis[:, 0, :, 0]
    mean = rho.mean(axis=1, keepdims=True)
    return np.where(mean > 0, rho / np.where(mean > 0, mean, 1.0), 1.0)


def _with_held_diffuse(blocks: TexelBlocks, normals_local, axes, basis, size, labels, opt: SvbrdfOptions,
                       max_albedo, weights, sse, axis_w):
    """The projection (weights (T, B), SSE (T,), inter-reflection weights (T, 2)) with the held
    texels' (finite ``axes``) projected again with a diffuse term about their input normals
    (``opt.interreflection_diffuse``); the others' as given, their diffuse weight 0. Only the
    held texels' samples are read (a few % of them)."""
    held = np.flatnonzero(np.isfinite(axes[:, 0]))
    b = blocks.gather(held)
    _, _, ch, _ = _in_frames(b, normals_local[held])
    extra = held_extras(b.texel, b.wi, b.wo, axes[held], labels[held], _lobes_alone(basis, size)[:, None],
                        _diffuse_colours(basis))
    w, e, x = project_chunk(*ch, labels[held], basis, size, prior=opt.weight_prior, select=opt.select_projection,
                            max_albedo=max_albedo, extra=extra)
    weights, sse, axis_w = weights.copy(), sse.copy(), np.pad(axis_w, ((0, 0), (0, 1)))
    weights[held], sse[held], axis_w[held] = w, e, x
    return weights, sse, axis_w


def _block_residual_medians(blocks: TexelBlocks, i: int, normals, basis, size, labels, weights):
    """The median residual of each of the block's texels with samples."""
    _, _, ch, _ = _in_frames(blocks.read(i), normals)
    _, _, med, counts = _residual_errors(ch, labels, weights, basis, size)
    return med[counts > 0]


def _block_normals(blocks: TexelBlocks, i: int, normals, basis, size, labels, weights, floor, spread,
                   brightest, min_samples, tukey_cutoff, peak_ratio=None, peak_compare=True, shadow_ratio=None):
    """Sec. 9: the tilt (n, 3) of each of the block's normals from ``normals`` (None: the mesh's),
    on the samples :func:`_inliers` keeps when ``floor`` is given, less each texel's
    ``brightest`` share (:func:`_below_brightest`) and, with ``shadow_ratio``, its samples below
    that share of its median (:func:`_not_dark`), under Tukey's loss with ``tukey_cutoff``;
    with ``peak_ratio``, the texels whose highlight it lost held at their peak (normals.py); and
    the free fit's normals of the texels held (n, 3), relative to ``normals`` (NaN: not held)."""
    b = blocks.read(i)
    wi, wo, ch, _ = _in_frames(b, normals)
    w = ch[5] if floor is None else ch[5] * _inliers(ch, labels, weights, basis, size, floor, spread)
    if brightest > 0:
        w = w * _below_brightest(b.texel, b.reflectance, brightest)
    if shadow_ratio is not None:
        w = w * _not_dark(b.texel, b.reflectance, shadow_ratio)
    out = fit_normals_chunk(b.texel, wi, wo, b.reflectance, w, labels, weights, basis, size, min_samples=min_samples,
                            tukey_c=tukey_cutoff, peak_weight=ch[5], peak_ratio=peak_ratio, peak_compare=peak_compare,
                            return_axes=True)
    return out[0], out[4]


def _block_relabel(blocks: TexelBlocks, i: int, normals, mats, min_samples: int, relative: bool = False):
    """Eq. 10 with the normal free: for each material the block's texels' normal and scale that
    fit their samples best under it alone (:func:`fit_normals_chunk`), then the material of
    least residual; returns the labels (n,) and that material's normals (n, 3), relative to
    ``normals`` (a texel on relief its mesh lacks shows its highlight where no material's lobe
    about the mesh normal puts it, and a wrong material wins). ``relative``: the residuals under
    multiplicative noise (:func:`~reconstruct.lensch.clustering.relative_error`)."""
    b = blocks.read(i)
    wi, wo, _, _ = _in_frames(b, normals)
    n = b.n_texels
    zeros, ones, one = np.zeros(n, np.int64), np.ones((n, 1)), np.ones(1, np.int64)
    sse, tilts = np.empty((len(mats), n)), np.empty((len(mats), n, 3))
    for k, m in enumerate(mats):
        basis = m[None, None]
        tilts[k], scale, _, _ = fit_normals_chunk(b.texel, wi, wo, b.reflectance, b.weight, zeros, ones, basis, one,
                                                  min_samples=min_samples)
        frames = tangent_frames(tilts[k])[b.texel]
        wik, wok = normalize(to_local(wi, frames)), normalize(to_local(wo, frames))
        visible = (wik[:, 2] > 0) & (wok[:, 2] > 0)
        t, z = lobe_geometry(wik, wok)
        pred = basis_values(t, z, np.where(visible, wik[:, 2], 0.0), b.texel, zeros, basis, one)[:, 0]
        model = pred * scale[b.texel]
        err = np.sum((model - b.reflectance) ** 2, axis=1)
        if relative:
            err = relative_error(err, model.mean(axis=1), m)
        sse[k] = np.bincount(b.texel, err * b.weight, minlength=n)
    best = np.argmin(sse, axis=0)
    return best, tilts[best, np.arange(n)]


def _block_no_highlight(blocks: TexelBlocks, i: int, normals, labels, mats):
    """:func:`_no_highlight` of the block's texels."""
    b = blocks.read(i)
    wi, _, (tx, t, z, *_), _ = _in_frames(b, normals)
    return _no_highlight(t, z, wi, b.weight, tx, b.n_texels, labels, mats)


def _in_frames(b: SampleBlock, normals):
    """A block's samples about ``normals`` (n, 3) (the texels' current normals in their input
    local frames; None: the input frames as they are): ``wi``, ``wo``, the per-texel steps'
    tuple (texel, t, z, cos_i, reflectance, weight) and, with normals, which samples stay
    above the horizon (cos_i is 0 for the others)."""
    wi, wo, visible = b.wi, b.wo, None
    cos_i = wi[:, 2]
    if normals is not None:
        frames = tangent_frames(normals)[b.texel]
        wi, wo = normalize(to_local(wi, frames)), normalize(to_local(wo, frames))
        visible = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        cos_i = np.where(visible, wi[:, 2], 0.0)
    t, z = lobe_geometry(wi, wo)
    return wi, wo, (b.texel, t, z, cos_i, b.reflectance, b.weight), visible


def _sorted(b: SampleBlock, normals, chunk_texels: int):
    """One block (the discovery subsample) as :class:`_Sorted`, about ``normals`` as
    :func:`_in_frames`; and its visible mask (None without normals)."""
    _, _, (tx, t, z, cos_i, r, w), visible = _in_frames(b, normals)
    return _Sorted(tx=tx, t=t, z=z, cos_i=cos_i, r=r, w=w, offsets=np.searchsorted(tx, np.arange(b.n_texels + 1)),
                   chunk_texels=chunk_texels), visible


def _residual_errors(ch, labels, weights, basis, size):
    """Per sample |r - f cos| (RGB norm) and |f cos| under the per-texel BRDFs, and per texel the
    median of the former (0 without samples)."""
    tx, t, z, cos_i, r, _ = ch
    n = len(labels)
    A = basis_values(t, z, cos_i, tx, labels, basis, size)
    pred = np.einsum("sbc,sb->sc", A, weights[tx])
    e = np.linalg.norm(r - pred, axis=1)
    return e, np.linalg.norm(pred, axis=1), _texel_medians(e, tx, n), np.bincount(tx, minlength=n)


def _texel_medians(e, tx, n: int) -> np.ndarray:
    """The (lower) median of each texel's values ``e`` (S,) (texel ``tx``), (n,); 0 without samples."""
    order = np.lexsort((e, tx))
    counts = np.bincount(tx, minlength=n)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return np.where(counts > 0, e[order][np.minimum(start + (counts - 1) // 2, len(e) - 1)], 0.0) if len(e) else np.zeros(n)


def _inliers(ch, labels, weights, basis, size, floor: float, spread: float) -> np.ndarray:
    """Samples the per-texel BRDFs explain, (S,) bool: |r - f cos| (RGB norm) within ``spread``
    robust standard deviations (1.4826 x median) of its texel's residuals, floored at
    ``floor`` (the median texel's over all blocks), plus 5 % of the prediction."""
    e, pred, med, _ = _residual_errors(ch, labels, weights, basis, size)
    sigma = 1.4826 * np.maximum(med, floor)
    return e <= spread * sigma[ch[0]] + 0.05 * pred


def _not_dark(texel, reflectance, ratio: float) -> np.ndarray:
    """Samples whose channel-summed reflectance reaches ``ratio`` x their texel's median (the
    lower median of all its samples), (S,) bool: the others are taken for cast shadows."""
    r = reflectance.sum(axis=1)
    return r >= ratio * _texel_medians(r, texel, int(texel.max()) + 1 if len(texel) else 0)[texel]


def _below_brightest(texel, reflectance, share: float) -> np.ndarray:
    """Samples outside each texel's brightest ``share`` (by channel-summed reflectance, rank
    within the texel), (S,) bool."""
    r = reflectance.sum(axis=1)
    order = np.lexsort((r, texel))   # by texel, then brightness
    counts = np.bincount(texel)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.empty(len(r), np.int64)
    rank[order] = np.arange(len(r)) - starts[texel[order]]
    return rank < np.ceil((1.0 - share) * counts)[texel]


def _most_similar(sums):
    """For each cluster the other cluster with the least error over its texels (-1 if K == 1);
    ``sums`` (K, K): row k the errors of cluster k's texels under every cluster, summed."""
    K = len(sums)
    similar = np.full(K, -1)
    if K < 2:
        return similar
    for k in range(K):
        e = sums[k].copy()
        e[k] = np.inf
        similar[k] = int(np.argmin(e))
    return similar


def _project(run, blocks: TexelBlocks, seen_in, basis, size, labels, opt: SvbrdfOptions, max_albedo, axes=None):
    """Sec. 8 projection of every texel, block by block: weights (T, B), SSE (T,) and the
    inter-reflection lobe's weights (T, 1) where ``opt.interreflection_lobe`` and some texel has
    an axis in ``axes`` (T, 3) (else None)."""
    if not (opt.interreflection_lobe and axes is not None and np.isfinite(axes[:, 0]).any()):
        axes = None
    parts = run(_block_project, [(blocks, i, _part(seen_in, r), basis, size, labels[r[0]:r[1]], opt.weight_prior,
                                  opt.select_projection, max_albedo, _part(axes, r))
                                 for i, r in enumerate(blocks.ranges)])
    if not parts:
        return np.zeros((0, basis.shape[1])), np.zeros(0), None
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
            None if axes is None else np.concatenate([p[2] for p in parts]))


def _free_fits_better(run, blocks: TexelBlocks, normals_local, axes, basis, size, labels, opt: SvbrdfOptions,
                      max_albedo, held=None):
    """The held texels (finite ``axes``, (T, 3)) whose free fit's normal (the axis), projected
    into ``basis`` without the inter-reflection lobe, fits their samples better than the held
    normal (``normals_local``) with it (its projection ``held``: weights, SSE, lobe weights;
    projected here if None), by the SSE or, with ``opt.undo_tukey``, Tukey's loss, more than
    ``opt.undo_margin`` times: (T,) bool,
    and that projection's weights (T, B) and SSE (T,)."""
    has = np.isfinite(axes[:, 0])
    if held is None:
        held = _project(run, blocks, normals_local, basis, size, labels, opt, max_albedo, axes)
    free_normals = np.where(has[:, None], axes, normals_local)
    w_alt, sse_alt, _ = _project(run, blocks, free_normals, basis, size, labels, opt, max_albedo)
    if opt.undo_tukey is None:
        return has & (opt.undo_margin * sse_alt < held[1]), w_alt, sse_alt
    parts = run(_block_undo_costs, [(blocks, i, normals_local[r[0]:r[1]], free_normals[r[0]:r[1]], basis, size,
                                     labels[r[0]:r[1]], held[0][r[0]:r[1]], w_alt[r[0]:r[1]], axes[r[0]:r[1]],
                                     held[2][r[0]:r[1]], opt.undo_tukey)
                                    for i, r in enumerate(blocks.ranges)])
    cost_held, cost_free = (np.concatenate([p[j] for p in parts]) for j in (0, 1))
    return has & (opt.undo_margin * cost_free < cost_held), w_alt, sse_alt


def _block_undo_costs(blocks: TexelBlocks, i: int, held_normals, free_normals, basis, size, labels, w_held, w_free,
                      axes, axis_w, cutoff: float):
    """Tukey's loss (``cutoff`` robust sigmas of the free fit's residuals, per texel) of the
    block's held texels (finite ``axes``; 0 for the others) under the held model (its normals,
    weights and inter-reflection lobes) and under the free one, (n,) each: light neither
    explains counts little."""
    b = blocks.read(i)
    n = b.n_texels
    held = np.isfinite(axes[b.texel, 0])   # only the held texels' samples (a few % of them)
    b = dataclasses.replace(b, texel=b.texel[held], wi=b.wi[held], wo=b.wo[held], reflectance=b.reflectance[held],
                            weight=b.weight[held], diffuse=None, specular=None)

    def errors(normals, weights, extra_w):
        _, _, (tx, t, z, cos_i, r, _), _ = _in_frames(b, normals)
        pred = np.einsum("sbc,sb->sc", basis_values(t, z, cos_i, tx, labels, basis, size), weights[tx])
        if extra_w is not None:
            lobes = axis_lobes(b.texel, b.wi, b.wo, axes, labels, _lobes_alone(basis, size)[:, None])
            pred = pred + np.einsum("se,sec->sc", extra_w[tx], lobes)
        return np.linalg.norm(r - pred, axis=1)
    e_held, e_free = errors(held_normals, w_held, axis_w), errors(free_normals, w_free, None)
    sigma = 1.4826 * np.maximum(_texel_medians(e_free, b.texel, n), 1e-12)
    s = cutoff * sigma[b.texel]

    def loss(e):
        return np.bincount(b.texel, tukey_loss(e, s) * b.weight, minlength=n)
    return loss(e_held), loss(e_free)


def _pfa(data: _Sorted, basis, size, labels, limit, rng):
    out = basis.copy()
    for k in range(len(basis)):
        members = _some(np.flatnonzero(labels == k), limit // 4, rng)
        if len(members) == 0:
            continue
        idx = data.index(members)
        local = np.searchsorted(members, data.tx[idx])
        out[k, :size[k]] = pfa_refine(basis[k, :size[k]], local, data.t[idx], data.z[idx],
                                      data.cos_i[idx], data.r[idx], data.w[idx])
    return out
