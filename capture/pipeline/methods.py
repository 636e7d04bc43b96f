"""The reconstruction methods as the pipeline runs them: one adapter per method, one result shape.

Each adapter takes the session's training lumitexels (and the rest of
:class:`capture.process.ProcessInputs`) and returns a :class:`Fitted`: a per-sample predictor
(reflectance ``f_r cos theta_i`` of any lumitexels on the same texels, so held-out samples score
the model), the arrays to store, the parameters it ran with and its headline figures. An adapter
raises :class:`MethodSkipped` with the reason when the captures do not allow the method, so
``gonio process`` can say which methods it skipped and why. The methods' code is imported plainly:
a broken dependency fails the import, never turns into a skipped method.

``lambertian`` is the reference every method must beat: one albedo per texel (closed-form least
squares of ``r = albedo / pi * cos theta_i``), the model a photograph without a reflectance
capture implies.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from reconstruct.brdf import BRDF, Lambertian
from reconstruct.frames import tangent_frames, to_world
from reconstruct.lensch import (ArrayBlocks, SvbrdfFit, SvbrdfOptions, TexelBlocks, fit_svbrdf_blocks,
                              fit_svbrdf_lumitexels)
from reconstruct.lumitexels import Lumitexels, pixel_neighbours
from reconstruct.passive import passive_reflectometry
from reconstruct.sharing import ANGULAR_WEIGHT, FIT_TEXELS, fit_spatial_blocks

from .process import ProcessInputs

__all__ = ["CAPTURED_LENSCH", "METHODS", "lensch_fitted", "DEFAULT_METHODS", "BLOCK_METHODS", "BlockRoute", "sharing_texels_for", "Fitted",
           "MethodSkipped", "fit_method"]


class MethodSkipped(Exception):
    """The method cannot run on this session (the message says why)."""


@dataclass
class Fitted:
    """A fitted model, as the pipeline stores, scores and reports it.

    Attributes
    ----------
    predict_samples : callable(texel, wi, wo) -> ndarray of shape (S, 3)
        Predicted reflectance ``f_r cos theta_i`` of samples: ``texel`` (S,) indexes the training
        lumitexels' texels, ``wi``, ``wo`` (S, 3) unit directions in the texel's local frame
        (mesh normal = +z); a function of each sample alone, so it runs over texel blocks
        (:mod:`capture.pipeline.block_scoring`).
    brdf : callable(ndarray of int) -> BRDF
        The recovered BRDF of the given texels (per-texel parameters, local frame of the
        texel's normal), for BRDF slices.
    arrays : dict of str -> ndarray
        What is stored with the result (per-texel parameters, labels, normals ...).
    params : dict
        The options the method ran with.
    figures : dict
        Headline numbers of the method's own report (JSON-able).
    warnings : list of str
        What a reader must know (e.g. passive reflectometry's adequacy warnings).
    normals : ndarray of shape (T, 3) or None
        Refined normals in the object frame, where the method fits them.
    """

    predict_samples: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    brdf: Callable[[np.ndarray], BRDF]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    params: dict[str, Any] = field(default_factory=dict)
    figures: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    normals: np.ndarray | None = None

    def predict(self, lt: Lumitexels) -> np.ndarray:
        """:attr:`predict_samples` of the samples of ``lt`` (texels of the training lumitexels)."""
        return self.predict_samples(lt.texel, lt.wi, lt.wo)


@dataclass(frozen=True)
class BlockRoute:
    """Where a method's per-texel steps read their samples and run: ``blocks``, the training
    samples one texel block at a time (the stored arrays' :class:`capture.pipeline.stored_blocks.StoredBlocks`,
    texels numbered as the training lumitexels'), and ``map_blocks`` (fn, argument tuples) ->
    results in order (:meth:`capture.pipeline.cluster.Executor.map`: here or on a cluster)."""

    blocks: TexelBlocks
    map_blocks: Callable[[Callable, list], list]


# -- reference: one albedo per texel ------------------------------------------------------------
def _block_albedo(blocks: TexelBlocks, i: int) -> np.ndarray:
    """The least-squares Lambertian albedo (n, 3) of block ``i``'s texels (a per-block task)."""
    b = blocks.read(i)
    return _albedo(b.texel, b.wi, b.reflectance, b.weight, b.n_texels)


def _albedo(texel, wi, reflectance, weight, n_texels: int) -> np.ndarray:
    cos = wi[:, 2].astype(np.float64)
    w = weight.astype(np.float64)
    num = np.stack([np.bincount(texel, w * cos * reflectance[:, c], n_texels) for c in range(3)], axis=1)
    den = np.bincount(texel, w * cos * cos, n_texels)[:, None]
    return np.pi * num / np.maximum(den, 1e-12)


def _lambertian(train: Lumitexels, inputs: ProcessInputs, *, rng: int, progress,
                route: BlockRoute | None = None) -> Fitted:
    if route is None:
        albedo = _albedo(train.texel, train.wi, train.reflectance, train.weight, train.n_texels)
    else:
        albedo = np.concatenate(route.map_blocks(_block_albedo, [(route.blocks, i) for i in range(len(route.blocks.ranges))]))
    model = Lambertian(np.maximum(albedo, 0.0))

    def predict(texel: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        return albedo[texel] / np.pi * np.maximum(wi[:, 2:3], 0.0)

    return Fitted(predict, lambda t: model.take(np.asarray(t)), arrays={"albedo": albedo.astype(np.float32)},
                  params={"model": "Lambertian albedo per texel (least squares of r = albedo/pi cos)"},
                  figures={"median_albedo": [round(float(v), 4) for v in np.median(albedo, axis=0)]})


# -- Lensch et al. 2003 -------------------------------------------------------------------------
#: Lensch's settings for sessions captured here, beyond the paper's (``gonio process`` applies
#: them under the lab's own options; imported sets have their own):
#: photographs hold cast shadows and inter-reflections the paper's data lacked
#: (``robust_samples``), and relief the mesh lacks, which misplaces the highlights Eq. 10 labels
#: by (``relabel_normals``) and keeps the texels that pin a sharp lobe out of its refits
#: (``refresh_confidence``); each texel's lobes predict broadened by its fitted normal's
#: uncertainty (``normal_broadening``: the hedge where the normal is not pinned, not everywhere).
#: Held-out rel. RMS over the floor, quick demo clusterings 0 / 1 / 2: 2.17 / 2.46 / 2.21x
#: before, 1.79 / 1.73 / 1.84x with the first three, 1.70 / 1.64 / 1.70x with broadening; full demo
#: 2.48 -> 1.51 -> 1.48x (docs/measurements.md, rounds floor5 and floor4). Errors under
#: multiplicative noise (``noise``: fits and labels): an HDR merge takes each pixel from the
#: bracket that exposes it well, so its noise is a roughly constant fraction of its value, and
#: the errors of resampling and of the normals grow with the signal too; quick demo 1.70 / 1.64 /
#: 1.70 -> 1.43 / 1.58 / 1.44x, full demo clusterings 0-4 1.48 / 1.37 / 1.56 / 1.40 / 1.42 ->
#: 1.30 / 1.38 / 1.40 / 1.44 / 1.41x (docs/measurements.md, "The demos' captures under
#: noise="relative"").
CAPTURED_LENSCH = {"robust_samples": True, "relabel_normals": True, "refresh_confidence": True,
                   "normal_broadening": 2.0, "noise": "relative"}


def _lensch(train: Lumitexels, inputs: ProcessInputs, *, rng: int, progress, route: BlockRoute | None = None,
            **options) -> Fitted:
    opt = SvbrdfOptions(fit_normals=True, **options)
    if route is None:
        fit = fit_svbrdf_lumitexels(train, opt, rng=rng, progress=progress)
    else:   # the same fit (to 1e-9), its per-texel steps over the stored blocks, on the executor
        fit = fit_svbrdf_blocks(route.blocks, opt, normals=train.normal, footprint_spread=train.footprint_spread_deg,
                                neighbours=None if opt.normal_broadening is None else pixel_neighbours(train),
                                rng=rng, progress=progress, map_blocks=route.map_blocks)
    return lensch_fitted(fit, opt, rng)


def lensch_fitted(fit: SvbrdfFit, opt: SvbrdfOptions, rng: int) -> Fitted:
    """A Lensch fit as the pipeline stores it: ``arrays["labels"]`` the cluster of each texel (Eq. 10;
    a material's variant clusters apart), ``arrays["materials"]`` its material
    (``fit.cluster_material[labels]``: clusters no held-out test tells apart are one material),
    the projection weights, the fitted normals (object frame), with ``normal_broadening`` each
    texel's ``lobe_variance``, and with ``interreflection_lobe`` each texel's inter-reflection
    axis and weights (with ``interreflection_diffuse`` also the diffuse term's colour per
    cluster)."""
    flags = {"too_few_samples": int(np.sum(fit.too_few_samples)), "no_highlight": int(np.sum(fit.no_highlight)),
             "mixed_footprint": int(np.sum(fit.mixed_footprint)), "material_variant": int(np.sum(fit.variant))}
    arrays = {"labels": np.asarray(fit.labels), "materials": np.asarray(fit.cluster_material[fit.labels], np.int64),
              "weights": np.asarray(fit.weights, np.float32)}
    if fit.normals is not None:
        arrays["normals"] = np.asarray(fit.normals, np.float32)
    if fit.lobe_variance is not None:   # rad^2 added to each lobe's 1/N when it predicts
        arrays["lobe_variance"] = np.asarray(fit.lobe_variance, np.float32)
    if fit.interreflection is not None:   # part of what predict() adds (not of the BRDFs)
        arrays["interreflection_axes"] = np.asarray(fit.interreflection.axes, np.float32)
        arrays["interreflection_weight"] = np.asarray(fit.interreflection.weight, np.float32)
        if fit.interreflection.diffuse is not None:   # the colour of weight[:, 1]'s diffuse term, per cluster
            arrays["interreflection_diffuse"] = np.asarray(fit.interreflection.diffuse, np.float32)
    return Fitted(fit.predict, fit.brdf, arrays=arrays,   # fitted normals applied
                  params={"n_materials": "from the data", "fit_normals": True, "rng": rng,
                          "discovery_texels": opt.discovery_texels, "robust_samples": opt.robust_samples,
                          "relabel_normals": opt.relabel_normals, "normal_broadening": opt.normal_broadening},
                  figures={"materials": fit.n_materials, "clusters": len(fit.materials),
                           "material_discovery": f"materials found on {fit.discovery_texels} of {len(fit.labels)} texels", "table_ii_rms": dict(fit.rms),
                           "table_ii_relative_rms": dict(fit.relative_rms), "flagged_texels": flags},
                  normals=None if fit.normals is None else np.asarray(fit.normals, float),
                  warnings=[h for h in fit.history if h.startswith("normal-fitting round")])


# -- Zickler et al. 2005 ------------------------------------------------------------------------
def _sharing(train: Lumitexels, inputs: ProcessInputs, *, rng: int, progress, route: BlockRoute | None = None,
             max_centers: int = 1000, fit_normals: bool = True, m_xy: float = 1.0, fit_texels: int = FIT_TEXELS,
             angular_weight: float | None = ANGULAR_WEIGHT) -> Fitted:
    if train.diffuse is None or train.specular is None:
        raise MethodSkipped("sharing: no polarized frames (the dichromatic model needs parallel and "
                            "crossed captures of each pose)")
    xy = _surface_xy(train.position)
    blocks = route.blocks if route is not None else ArrayBlocks(   # the gathered lumitexels as one block
        train.texel, train.wi, train.wo, train.reflectance, train.weight, n_texels=train.n_texels,
        block_texels=max(train.n_texels, 1), diffuse=train.diffuse, specular=train.specular)
    # the per-texel steps per block, the RBFs on at most fit_texels texels' samples
    fit = fit_spatial_blocks(blocks, xy, fit_texels=fit_texels, max_centers=max_centers, fit_normals=fit_normals,
                             m_xy=m_xy, angular_weight=angular_weight, rng=rng, progress=progress,
                             map_blocks=None if route is None else route.map_blocks)

    def per_texel(t: np.ndarray) -> BRDF:   # about the fitted normals, where there are
        t = np.asarray(t)
        return fit.brdf_at(fit.texel_xy[t], t)

    figures = {"mode": fit.mode, "samples_used": fit.n_used, "samples_dropped": fit.n_dropped,
               "centres": {k: len(f.model.centers) for k, f in fit.fits.items()},
               "rbf_texels": f"RBFs fitted on {fit.fit_texels} of {train.n_texels} texels"}
    arrays = {"xy": xy.astype(np.float32), "albedo": np.asarray(fit.albedo, np.float32)}
    normals = None
    if fit.normals is not None:   # local (mesh normal = +z) -> object frame
        normals = to_world(fit.normals.normals, tangent_frames(train.normal))
        arrays["normals"] = normals.astype(np.float32)
        figures["normals_fitted"] = int(fit.normals.fitted.sum())
    return Fitted(fit.predict, per_texel, arrays=arrays,
                  params={"surface_xy": "azimuth about the turntable axis and height, scaled to [0, 1]",
                          "max_centers": max_centers, "fit_normals": fit_normals, "m_xy": m_xy, "rng": rng,
                          "fit_texels": fit_texels, "angular_weight": angular_weight},
                  figures=figures, normals=normals)


#: bytes a sample in sharing's global step (the gathered subsample, its re-framed samples and the
#: greedy RBF fits) holds: 1 460 measured (tracemalloc, 1000 centres, 5 k -> 22 k samples); the RBF's
#: own working set, ~50 MiB at 1000 centres (its matrices and candidate distances), comes on top
_SHARING_BYTES_PER_SAMPLE = 1500


def sharing_texels_for(memory_bytes: int, n_train_views: int) -> int:
    """Sharing's RBF subsample (texels) within half of ``memory_bytes``, every texel counted with a
    sample in every training view (a bound), capped at the method's default
    (:data:`reconstruct.sharing.FIT_TEXELS`); at least 1000."""
    fit = int(memory_bytes // (2 * _SHARING_BYTES_PER_SAMPLE * max(n_train_views, 1)))
    return max(1000, min(FIT_TEXELS, fit))


def _surface_xy(position: np.ndarray) -> np.ndarray:
    """A 2-D surface parameter for the spatial RBF, in [0, 1]^2 as the paper's: the azimuth about
    the turntable axis and the height (a cylindrical map, the turntable's natural one; points
    that share both, e.g. an ear in front of the head, share a parameter)."""
    az = (np.arctan2(position[:, 1], position[:, 0]) + np.pi) / (2 * np.pi)
    z = position[:, 2]
    return np.stack([az, (z - z.min()) / max(float(np.ptp(z)), 1e-9)], axis=1)


# -- Romeiro et al. 2008 ------------------------------------------------------------------------
def _passive(train: Lumitexels, inputs: ProcessInputs, *, rng: int, progress, route: BlockRoute | None = None) -> Fitted:
    """One BRDF from the room-lit image: of the lab's sample sphere when captured
    (``inputs.passive.sample_sphere``: the BRDF is the sample's, scored by
    :mod:`capture.pipeline.passive_sample`), else of the object (outside the method's assumption
    when it has several materials). ``predict`` applies that one BRDF to any lumitexels. With a
    ``route``, its lighting matrix's blocks of pixels run on the route's executor."""
    p = inputs.passive
    if p is None:
        why = "; ".join(n.removeprefix("passive: ") for n in inputs.notes if "passive" in n) or \
            "no passive capture (add [[calibration]] kind = \"passive_sphere\": the sample sphere, lamp off, room lit)"
        raise MethodSkipped(f"passive: {why}")
    fit = passive_reflectometry(p.image, p.normals, p.mask, p.environment, view_dirs=p.view_dirs,
                                environment_weight=p.environment_weight, rng=rng, progress=progress,
                                map_blocks=None if route is None else route.map_blocks)
    brdf = fit.brdf

    def predict(texel: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        return brdf.evaluate(wi, wo) * np.maximum(wi[:, 2:3], 0.0)

    ad = fit.adequacy
    return Fitted(predict, lambda t: brdf,
                  arrays={"bivariate": np.asarray(brdf.table, np.float32), "lambertian": np.asarray(fit.lambertian)},
                  params={"grid": list(np.asarray(brdf.table).shape[:2]), "rng": rng},
                  figures={"prior": fit.prior, "residual": np.asarray(fit.residual).tolist(),
                           "effective_rank": int(ad.effective_rank), "condition": float(ad.condition),
                           "observations": int(ad.n_observations),
                           "poorly_observed": {k: float(v) for k, v in ad.poorly_observed.items()},
                           # the report's table: where the environment could not constrain the BRDF
                           "unconstrained": [{"theta_d_deg": list(b.theta_d_deg), "theta_h_deg": b.theta_h_deg,
                                              "poorly_lit_share": b.poorly_lit_share}
                                             for b in ad.unconstrained_bands()]},
                  warnings=[*dict.fromkeys([*fit.warnings, *ad.warnings]), *(
                      [] if p.sample_sphere is not None else
                      ["passive reflectometry recovers one BRDF for the whole object: on a "
                       "multi-material object it is their average"])])


METHODS: dict[str, Callable[..., Fitted]] = {"lambertian": _lambertian, "lensch": _lensch,
                                             "sharing": _sharing, "passive": _passive}
#: what ``gonio process`` runs without --methods (the reference first)
DEFAULT_METHODS = ("lambertian", "lensch", "sharing", "passive")


#: the methods whose per-block tasks run over a :class:`BlockRoute` when given one (passive fits
#: one image, not the lumitexels: only its lighting matrix's blocks of pixels run on the executor)
BLOCK_METHODS = ("lambertian", "lensch", "sharing", "passive")


def fit_method(name: str, train: Lumitexels, inputs: ProcessInputs, *, rng: int = 0,
               progress: Callable[[int, int], None] | None = None, route: BlockRoute | None = None,
               **options: Any) -> Fitted:
    """Run method ``name`` (one of :data:`METHODS`) on the training lumitexels; ``options`` are
    the method's own (``sharing``: ``max_centers``, default 1000 per RBF, the paper's "< 1000
    suffice"; ``fit_normals``, default True: normals from the diffuse samples first; ``m_xy``,
    default 1: the spatial scale on :func:`_surface_xy`'s whole-object map, where the paper's 0.3
    for a face's [0, 1]^2 blends the materials' lobes: held out 0.42 / 0.51 at 0.3, 0.39 / 0.46
    at 0.6, 0.37 / 0.47 at 1, 0.39 at 2 on the quick demo's bumpy sphere / four-material bunny;
    ``fit_texels``, default :data:`reconstruct.sharing.FIT_TEXELS`: the RBFs' random subsample of
    texels; ``angular_weight``, default :data:`reconstruct.sharing.ANGULAR_WEIGHT`: (u, v) in
    polar form, None: as the paper).
    With a ``route``, the :data:`BLOCK_METHODS` read their samples block by block from it and run
    their per-block tasks on its executor (the same figures to 1e-9; passive only runs its
    lighting matrix's blocks of pixels there); the others fit ``train``.

    Raises
    ------
    MethodSkipped
        The session's captures do not allow it (says why).
    ValueError
        ``name`` is not a method.
    """
    if name not in METHODS:
        raise ValueError(f"methods: unknown {name!r}; known: {', '.join(METHODS)}")
    if route is not None and name in BLOCK_METHODS:
        options = {**options, "route": route}
    return METHODS[name](train, inputs, rng=rng, progress=progress, **options)
