"""``gonio process`` on an imported multi-light set (:mod:`capture.importers`): no rig, no mesh.

An imported DiLiGenT-layout session gives what calibration would otherwise measure: the light
directions and intensities and an orthographic camera. So the calibration stages are skipped
(each is listed with the reason), and the object's normals come from the images themselves:
robust least-squares photometric stereo on the training lights
(:func:`reconstruct.photometric_stereo.photometric_stereo`, ``robust=True``: the darkest and
brightest lights per pixel dropped, then the lights the fit shades or far exceeds). Every mask
pixel (or a random ``max_texels`` of them) becomes a texel
(:func:`reconstruct.directional_lumitexels.directional_lumitexels`); the held-out lights score
every method as on a captured session. Ground-truth normals, where the set has them, are used
only to score: least squares, the robust variant and each method's fitted normals.

Methods: ``lambertian`` (the reference) and ``lensch`` (:data:`LENSCH_OPTIONS`: robust sample
selection for its normal fitting, two lobes, the peak test with an inter-reflection lobe) run; ``sharing`` needs polarization-separated
diffuse and specular images, and
``passive`` a room-lit image with a mirror probe, which such a set does not have: both are
reported skipped with that reason.

The report is the captured sessions' (:func:`capture.pipeline.report_html.write_html_report`),
given :class:`ImportedFacts`: what was imported and the normals' error maps.
"""
from __future__ import annotations

import io
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from reconstruct.directional_lumitexels import directional_lumitexels
from reconstruct.lumitexels import Lumitexels
from reconstruct.metrics import relative_rms, trimmed_relative_rms
from reconstruct.photometric_stereo import angular_error_deg, photometric_stereo

from ..importers import MultiLightSet, read_imported_session
from ..outputs import session_file, write_atomically
from ..store import Store
from .methods import MethodSkipped, fit_method
from .process import ProcessInputs
from .process_report import MethodOutcome, ProcessReport
from .progress import ProgressSink, counter
from .report_html import write_html_report

__all__ = ["ImportedInputs", "ImportedFacts", "imported_facts", "imported_inputs", "process_imported_session", "is_imported",
           "relighting_pictures", "SKIPPED_STAGES", "LENSCH_OPTIONS"]

#: The calibration stages a captured session runs, and why an imported set skips each.
SKIPPED_STAGES = {
    "intrinsics": "the camera is given: orthographic, viewing along the optical axis",
    "turntable": "no turntable: one view of the object",
    "lights": "the light directions and intensities are given with the set",
    "gray_card": "no gray card: reflectance is relative (images divided by the given intensities)",
    "probe": "no mirror probe: no environment map (passive reflectometry cannot run)",
    "mesh": "no mesh: normals from robust least-squares photometric stereo on the training lights",
}
#: Lensch options on real photographs: robust sample selection against cast shadows and
#: inter-reflections before each normal-fitting round (within 1.5 robust sigma), each texel's
#: brightest 10 % of samples left out of it (ST14's low-intensity part), Tukey's loss in the
#: normal fit (cut off at 2 robust sigmas of each texel's residuals), two lobes per material,
#: each material's lobes alone in its projection basis (a texel's own highlight strength), the
#: peak test (a texel whose brightest sample is over 1.5x its fitted model there is held near
#: that sample's half vector) with an inter-reflection lobe about the normal its free fit found
#: (the object's image of the light in itself), each held texel kept out of the BRDF refits and
#: sent back to that free normal where it fits its samples clearly better under Tukey's loss
#: (3 robust sigmas; the per-texel undo; a round as a whole undone only past 1.5x its error),
#: in the last round each texel's samples below 0.1x its median left out of the normal fit (cast
#: shadows), after the normal fit a diffuse term about each held texel's input normal (the light
#: the object sends it, broadly; round lensch11), and the Lafortune fits stopped where
#: they crawl (20 iterations, 1e-4) (see benchmarks/diligent.py --ablation and docs/diligent.md
#: for what each buys).
LENSCH_OPTIONS = {"robust_samples": True, "n_lobes": 2, "robust_spread": 1.5, "brightest_dropped": 0.1,
                  "tukey_cutoff": 2.0, "lobes_alone": True, "peak_ratio": 1.5, "peak_compare": False,
                  "interreflection_lobe": True, "texel_undo": True, "undo_tukey": 3.0, "undo_margin": 1.25,
                  "undo_ratio": 1.5, "lm_stall": (20, 1e-4), "shadow_ratio": 0.1,
                  "interreflection_diffuse": True}


def is_imported(store: Store, session: str) -> bool:
    """The session was written by an importer (its plan holds ``imported``)."""
    plan = store.session(session).plan
    return isinstance(plan, dict) and "imported" in plan


class ImportedInputs:
    """Training and held-out lumitexels of an imported set, with the normals they were built on.

    ``train`` / ``held`` :class:`Lumitexels` (texel i = pixel ``pixels[i]``, ``view`` the light
    index); ``normals_ls`` and ``normals_robust`` (T, 3) least-squares and robust photometric-
    stereo normals of the texels (OpenCV camera frame; the lumitexels' local frames are built on
    ``frames_from``: the robust ones by default); ``ls`` / ``robust`` the two full
    :class:`~reconstruct.photometric_stereo.PhotometricStereoResult`; ``truth`` (T, 3) or None.
    Observations with a clipped channel get weight 0.
    """

    def __init__(self, data: MultiLightSet, *, max_texels: int | None = None, rng: int = 0,
                 frames_from: str = "robust"):
        train = ~data.held_out
        radiance = data.radiance()
        valid = np.all(data.images < data.full_scale, axis=-1)   # clipped channels are unusable
        ls = photometric_stereo(radiance[train], data.light_directions[train], data.mask)
        rb = photometric_stereo(radiance[train], data.light_directions[train], data.mask, robust=True)
        mask = data.mask & rb.mask
        if max_texels is not None and mask.sum() > max_texels:
            rows, cols = np.nonzero(mask)
            pick = np.random.default_rng(rng).choice(len(rows), max_texels, replace=False)
            mask = np.zeros_like(mask)
            mask[rows[pick], cols[pick]] = True
        self.mask = mask
        self.pixels = np.stack(np.nonzero(mask), axis=1)
        self.normals_ls = ls.normals[mask].astype(np.float64)
        self.normals_robust = rb.normals[mask].astype(np.float64)
        self.truth = None if data.normals_gt is None else data.normals_gt[mask]
        if frames_from not in ("robust", "least_squares"):
            raise ValueError(f"frames_from must be 'robust' or 'least_squares', got {frames_from!r}")
        start = rb.normals if frames_from == "robust" else ls.normals
        self.ls, self.robust = ls, rb
        self.train = directional_lumitexels(radiance[train], data.light_directions[train],
                                            data.view_direction, start, mask, valid=valid[train])
        held = directional_lumitexels(radiance[~train], data.light_directions[~train],
                                      data.view_direction, start, mask, valid=valid[~train])
        held.view = np.flatnonzero(~train)[held.view]
        self.train.view = np.flatnonzero(train)[self.train.view]
        self.held = held
        self.data = data

    def lambertian_relighting(self, ps=None) -> float:
        """Held-out relative RMS of the Lambertian reference, rho_c max(0, n . l), with the
        normals and per-channel albedo of a photometric-stereo result (the least-squares one,
        ``ls``, by default), on the held-out samples of the texels: the relighting every
        method must beat."""
        ps = self.ls if ps is None else ps
        held = self.held
        rows, cols = self.pixels[held.texel, 0], self.pixels[held.texel, 1]
        n = ps.normals[rows, cols].astype(np.float64)
        shade = np.maximum(np.sum(n * self.data.light_directions[held.view], axis=1), 0.0)
        pred = ps.albedo[rows, cols].astype(np.float64) * shade[:, None]
        use = held.weight > 0
        return relative_rms(pred[use], held.reflectance[use])

    def normal_errors(self, normals: np.ndarray) -> float | None:
        """Mean angular error (deg) of (T, 3) normals against the truth; None without truth."""
        if self.truth is None:
            return None
        return float(angular_error_deg(normals, self.truth).mean())


@dataclass(frozen=True)
class ImportedFacts:
    """What the report of an imported session shows beyond :class:`capture.pipeline.process_report.ProcessReport`.

    ``provenance`` the plan's ``imported`` record without the per-file hashes (``files_hashed``
    counts them); ``images`` the image count, ``image_size_px`` (width, height), ``mask_pixels``;
    ``light_directions`` (K, 3) unit vectors towards the lights, OpenCV camera frame, and
    ``held_out`` (K,) bool; ``normal_errors`` name -> (H, W) angle (deg) between recovered and
    true normals, NaN where not scored (empty without ground truth); ``fitted`` (H, W) bool the
    pixels the methods fitted (the texels) and ``texels_note`` the same in words."""

    provenance: dict[str, Any]
    files_hashed: int
    images: int
    image_size_px: tuple[int, int]
    mask_pixels: int
    light_directions: np.ndarray
    held_out: np.ndarray
    normal_errors: dict[str, np.ndarray]
    fitted: np.ndarray
    texels_note: str


def _error_map(normals: np.ndarray, truth: np.ndarray, where: np.ndarray) -> np.ndarray:
    """(H, W) angle (deg) between (H, W, 3) normals and the truth where ``where``, NaN elsewhere."""
    out = np.full(where.shape, np.nan)
    out[where] = angular_error_deg(normals[where], truth[where])
    return out


def imported_facts(store: Store, session: str, inp: ImportedInputs, methods) -> ImportedFacts:
    """:class:`ImportedFacts` of a processed imported session: the normals' error maps of least
    squares, the robust variant and each stored method that fits normals (read from its
    ``model.npz``: ``normals`` at ``pixels``)."""
    data = inp.data
    prov = dict(store.session(session).plan["imported"])
    hashed = len(prov.pop("sha256", {}))
    maps: dict[str, np.ndarray] = {}
    if data.normals_gt is not None:
        scored = data.mask & inp.robust.mask   # the pixels texels are drawn from
        maps["least squares"] = _error_map(inp.ls.normals, data.normals_gt, scored)
        maps["robust least squares"] = _error_map(inp.robust.normals, data.normals_gt, scored)
        info = store.session(session)
        stored = {r.id: r for r in store.results(info.id, "reconstruction")}
        for m in methods:
            r = stored.get(m.result_id)
            if r is None or "model.npz" not in r.artifacts:
                continue
            with np.load(io.BytesIO(store.read_object(r.artifacts["model.npz"]))) as z:
                if "normals" not in z.files or "pixels" not in z.files:
                    continue
                normals, px = z["normals"], z["pixels"]
            grid = np.zeros(data.mask.shape + (3,))
            grid[px[:, 0], px[:, 1]] = normals
            fitted = np.zeros(data.mask.shape, bool)
            fitted[px[:, 0], px[:, 1]] = True
            maps[f"{m.method} (fitted)"] = _error_map(grid, data.normals_gt, fitted)
    n = int(data.mask.sum())
    return ImportedFacts(prov, hashed, len(data.filenames), tuple(int(v) for v in data.mask.shape[::-1]), n,
                         data.light_directions, data.held_out, maps, inp.mask,
                         f"{inp.train.n_texels} of the {n} mask pixels" if inp.train.n_texels < n
                         else "every mask pixel")


def imported_inputs(store: Store, session: str, **kw) -> ImportedInputs:
    """:class:`ImportedInputs` of an imported session (``max_texels``, ``rng``)."""
    return ImportedInputs(read_imported_session(store, session), **kw)


def relighting_pictures(inp: ImportedInputs, predicted: np.ndarray) -> dict[str, np.ndarray]:
    """The report's held-out relighting pictures of one method (its ``report.npz``).

    For the held-out light nearest the view axis and the one farthest from it: the photograph
    (``heldout_captured``, ``_2`` for the second; (H, W, 3) radiance per unit light intensity)
    and the method's ``predicted`` reflectance of ``inp.held``'s samples drawn at exactly the
    pixels it fitted (``heldout_predicted``; NaN elsewhere and where the light is below a
    texel's horizon: nothing is filled in). ``heldout_lights`` (n, 2): each pair's light index
    and its angle to the view axis (deg)."""
    held, data = inp.held, inp.data
    lights = np.unique(held.view)
    if len(lights) == 0:
        return {}
    angle = np.degrees(np.arccos(np.clip(data.light_directions[lights] @ data.view_direction, -1, 1)))
    chosen = lights[[int(np.argmin(angle)), int(np.argmax(angle))]] if len(lights) > 1 else lights
    H, W = data.mask.shape
    out: dict[str, np.ndarray] = {}
    for suffix, k in zip(("", "_2"), chosen):
        on = held.view == k
        col, row = held.pixel[held.texel[on]].astype(int).T
        pred = np.full((H, W, 3), np.nan, np.float32)
        pred[row, col] = predicted[on]
        out["heldout_captured" + suffix] = data.radiance([k])[0]
        out["heldout_predicted" + suffix] = pred
    out["heldout_lights"] = np.array([[k, a] for k, a in zip(chosen, angle[np.searchsorted(lights, chosen)])])
    return out


def _score(lt: Lumitexels, predicted: np.ndarray) -> dict[str, float]:
    use = lt.weight > 0
    return {"held_out_rel_rms": relative_rms(predicted[use], lt.reflectance[use]),
            "held_out_rel_rms_trimmed": trimmed_relative_rms(predicted[use], lt.reflectance[use])}


def _npz(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def process_imported_session(store: Store, session: str, *, methods: Sequence[str],
                             force: bool = False, rng: int = 0, max_texels: int | None = 5000,
                             progress: ProgressSink | None = None,
                             report_path: str | Path | None = None):
    """Run ``methods`` on an imported session and write its report (``report_path``, default
    ``<session>-report.html`` beside the store, with its ``.json`` summary); returns a
    :class:`capture.pipeline.process_report.ProcessReport`.

    ``max_texels``: texels (mask pixels drawn at random with ``rng``) the methods fit; None: all.
    """
    info = store.session(session)
    rep = ProcessReport(session)
    rep.calibration = [{"stage": s, "status": "skipped", "reason": why, "figures": {}}
                       for s, why in SKIPPED_STAGES.items()]
    rep.calibration += [{"stage": r.kind, "status": "stored", "reason": f"result {r.id} "
                         "(given with the set)", "figures": {}}
                        for r in store.results(info.id, "calibration")]
    t0 = time.perf_counter()
    inp = imported_inputs(store, session, max_texels=max_texels, rng=rng)
    rep.timings["inputs"] = round(time.perf_counter() - t0, 3)
    frames = [f.id for f in store.frames(info.id)]
    rep.inputs = {"texels": inp.train.n_texels, "training_samples": inp.train.n_samples,
                  "held_out_samples": inp.held.n_samples,
                  "training_lights": int((~inp.data.held_out).sum()),
                  "held_out_lights": int(inp.data.held_out.sum()), "absolute_units": False,
                  "normals_from": "robust least-squares photometric stereo (training lights)"}
    if inp.truth is not None:
        rep.inputs["normal_error_least_squares_deg"] = inp.normal_errors(inp.normals_ls)
        rep.inputs["normal_error_robust_deg"] = inp.normal_errors(inp.normals_robust)
    stub = ProcessInputs(calibration=None, views=[], held_out=[], view_steps=[], held_out_steps=[],
                         view_frames=frames, notes=[
                             "passive: " + SKIPPED_STAGES["probe"],
                             "sharing: no polarization-separated images in an imported set"])
    stored = {r.kind: r for r in store.results(info.id, "reconstruction")}
    for name in methods:
        if name in stored and not force:
            rep.methods.append(MethodOutcome(name, "done", f"stored before (result {stored[name].id});"
                                             " --force re-runs it",
                                             figures=stored[name].result.get("figures", {}),
                                             result_id=stored[name].id))
            continue
        started = time.perf_counter()
        try:
            fit = fit_method(name, inp.train, stub, rng=rng, progress=counter(progress, name),
                             **(LENSCH_OPTIONS if name == "lensch" else {}))
        except MethodSkipped as exc:
            rep.methods.append(MethodOutcome(name, "skipped", str(exc)))
            continue
        except (ValueError, np.linalg.LinAlgError) as exc:
            rep.methods.append(MethodOutcome(name, "failed", f"{type(exc).__name__}: {exc}"))
            continue
        figures: dict[str, Any] = dict(fit.figures)
        predicted = fit.predict(inp.held)
        figures.update(_score(inp.held, predicted))
        if fit.normals is not None and inp.truth is not None:
            figures["normal_error_deg"] = inp.normal_errors(fit.normals)
        seconds = round(time.perf_counter() - started, 3)
        rep.timings[name] = seconds
        arrays = {**fit.arrays, "pixels": inp.pixels.astype(np.int32)}
        if fit.normals is not None:   # full precision: the report's error map restates normal_error_deg
            arrays["normals"] = np.asarray(fit.normals, np.float64)
        rid = store.add_reconstruction(info.id, name, result={
            "figures": figures, "warnings": fit.warnings, "inputs_summary": rep.inputs},
            params={**fit.params, **(LENSCH_OPTIONS if name == "lensch" else {}),
                    "max_texels": max_texels}, input_frames=frames,
            artifacts={"model.npz": _npz(arrays), "report.npz": _npz(relighting_pictures(inp, predicted))})
        rep.methods.append(MethodOutcome(name, "ok", "", figures, rid, seconds, fit.warnings))
    started = time.perf_counter()
    facts = imported_facts(store, session, inp, rep.methods)
    path = Path(report_path) if report_path else session_file(Path(store.root).resolve().parent, session,
                                                               info.id, "-report.html")
    rep.report_path = write_html_report(store, session, rep, path=path, imported=facts)
    rep.timings["report"] = round(time.perf_counter() - started, 3)   # in the .json, as a captured session's
    write_atomically(rep.report_path.with_suffix(".json"), json.dumps(rep.summary(), indent=1, default=str))
    return rep
