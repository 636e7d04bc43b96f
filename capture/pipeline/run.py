"""``gonio process``: a captured session -> calibration -> every method -> stored results -> report.

:func:`process_session` runs, in order: the calibration (when none is stored, or ``force``), the
reconstruction inputs (:mod:`capture.pipeline.process`), the lumitexels over the object's mesh with the
held-out samples split off, then each requested method (:mod:`capture.pipeline.methods`). Every method's
model is scored on the held-out lights (relative RMS of predicted against captured reflectance)
and stored with :meth:`capture.store.Store.add_reconstruction`: its figures and parameters, the
ids of the frames and calibrations it used, the code version, and its arrays (``model.npz``) and
report pictures (``report.npz``) as content-addressed objects. A method already stored for the
session is skipped unless ``force``.

With a :class:`capture.pipeline.demo_lab.DemoTruth` (the simulated lab's ground truth) the figures gain
truth columns: calibration errors (focal length, lights, lamp intensity), the inputs' own error
(measured reflectance against the true ``f_r cos``: what calibration and noise leave) and each
model's error against the truth on the held-out samples, and the :class:`Floor`: the true model
scored on the held-out captures like every method, with each method's ratio to it. Passive
reflectometry on the lab's sample sphere is scored on the sphere instead
(:mod:`capture.pipeline.passive_sample`): the object's held-out lights see another surface.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import trimesh

from reconstruct.frames import tangent_frames, to_local, to_world
from reconstruct.lumitexels import Lumitexels
from reconstruct.metrics import relative_rms, trimmed_relative_rms
from rig import LightTarget

from ..export.appearance import EXPORTED_METHODS, appearance_npz
from ..lab import GrayCardPose, LabTargets, SessionLab
from ..lab_resolver import resolve_lab
from .calibration_record import stored_calibration
from .calibrate import NothingToCalibrate, calibrate_session
from .imported import is_imported, process_imported_session
from .mesh_checks import check_mesh_placement
from .methods import (BLOCK_METHODS, CAPTURED_LENSCH, DEFAULT_METHODS, METHODS, BlockRoute, Fitted, MethodSkipped,
                      fit_method, sharing_texels_for)
from .passive_sample import SampleTruth, score_sample_sphere
from .pictures import method_pictures
from .cluster import ClusterOptions, Executor
from .block_inputs import inputs_over_blocks
from .block_results import BlockResults
from .heap import release_freed_memory
from .block_scoring import score_blocks
from .lumitexel_arrays import (LumitexelArrays, block_texels_for, default_memory_limit, discovery_texels_for,
                               method_texels_for, stream_lumitexels)
from .stored_blocks import StoredBlocks
from .progress import Progress, ProgressSink, counter
from .process import (MissingCalibration, PassiveInput, ProcessInputs, SessionCalibration, ViewPlan, passive_input,
                      plan_inputs, read_calibration, sample_sphere_of, select_samples, session_images, view_plan)
from .process_report import Floor, MethodOutcome, ProcessReport
from .report_html import write_html_report
from ..outputs import session_file, write_atomically
from ..store import Store, crash

__all__ = ["Floor", "MethodOutcome", "ProcessReport", "process_session"]

#: why passive reflectometry does not fit a multi-material object (Romeiro et al. 2008 Sec. 3)
PASSIVE_ASSUMPTION = "Romeiro et al. assume one homogeneous curved surface"


class _Clock:
    """Times each stage into the report and announces it to the progress sink."""

    def __init__(self, report: ProcessReport, progress: ProgressSink | None) -> None:
        self.report, self.progress = report, progress

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        crash.point(f"stage {name}")   # the crash test kills here (GONIO_CRASH_AFTER)
        release_freed_memory()   # each stage starts from what is live, not the last one's high-water mark
        if self.progress is not None:
            self.progress(Progress(name, 0, 1))
        started = time.perf_counter()
        try:
            yield
        finally:
            self.report.timings[name] = round(self.report.timings.get(name, 0.0)
                                              + time.perf_counter() - started, 3)


def process_session(store: Store, session: str, *, methods: Sequence[str] = DEFAULT_METHODS,
                    mesh: trimesh.Trimesh | None = None, targets: LabTargets | None = None,
                    gray_card: GrayCardPose | None = None, probe_reflectance: float | None = None, truth=None,
                    force: bool = False, rng: int = 0, lab: SessionLab | None = None,
                    method_options: dict[str, dict[str, Any]] | None = None,
                    progress: ProgressSink | None = None,
                    report_path: str | Path | None = None, cluster: ClusterOptions = ClusterOptions(),
                    memory_limit: int | None = None,
                    say: Callable[[str], None] = lambda text: None) -> ProcessReport:
    """Calibrate (if needed), build the inputs, run and store each method, write the report.

    ``lab`` is the session's :class:`capture.lab.SessionLab` (:func:`capture.lab_resolver.resolve_lab`:
    mesh, targets, gray-card pose, probe reflectance, truth, method options); without it the lab
    is resolved here from the parts given (``mesh`` ... ``method_options``), a session recorded
    in the built-in simulated lab taking every part not given from the lab itself.

    Parameters
    ----------
    store, session
        The captured session.
    methods : sequence of str
        Names from :data:`capture.pipeline.methods.METHODS`; each is run if the captures allow it.
    mesh : trimesh.Trimesh
        The object's mesh in the object frame (the lab frame at turntable reading 0), mm (needed
        unless the session was recorded in the built-in simulated lab).
    targets : LabTargets, optional
        The lab's calibration targets (for a calibration run here).
    gray_card : GrayCardPose, optional
        The card's pose, for the lamp's absolute intensity.
    probe_reflectance : float, optional
        The mirror probe's reflectance (divided out of the environment map; default 1).
    truth : capture.pipeline.demo_lab.DemoTruth, optional
        Ground truth of a simulated session (adds truth columns).
    force : bool
        Re-run the calibration and every method even when stored.
    rng : int
        Seed handed to the methods.
    method_options : dict of str -> dict, optional
        Per method, its own options (:func:`capture.pipeline.methods.fit_method`; they replace the built-in
        lab's for that method).
    progress : callable(Progress), optional
        Each stage as it starts and its progress (:mod:`capture.pipeline.progress`).
    report_path : path, optional
        Where to write the HTML report (default: ``<session>-report.html`` beside the store).
    cluster : ClusterOptions
        Where the lumitexels' per-view tasks run (default: this process; :mod:`capture.pipeline.cluster`).
    memory_limit : int, optional
        Bytes the per-view tasks may hold together; sets the texel block size
        (:func:`capture.pipeline.lumitexel_arrays.block_texels_for`; default: half the machine's memory).
        Where the gathered lumitexels would exceed it (:meth:`LumitexelArrays.gathered_bytes`)
        they are not gathered: the inputs come from one pass over blocks
        (:mod:`capture.pipeline.block_inputs`), Lambertian, Lensch and sharing run over blocks
        here too, and the export is fitted on a stated subsample of texels.
    say : callable(str), optional
        One-line news (the Dask dashboard's address when a cluster is used).
    lab : SessionLab, optional
        The resolved lab (then none of its parts may be given).

    Raises
    ------
    ValueError
        An unknown method name, no mesh, or both ``lab`` and its parts.
    capture.process.ProcessError
        The session cannot give inputs (no measurement steps, lights not calibrated ...).
    capture.store.SessionBusy
        Another process is writing (capturing or processing) the session.
    capture.store.ObjectDamaged
        A frame or stored artifact is missing or altered (the message names its step).
    capture.store.StoreFull, OSError (ENOSPC)
        The disk filled up; what was stored so far is kept and a re-run resumes.
    """
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"methods: unknown {', '.join(unknown)}; known: {', '.join(METHODS)}")
    info = store.session(session)
    if is_imported(store, session):  # no rig, no mesh: its own path (calibration given)
        with store.writer(session):
            return process_imported_session(store, session, methods=methods, force=force, rng=rng,
                                            progress=progress, report_path=report_path)
    if lab is None:
        lab = resolve_lab(store, session, mesh=mesh, targets=targets, gray_card=gray_card,
                          probe_reflectance=probe_reflectance, truth=truth, method_options=method_options)
    elif any(v is not None for v in (mesh, targets, gray_card, probe_reflectance, truth, method_options)):
        raise ValueError("give the session's lab (lab=) or its parts (mesh=, targets= ...), not both")
    mesh, truth, method_options = lab.require_mesh(), lab.truth, lab.method_options
    # one process per session: a second `gonio process` (or a capture) gets SessionBusy instead
    # of failing mid-way or storing every method twice
    with store.writer(session):
        rep = ProcessReport(session)
        clock = _Clock(rep, progress)
        with clock.stage("calibration"):
            rep.calibration = _calibration(store, session, lab.targets, force, progress)
        if rep.calibration and rep.calibration[-1]["status"] == "skipped" and rep.calibration[-1]["stage"] == "calibration":
            # nothing to calibrate: say what the session lacks, not "run gonio calibrate"
            raise MissingCalibration(f"the session cannot be calibrated: {rep.calibration[-1]['reason']}")
        cal = read_calibration(store, session, gray_card=lab.gray_card, probe_reflectance=lab.probe_reflectance)
        check_mesh_placement(mesh, cal.camera, "the simulated lab's mesh" if lab.built_in else "the mesh")
        if truth is not None:
            rep.calibration_truth = calibration_against_truth(store, session, cal, truth)
        # a method stored from another calibration (one since redone) is stale: fitted again
        stored = {r.kind: r for r in store.results(info.id, "reconstruction")
                  if r.result.get("inputs", {}).get("calibration_ids") == cal.ids}
        todo = [m for m in methods if force or m not in stored]
        outcomes = {m: MethodOutcome(m, "done", f"stored before (result {stored[m].id}); --force re-runs it",
                                     figures=stored[m].result.get("figures", {}), result_id=stored[m].id,
                                     warnings=stored[m].result.get("warnings", []),
                                     outside_assumption=stored[m].result.get("outside_assumption", ""))
                    for m in methods if m not in todo}
        if outcomes:
            first = stored[next(iter(outcomes))].result
            rep.inputs = first.get("inputs_summary", {})
            rep.floor = Floor(**first["floor"]) if first.get("floor") else None
        # the executor serves the lumitexels' per-view tasks and the methods' per-block tasks
        with contextlib.ExitStack() as running:
            if todo:
                with clock.stage("inputs"):
                    images = session_images(store, session)
                    plan = view_plan(images, session, cal, mesh=mesh, sample_sphere=sample_sphere_of(lab.targets))
                with clock.stage("lumitexels"):
                    executor = running.enter_context(Executor(cluster, store_root=store.root, say=say))
                    limit = default_memory_limit() if memory_limit is None else memory_limit
                    block = block_texels_for(limit, n_views=len(plan.poses), pixels=cal.camera.width * cal.camera.height,
                                             workers=1 if cluster.in_process else max(cluster.workers, 1))
                    arrays = stream_lumitexels(images, session, cal, plan, mesh, executor, block_texels=block,
                                               progress=counter(progress, "lumitexels"))
                    # on a cluster the block methods' per-texel steps run there, over the stored blocks
                    method_block = method_texels_for(limit, arrays.n_train)
                    refused = None if arrays.gathered_bytes() <= limit else limit
                    if refused is None:
                        train, held = arrays.gather()
                        n_samples = (train.n_samples, held.n_samples)
                        blocks = None if cluster.in_process else StoredBlocks(arrays, method_block)
                    else:   # gathering would exceed the limit: one pass over blocks, every block method over them
                        over = inputs_over_blocks(arrays, max_texels=method_block, truth_of=None if truth is None
                                                  else functools.partial(_truth_of, truth))
                        train, held = over.train, over.held   # every texel, one view's samples each
                        n_samples = (over.n_training_samples, over.n_held_samples)
                        blocks = StoredBlocks(arrays, method_block)
                with clock.stage("inputs"):
                    # the held-out view for its picture alone; the passive input when passive runs
                    inputs = plan_inputs(images, plan, cal, mesh, images_of=[int(held.view.min())] if held.n_samples else [],
                                         passive=False, picture_only=True)
                rep.inputs = {"views": len(inputs.views), "held_out_views": len(inputs.held_out),
                              "polarization_separated": inputs.separated, "texels": train.n_texels,
                              "training_samples": n_samples[0], "held_out_samples": n_samples[1],
                              "light_source": cal.light_source, "absolute_units": cal.absolute,
                              "passive_capture": plan.passive is not None,
                              "passive_on": _passive_subject(plan), "notes": inputs.notes,
                              "lumitexel_arrays": {"path": str(arrays.path.resolve().relative_to(Path(store.root).resolve())),
                                                   "digest": arrays.digest, "block_texels": arrays.block_texels,
                                                   "reused_views": arrays.reused_views}}
                if refused is None:
                    truth_r = _truth_reflectance(truth, train, held) if truth is not None else None
                    scored_truth = truth_r is not None
                    if truth_r is not None:
                        scored = (held, truth_r[1]) if held.n_samples else (train, truth_r[0])
                        rep.inputs["measured_vs_truth_rel_rms"] = relative_rms(scored[0].reflectance, scored[1])
                        rep.inputs["measured_vs_truth_median_ratio"] = float(np.median(
                            scored[0].reflectance.sum(axis=1) / np.maximum(scored[1].sum(axis=1), 1e-12)))
                        if held.n_samples:
                            rep.floor = Floor(relative_rms(truth_r[1], held.reflectance),
                                              trimmed_relative_rms(truth_r[1], held.reflectance))
                else:
                    rep.inputs["over_blocks"] = (
                        f"the gathered lumitexels ({arrays.gathered_bytes() / 2**20:.0f} MiB at most) exceed --memory-limit "
                        f"{limit / 2**20:.0f} MiB: scoring, Lambertian, Lensch and sharing over blocks of {method_block} texels "
                        f"(Lensch's materials and sharing's RBFs fitted on a subsample), the pictures from one view's "
                        f"samples, the export fitted on a subsample of texels")
                    scored_truth = over.truth is not None
                    if over.truth is not None:
                        rep.inputs["measured_vs_truth_rel_rms"] = over.truth.measured_vs_truth_rel_rms
                        rep.inputs["measured_vs_truth_median_ratio"] = over.truth.measured_vs_truth_median_ratio
                        rep.floor = over.truth.floor
                on_object = plan.passive is None or plan.sample_sphere is None
                make_passive = functools.partial(passive_input, images, plan, cal, mesh)
                assumption = {"passive": _passive_assumption(truth, train)} if truth is not None and on_object else {}
                for name in todo:
                    started = time.perf_counter()
                    options = _options(name, method_options, limit, arrays)
                    # the block methods' per-block results stored as each block finishes: a re-run resumes
                    stored_blocks = None if blocks is None or name not in BLOCK_METHODS else \
                        BlockResults(blocks, {"method": name, "options": options, "rng": rng})
                    with clock.stage(name):
                        outcomes[name] = _run_method(store, info.id, name, arrays, train, held, inputs, make_passive,
                                                     truth, scored_truth, rng, rep.inputs, counter(progress, name),
                                                     options, rep.floor, assumption.get(name, ""), executor.map,
                                                     stored_blocks, method_block, refused)
                    if stored_blocks is not None:
                        # a finished run's results are all it reads again: earlier options' go
                        pruned = stored_blocks.prune() if outcomes[name].status == "ok" else 0
                        say(f"{name}: {stored_blocks.computed} block tasks computed, {stored_blocks.reused} read back "
                            f"from {stored_blocks.group.path}" + (f", {pruned} stale ones deleted" if pruned else ""))
                    outcomes[name].seconds = round(time.perf_counter() - started, 3)
        rep.methods = [outcomes[m] for m in methods]
        if rep.floor is not None:
            for m in rep.methods:
                m.floor_ratio = _ratio(m.figures.get("held_out_rel_rms"), rep.floor.held_out_rel_rms)
                m.floor_ratio_trimmed = _ratio(m.figures.get("held_out_rel_rms_trimmed"),
                                               rep.floor.held_out_rel_rms_trimmed)
        with clock.stage("report"):
            rep.report_path = write_html_report(store, session, rep, truth=truth, path=report_path or session_file(
                Path(store.root).resolve().parent, session, info.id, "-report.html"))
        write_atomically(rep.report_path.with_suffix(".json"), json.dumps(rep.summary(), indent=1, default=_jsonable))
        return rep


def _ratio(score: float | None, floor: float) -> float | None:
    return None if score is None or not floor > 0 else float(score) / floor


def _passive_subject(plan: ViewPlan) -> str:
    """What passive reflectometry's image shows ("" when there is none)."""
    if plan.passive is None:
        return ""
    return "the object" if plan.sample_sphere is None else "the sample sphere"


def _passive_assumption(truth, train: Lumitexels) -> str:
    """Why passive reflectometry's one-material assumption fails on the captured object ("" when
    its texels are one true material)."""
    try:
        ids, materials = truth.materials(train.position)
    except ValueError:
        return ""
    n = len(np.unique(ids))
    return "" if n < 2 else (f"the object has {n} materials; {PASSIVE_ASSUMPTION}, so its one BRDF is "
                             "their blend and its figures do not measure the method")


def _jsonable(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return str(obj)


def _calibration(store: Store, session: str, targets, force: bool,
                 progress: ProgressSink | None) -> list[dict[str, Any]]:
    """Reuse the stored calibration when it is complete and matches the session's frames
    (:mod:`capture.pipeline.calibration_record`), else run it again (saying why)."""
    info = store.session(session)
    state = stored_calibration(store, info.id)
    if state.complete and not force:
        return [{"stage": s.stage, "status": "stored" if s.calibration_id else s.status,
                 "reason": f"result {s.calibration_id}" if s.calibration_id else s.reason,
                 "figures": {}} for s in state.stages]
    redone = [] if force or state.why == "no calibration is stored" else [
        {"stage": "calibration", "status": "redone", "reason": state.why, "figures": {}}]
    try:
        report = calibrate_session(store, session, targets=targets, measurement_hdr=False, progress=progress)
    except NothingToCalibrate as exc:
        return [{"stage": "calibration", "status": "skipped", "reason": str(exc), "figures": {}}]
    return redone + [{"stage": s.stage, "status": s.status, "reason": s.reason, "figures": s.figures,
                      "seconds": s.seconds} for s in report.stages]


# -- one method ---------------------------------------------------------------------------------
def _options(name: str, method_options, memory_limit: int, arrays: LumitexelArrays) -> dict[str, Any]:
    """The method's options for this lab, and for Lensch the settings for captured sessions
    (:data:`~capture.pipeline.methods.CAPTURED_LENSCH`) and a material-discovery subsample, for
    sharing an RBF subsample, the memory limit holds (unless the lab sets them)."""
    options = dict((method_options or {}).get(name, {}))
    if name == "lensch":
        options = {**CAPTURED_LENSCH, **options}
        options.setdefault("discovery_texels", discovery_texels_for(memory_limit, arrays.n_train))
    if name == "sharing":
        options.setdefault("fit_texels", sharing_texels_for(memory_limit, arrays.n_train))
    return options


def _run_method(store: Store, session_id: int, name: str, arrays: LumitexelArrays, train: Lumitexels,
                held: Lumitexels, inputs: ProcessInputs, make_passive: Callable[[], PassiveInput | None], truth,
                scored_truth: bool, rng: int, summary: dict, progress, options: dict[str, Any], floor: Floor | None,
                assumption: str, run_blocks: Callable | None, stored_blocks: BlockResults | None, block_texels: int,
                refused: int | None) -> MethodOutcome:
    """Fit, score and store one method. ``make_passive`` makes the passive input (passive
    reflectometry's alone: made here, let go when the method is stored). ``stored_blocks``: a
    block method's tasks run on ``run_blocks`` (an executor's ``map``) over the stored blocks,
    their results over texel blocks stored and reused (:mod:`capture.pipeline.block_results`);
    None: the method fits ``train``. ``refused``: the memory limit (bytes) when the lumitexels
    were not gathered (``train`` and ``held`` then hold every texel but one view's samples each):
    the export is fitted on a subsample of texels."""
    if name == "passive":
        inputs = dataclasses.replace(inputs, passive=make_passive())
    route = None if stored_blocks is None else BlockRoute(stored_blocks.blocks, stored_blocks.map(run_blocks))
    try:
        fit = fit_method(name, train, inputs, rng=rng, progress=progress, route=route, **options)
    except MethodSkipped as exc:
        return MethodOutcome(name, "skipped", str(exc), outside_assumption=assumption)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return MethodOutcome(name, "failed", f"{type(exc).__name__}: {exc}", outside_assumption=assumption)
    if name == "passive" and inputs.passive is not None and inputs.passive.sample_sphere is not None:
        figures, pictures = _sample_sphere_figures(fit, train, held, inputs, truth)
    else:   # pictures: one view's samples each when the lumitexels were not gathered
        figures, pictures = _object_figures(fit, arrays, block_texels, train, held, inputs, truth, scored_truth)
    result = {"figures": figures, "warnings": fit.warnings,
              "inputs": {"calibration_ids": inputs.calibration.ids, "views": inputs.view_steps,
                         "held_out_views": inputs.held_out_steps, "texels": train.n_texels,
                         "training_samples": summary["training_samples"], "held_out_samples": summary["held_out_samples"]},
              "inputs_summary": summary, "floor": None if floor is None else asdict(floor),
              "outside_assumption": assumption}
    artifacts = {"model.npz": _npz(fit.arrays), "report.npz": _npz(pictures)}
    if name in EXPORTED_METHODS:   # what `gonio export` writes files from (its GGX fit is global)
        if refused is None:
            artifacts["appearance.npz"] = appearance_npz(name, fit, train, held, inputs.views, inputs.held_out,
                                                          fit.predict(train), fit.predict(held))
        else:
            release_freed_memory()   # scoring's and the pictures' blocks
            artifacts["appearance.npz"], figures["export_texels"] = _appearance_on_subsample(
                name, fit, arrays, train.n_texels, inputs, arrays.gatherable_texels(refused // 8), rng, block_texels)
    rid = store.add_reconstruction(session_id, name, result=result, params=fit.params,
                                   input_frames=inputs.view_frames, artifacts=artifacts)
    return MethodOutcome(name, "ok", "", figures, rid, warnings=fit.warnings, outside_assumption=assumption)


def _sample_sphere_figures(fit: Fitted, train: Lumitexels, held: Lumitexels, inputs: ProcessInputs,
                           truth) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Passive reflectometry's figures and pictures on the sample sphere: against the sphere's
    image and, with truth, its true material (never the object's held-out lights: another surface)."""
    material = truth.sample_sphere.material if truth is not None else None
    brdf = fit.brdf(np.zeros(1, int))
    score = score_sample_sphere(brdf, fit.arrays["lambertian"], inputs.passive, truth=material,
                                held_out_environment=truth.held_out_environment() if truth is not None else None)
    no_held = select_samples(held, np.zeros(held.n_samples, bool))
    pictures = method_pictures(fit, train, no_held, inputs, None if material is None else SampleTruth(material))
    return {**fit.figures, **score.figures}, {**pictures, **score.pictures}


def _object_figures(fit: Fitted, arrays: LumitexelArrays, block_texels: int, train: Lumitexels, held: Lumitexels,
                    inputs: ProcessInputs, truth, scored_truth: bool) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """A method's figures on the object's training and held-out samples (and the truth's),
    scored one texel block at a time from the stored arrays (block_scoring: per-block sums), and
    its report pictures."""
    figures = dict(fit.figures)
    scores = score_blocks(fit.predict_samples, arrays, max_texels=block_texels,
                          truth_of=functools.partial(_truth_of, truth) if scored_truth else None)
    figures["training_rel_rms"] = scores.training.relative_rms
    if scores.held_out.count:
        figures["held_out_rel_rms"] = scores.held_out.relative_rms
        figures["held_out_rel_rms_trimmed"] = scores.held_out.trimmed_relative_rms()
    if scores.truth is not None:
        figures["truth_rel_rms"] = scores.truth.relative_rms
    if fit.normals is not None:
        figures["normal_change_deg"] = _median_angle_deg(fit.normals, train.normal)
        true_n = truth.normals(train.position) if truth is not None else None
        if true_n is not None:   # detail the mesh lacks: the fitted normals should recover it
            figures["normal_error_mesh_deg"] = _median_angle_deg(train.normal, true_n)
            figures["normal_error_fitted_deg"] = _median_angle_deg(fit.normals, true_n)
    release_freed_memory()   # the fit's and scoring's blocks, before the pictures' full-size images
    return figures, method_pictures(fit, train, held, inputs, truth)


def _appearance_on_subsample(name: str, fit: Fitted, arrays: LumitexelArrays, n_texels: int, inputs: ProcessInputs,
                             n_pick: int, rng: int, block_texels: int) -> tuple[bytes, str]:
    """:func:`capture.export.appearance.appearance_npz` of ``n_pick`` of the ``n_texels`` texels
    drawn at random (all their samples gathered), and the figure that says so. (Gathered samples
    an eighth of the limit, ``n_pick`` from :meth:`LumitexelArrays.gatherable_texels`: the GGX
    fit and Lensch's predictions take about as much again, a quarter of the limit in all, what
    the limit leaves beside the pictures' full-size images; 11 650 texels of 36 views took
    113 MiB at 9x pixels.)"""
    pick = np.sort(np.random.default_rng(rng).choice(n_texels, min(n_pick, n_texels), replace=False))
    train, held = arrays.gather(pick, max_texels=block_texels)
    sub = dataclasses.replace(fit, arrays={k: np.asarray(v)[pick] for k, v in fit.arrays.items()
                                                   if k in ("labels", "materials")},
                              normals=None if fit.normals is None else fit.normals[pick])
    npz = appearance_npz(name, sub, train, held, inputs.views, inputs.held_out,
                         fit.predict_samples(pick[train.texel], train.wi, train.wo),
                         fit.predict_samples(pick[held.texel], held.wi, held.wo))
    return npz, f"the export fitted on {len(pick)} of {n_texels} texels drawn at random (--memory-limit)"


def _median_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Median angle (deg) between rows of unit vectors (N, 3)."""
    return float(np.degrees(np.median(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1, 1)))))


def _npz(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **{k: np.asarray(v) for k, v in arrays.items()})
    return buf.getvalue()


# -- truth --------------------------------------------------------------------------------------
def _truth_reflectance(truth, train: Lumitexels, held: Lumitexels) -> tuple[np.ndarray, np.ndarray] | None:
    """True ``f_r cos`` of every training and held-out sample (:func:`_truth_of`); None when the
    truth has no materials at these points."""
    try:
        return _truth_of(truth, train), _truth_of(truth, held)
    except ValueError:
        return None


def _truth_of(truth, lt: Lumitexels) -> np.ndarray:
    """True ``f_r cos`` (S, 3) of the samples of ``lt`` (mesh normals: the simulated object's
    own), in the calibration's units when it is absolute (1/sr); per texel and sample, so a texel
    block's alone. Raises ValueError where the truth has no materials."""
    ids, materials = truth.materials(lt.position)
    true_n = truth.normals(lt.position)
    wi, wo = lt.wi, lt.wo
    if true_n is not None:   # the sample's directions about the true (detailed) normal
        mesh_f, true_f = tangent_frames(lt.normal)[lt.texel], tangent_frames(true_n)[lt.texel]
        wi, wo = to_local(to_world(wi, mesh_f), true_f), to_local(to_world(wo, mesh_f), true_f)
    out = np.zeros((lt.n_samples, 3))
    tid = ids[lt.texel]
    for k, m in enumerate(materials):
        s = tid == k
        if s.any():
            out[s] = m.evaluate(wi[s], wo[s]) * np.maximum(wi[s, 2:3], 0.0)
    return out


def calibration_against_truth(store: Store, session: str, cal: SessionCalibration, truth) -> dict[str, Any]:
    """The calibration's errors against the simulation: focal length (%), principal point (px),
    camera centre (mm), each light (mm, % of its distance from the lab origin, direction deg)
    and the lamp intensity (% against the truth times the sensor's DN per radiance)."""
    K, Kt = cal.camera.K, truth.camera.K
    out: dict[str, Any] = {
        "focal_error_pct": [100 * float(K[i, i] / Kt[i, i] - 1) for i in (0, 1)],
        "principal_point_error_px": [float(K[0, 2] - Kt[0, 2]), float(K[1, 2] - Kt[1, 2])],
        "camera_centre_error_mm": float(np.linalg.norm(cal.camera.center - truth.camera.center)),
        "light_source": cal.light_source}
    steps = {s.index: s.step for s in store.steps(store.session(session).id)}
    rows, seen = [], set()
    for s, p in sorted(cal.lights_mm.items()):
        light = steps[s].light
        if light is None or light.xyz_mm is not None or _key(light) in seen:
            continue
        seen.add(_key(light))
        t = truth.light_position(light)
        d = float(np.linalg.norm(t))
        cosang = float(p @ t / (np.linalg.norm(p) * d))
        rows.append({"azimuth_deg": light.azimuth_deg, "elevation_deg": light.elevation_deg,
                     "error_mm": float(np.linalg.norm(p - t)), "distance_error_pct": 100 * float(np.linalg.norm(p) / d - 1),
                     "direction_error_deg": float(np.degrees(np.arccos(np.clip(cosang, -1, 1))))})
    out["lights"] = rows
    if rows:
        out["max_light_distance_error_pct"] = max(abs(r["distance_error_pct"]) for r in rows)
        out["max_light_direction_error_deg"] = max(r["direction_error_deg"] for r in rows)
        out["max_light_error_pct_of_distance"] = max(100 * r["error_mm"] / float(np.linalg.norm(
            truth.light_position(LightTarget(r["azimuth_deg"], r["elevation_deg"])))) for r in rows)
    if cal.absolute:
        expected = truth.light_intensity * truth.sensor_dn_per_radiance
        out["intensity_error_pct"] = (100 * (cal.light_intensity / expected - 1)).tolist()
    return out


def _key(light: LightTarget) -> tuple:
    return round(light.azimuth_deg, 3), round(light.elevation_deg, 3)
