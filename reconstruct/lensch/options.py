"""Settings of :func:`~reconstruct.lensch.fit_svbrdf`, one frozen object (as ``scipy.optimize``
takes a solver's settings), checked when made so that a bad value is named before any fitting."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .lafortune_fit import LafortuneFitError


class SvbrdfError(LafortuneFitError):
    """Inputs :func:`~reconstruct.lensch.fit_svbrdf` cannot use; the message names the argument."""


@dataclass(frozen=True)
class SvbrdfOptions:
    """How :func:`~reconstruct.lensch.fit_svbrdf` fits (Lensch et al. 2003, Secs. 7-9).

    Attributes
    ----------
    n_materials : int, optional
        Number of clusters, each its own material; None: clusters decided from the data
        (held-out split test, see :mod:`reconstruct.lensch.clustering`), at most
        ``max_materials``, and clusters that no held-out test tells apart counted as one
        material (:attr:`~reconstruct.lensch.SvbrdfFit.cluster_material`).
    n_lobes : int
        Lafortune lobes per material.
    fit_normals : bool
        Fit a normal per texel (Sec. 9), then refit the cluster BRDFs and project again.
    pfa : bool
        Refine each cluster's basis by principal function analysis (Eq. 13).
    noise : {"absolute", "relative"}
        Noise model of the BRDF fits (see :func:`~reconstruct.lensch.fit_lafortune`) and of the
        texels' labels (Eq. 10; "relative": Eq. 6 divided by the model's squared value, see
        :func:`~reconstruct.lensch.clustering.sample_errors`); the clustering's splits use the
        squared error either way.
    max_materials : int
        Cap on clusters (so on materials) when ``n_materials`` is None.
    cluster_texels : int
        Texels used for clustering, chosen favouring likely highlights (Sec. 7.1). Not fewer
        where each has many samples: on DiLiGenT pot1 clustering ~720 texels (50,000 samples)
        instead of 4000 started the final fit elsewhere (normals 8.8 deg instead of 7.6).
    fit_texels : int
        Most texels per cluster for the final fit of its BRDF.
    fit_samples : int
        About the most samples per cluster for that fit (fewer texels drawn where they have many
        samples each): 7 parameters per channel (2 lobes) are pinned long before 50,000
        samples, and DiLiGenT's 5000 texels x 70 samples made each of the three refits ~20 s
        of CPU.
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
        misses by more than ``robust_spread`` robust standard deviations of its texel's residuals (plus 5 % of
        the prediction): cast shadows (dark where the model is lit) and inter-reflections
        (bright where it is not), which the paper's synthetic and mesh-shadowed data lack and
        which pull a normal towards the wrong side on real photographs. The BRDF refit of that
        round uses the same samples; the RMS columns still count every sample.
    robust_spread : float
        How many robust standard deviations of its texel's residuals a sample may miss by and
        stay in (``robust_samples``). 3 keeps nearly every sample of Gaussian noise; on DiLiGenT
        1.5 (with ``brightest_dropped`` 0.1) brought the normals 0.4-0.9 deg closer on pot1,
        bear and goblet (benchmarks/diligent.py --ablation, docs/diligent.md).
    brightest_dropped : float
        Share (0 <= x < 1) of each texel's brightest samples (rank by channel-summed
        reflectance within the texel) left out of normal fitting and that round's refit, as
        ST14 (Shi et al. 2014) fits only the low-intensity part of each pixel's observations: a
        glossy metal's brightest samples mix the highlight with inter-reflections the
        lobes cannot express (DiLiGenT's goblet: 16.5 -> 15.2 deg at 0.1; 0.2 and more cost
        pot1's painted pattern its highlight evidence: +0.2 deg).
    shadow_ratio : float, optional
        In the last round of normal fitting (Sec. 9; not in the BRDF refits nor in the peak
        test), leave out each texel's samples whose channel-summed reflectance is below this
        share of the texel's median (None: none): in a cast shadow a light above the texel's
        horizon leaves it dark, and a normal tilted to put that light below its horizon explains
        the darkness as an attached shadow, which Tukey's loss does not undo (the tilted model
        fits those samples). Only in the last round: in every round, from the photometric-stereo
        normals on, it made DiLiGenT's goblet relight worse than the Lambertian reference on a
        draw of 5000 texels where it had not, and on another the first round's error rose 1.74x
        (undone); in the last round alone, 0.1 brought pot1's normals 0.24 deg and goblet's
        0.51 deg closer, relighting still ahead (docs/diligent.md, round lensch10). In every round
        with a round it worsens run again without it: 0.04 deg closer over three draws, within
        their spread, for goblet's relighting 0.0062 worse on one draw (round lensch12, not kept).
    tukey_cutoff : float, optional
        Fit each texel's normal (Sec. 9) under Tukey's biweight loss on each sample's RGB
        residual, cut off at this many robust standard deviations (1.4826 x the median residual
        at the round's start normal) of the texel's own residuals, instead of least squares
        (None, the paper's): a per-texel adaptive selection, so that the samples the lobe about
        the texel's own normal cannot explain (inter-reflections, cast shadows the hard
        ``robust_samples`` cut kept) fade out as the normal moves, rather than being chosen once
        from the previous round's normal. 4.685 is the usual 95 %-efficiency constant; on
        DiLiGenT 2 did better on pot1, bear and goblet (docs/diligent.md) and is what
        ``gonio process`` runs on imported sets.
    peak_ratio : float, optional
        The peak test of the normal fit (None: none; see
        :func:`~reconstruct.lensch.normals.fit_normals_chunk`): a texel whose brightest sample
        exceeds this many times what its fitted BRDF predicts about its fitted normal has lost
        its highlight to the fit; its normal is held near that sample's half vector.
    peak_compare : bool
        With the peak test, keep a held normal only where it fits all the texel's samples at
        least as well as the free fit's (True, under Tukey's loss); False: every texel the test
        flags is held (with ``interreflection_lobe`` its free fit's normal becomes its
        inter-reflection axis).
    interreflection_lobe : bool
        Give each texel the peak test holds a second, inter-reflection lobe: its material's
        lobes alone (the ``lobes_alone`` slot) about the normal its free fit found, with a
        non-negative weight of its own fitted with the projection (Sec. 8) and added to every
        prediction. On a mirror-like object that reflects itself (DiLiGenT's goblet) a light's
        image in the object is a second highlight, as sharp as the first, about another axis:
        the one the free fit follows (docs/diligent.md). Needs ``lobes_alone``.
    interreflection_diffuse : bool
        With ``interreflection_lobe``, after the normal fit each held texel's projection (Sec. 8)
        also gets a diffuse term about its input normal (the photometric-stereo normal its frame
        was built on; its material's diffuse colour, a non-negative weight of its own): a texel
        the peak test holds at its highlight is lit besides by the object, broadly, which the
        held model cannot express and the Lambertian reference explains about that normal.
        Trained on the texel's own samples only; the normals do not move (DiLiGenT's goblet:
        docs/diligent.md, round lensch11).
    texel_undo : bool
        A texel the peak test held stays out of the round's BRDF refits where its free fit's
        normal (its inter-reflection axis; no lobe), projected into the basis, fits its samples
        better than the held normal with its inter-reflection lobe; after the refits, the same
        test under the new basis sends it back to its free fit's normal: the round's undo per
        texel, before the round as a whole is judged (``undo_ratio``). Needs
        ``interreflection_lobe``.
    undo_tukey : float, optional
        With ``texel_undo``, compare a held texel's two models by Tukey's loss cut off at this
        many robust sigmas of its free fit's residuals (light neither explains counts little)
        instead of by their squared errors (None).
    undo_margin : float
        With ``texel_undo``, a held texel goes back to its free fit's normal only where that
        fits its samples more than this many times better (1: any better).
    undo_ratio : float
        A normal-fitting round that raises the projection's total error more than this many
        times is undone, and ends the fitting (inf: never undone).
    lobes_alone : bool
        Add each material's lobes without its diffuse term to its projection basis (Sec. 8), so
        that a texel's highlight strength is free of its diffuse albedo.
    lm_stall : (int, float), optional
        ``(window, rtol)``: each Lafortune fit of the clustering and of the materials' refits also
        stops where its cost fell by less than ``rtol`` over its last ``window`` iterations (None:
        only at a step's gain below 1e-8 or 200 iterations). On DiLiGenT's goblet 16 of 42
        clustering fits ran all 200 iterations, crawling (two lobes trading energy) by 1e-6 to
        1e-5 of the cost an iteration, 2/3 of the clustering's CPU (docs/diligent.md).
    relabel_normals : bool
        At the start of each round of normal fitting, label every texel again by Eq. 10 with its
        normal free: under each material alone (with a scale) the normal that fits its samples
        best, then the material of least residual, and start the round's normal fit from that
        material's normal. Eq. 10 about the mesh normal mislabels texels on relief the mesh
        lacks: their highlight sits where no material's lobe about the mesh normal puts it, so
        a broader or off-specular material wins (quick demo: 403 of 9,438 texels, their mesh
        normals 9.4 deg off the truth against 1.2 for the rest, 43 % of the held-out squared
        error). Costs one normal fit per material per round.
    refresh_confidence : bool
        After each round of normal fitting, the materials' refits trust the texels Eq. 10 finds
        confident (:func:`~reconstruct.lensch.svbrdf._confident`) about the new normals rather
        than the mesh's: texels whose highlight the mesh normal misplaced, the ones that pin a
        sharp lobe, otherwise stay out of the refits after their normals are found (full demo:
        held-out 1.66 -> 1.51x the floor). Where that round raises the training error, its refit
        falls back to the mesh normals' choice before the round is undone.
    max_footprint_spread_deg : float
        Texels whose normal turns by more than this across their pixel footprint (the
        ``footprint_spread`` given to :func:`~reconstruct.lensch.fit_svbrdf`, degrees) take no
        part in material discovery (clustering, the split test) nor in the materials' fits: their
        reflectance mixes normals, so no one normal explains it and a sharp material looks like
        a broader one. They are still labelled, projected and given a normal like every texel.
        Default inf (none left out): at 6 deg the bumpy object's blue material went 45 % -> 73 %
        into one cluster on one capture, but the material count did not fall anywhere and rose
        on two of three runs (quick demo 3 -> 4, another capture 4 -> 5; docs/methods.md).
    normal_broadening : float, optional
        Broaden each texel's lobes when it predicts by its fitted normal's uncertainty (None:
        not; :mod:`~reconstruct.lensch.broadening`): the angular variance
        ``normal_broadening`` x e^2 (rad^2) is added to each lobe's 1/N, e the fitted normals'
        turn against the texel's pixel neighbours beyond the mesh normals' (needs
        ``fit_normals``, the normals and the texels' ``neighbours``). A mirror lobe moves by
        twice a normal's error: 2 spreads a texel's lobe over an error of RMS magnitude e. At 2
        the full demo's held-out error went 1.515 -> 1.480x the floor (1.474x at 4, 1.487x at 8)
        and the quick demo's 1.79 -> 1.70x; the bumpy test object (captured settings) 0.539 ->
        0.527 held out, where 4 gave 0.539 (docs/measurements.md, round floor4).
    chunk_texels : int
        Texels per chunk of the per-texel steps.
    discovery_texels : int
        Most texels material discovery (the clustering and each material's fits, redone after
        each normal-fitting round) works on: a random subsample of that many when there are
        more, whose samples are held in memory (Lensch et al. fitted 1.6-3.6 million
        lumitexels; the clustering itself picks ``cluster_texels`` of these). The default
        covers every session gonio has met (the demo: 37 k texels).
    """

    n_materials: int | None = None
    n_lobes: int = 1
    fit_normals: bool = False
    pfa: bool = False
    noise: str = "absolute"
    max_materials: int = 12
    cluster_texels: int = 4000
    fit_texels: int = 20_000
    fit_samples: int = 50_000
    min_samples: int = 3
    normal_rounds: int = 2
    weight_prior: float = 1e-3
    select_projection: bool = True
    robust_samples: bool = False
    relabel_normals: bool = False
    refresh_confidence: bool = False
    max_footprint_spread_deg: float = float("inf")
    robust_spread: float = 3.0
    brightest_dropped: float = 0.0
    shadow_ratio: float | None = None
    tukey_cutoff: float | None = None
    peak_ratio: float | None = None
    lobes_alone: bool = False
    peak_compare: bool = True
    interreflection_lobe: bool = False
    interreflection_diffuse: bool = False
    texel_undo: bool = False
    undo_tukey: float | None = None
    undo_margin: float = 1.0
    undo_ratio: float = 1.05
    lm_stall: tuple[int, float] | None = None
    normal_broadening: float | None = None
    chunk_texels: int = 100_000
    discovery_texels: int = 200_000

    def __post_init__(self):
        def whole(name, least):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < least:
                raise SvbrdfError(f"{name} must be an integer >= {least}, got {v!r}")
        if self.n_materials is not None:
            whole("n_materials", 1)
        for name in ("n_lobes", "max_materials", "cluster_texels", "fit_texels",
                     "fit_samples", "chunk_texels", "discovery_texels"):
            whole(name, 1)
        whole("min_samples", 0)
        whole("normal_rounds", 0)
        if self.noise not in ("absolute", "relative"):
            raise SvbrdfError(f"noise must be 'absolute' or 'relative', got {self.noise!r}")
        if not self.robust_spread > 0:
            raise SvbrdfError(f"robust_spread must be > 0, got {self.robust_spread!r}")
        if self.shadow_ratio is not None and not 0 < self.shadow_ratio < 1:   # also refuses NaN
            raise SvbrdfError(f"shadow_ratio must be a share of the texel's median in (0, 1) or None, "
                              f"got {self.shadow_ratio!r}")
        if self.tukey_cutoff is not None and not self.tukey_cutoff > 0:   # also refuses NaN
            raise SvbrdfError(f"tukey_cutoff must be > 0 robust sigmas or None, got {self.tukey_cutoff!r}")
        if self.normal_broadening is not None and not (np.isfinite(self.normal_broadening)
                                                       and self.normal_broadening > 0):
            raise SvbrdfError(f"normal_broadening must be a finite factor > 0 or None, got {self.normal_broadening!r}")
        if self.peak_ratio is not None and not self.peak_ratio > 0:
            raise SvbrdfError(f"peak_ratio must be > 0 or None, got {self.peak_ratio!r}")
        if not self.undo_ratio >= 1:   # also refuses NaN
            raise SvbrdfError(f"undo_ratio must be >= 1 (inf: never undo), got {self.undo_ratio!r}")
        if self.interreflection_lobe and not (self.lobes_alone and self.peak_ratio is not None):
            raise SvbrdfError("interreflection_lobe needs lobes_alone=True (its lobe is that slot) and a "
                              f"peak_ratio (its axis is the free fit of a held texel), got lobes_alone="
                              f"{self.lobes_alone!r}, peak_ratio={self.peak_ratio!r}")
        if self.interreflection_diffuse and not self.interreflection_lobe:
            raise SvbrdfError("interreflection_diffuse needs interreflection_lobe=True (its axis is that lobe's)")
        if self.undo_tukey is not None and not (self.undo_tukey > 0 and self.texel_undo):
            raise SvbrdfError(f"undo_tukey must be > 0 robust sigmas, with texel_undo=True, or None; got "
                              f"undo_tukey={self.undo_tukey!r}, texel_undo={self.texel_undo!r}")
        if not self.undo_margin >= 1:   # also refuses NaN
            raise SvbrdfError(f"undo_margin must be >= 1, got {self.undo_margin!r}")
        if self.texel_undo and not self.interreflection_lobe:
            raise SvbrdfError("texel_undo needs interreflection_lobe=True (a held texel's alternative is its "
                              "inter-reflection axis)")
        stall = self.lm_stall
        if stall is not None and not (isinstance(stall, (tuple, list)) and len(stall) == 2
                                      and isinstance(stall[0], (int, np.integer)) and not isinstance(stall[0], bool)
                                      and stall[0] >= 1 and isinstance(stall[1], (int, float, np.floating))
                                      and 0 < stall[1] < 1):
            raise SvbrdfError(f"lm_stall must be (window: an integer >= 1, rtol in (0, 1)) or None, got {stall!r}")
        if not 0 <= self.brightest_dropped < 1:
            raise SvbrdfError(f"brightest_dropped must be a share in [0, 1), got {self.brightest_dropped!r}")
        if not self.max_footprint_spread_deg > 0:   # also refuses NaN
            raise SvbrdfError("max_footprint_spread_deg must be > 0 degrees, got "
                              f"{self.max_footprint_spread_deg!r}")
        if not np.isfinite(self.weight_prior) or self.weight_prior < 0:
            raise SvbrdfError(f"weight_prior must be finite and >= 0, got {self.weight_prior!r}")

    def but(self, **settings) -> SvbrdfOptions:
        """A copy with ``settings`` changed; an unknown name is an :class:`SvbrdfError` naming it."""
        known = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(settings) - known)
        if unknown:
            raise SvbrdfError(f"unknown fit_svbrdf setting(s) {', '.join(unknown)}; "
                              f"SvbrdfOptions has {', '.join(sorted(known))}")
        return dataclasses.replace(self, **settings) if settings else self
