"""Session calibration pipeline: stored frames -> ``calibration`` functions -> stored results.

:func:`calibrate_session` runs every calibration a session's captures allow, in dependency
order, and records each result in the store with its provenance (input frame ids, parameters,
code version)::

    dark        mean dark frame per exposure time (lens-cap steps)
    hdr         raw brackets of every step -> linear radiance (dark-subtracted, exposure-normalised)
    intrinsics  K and distortion from the checkerboard / ChArUco steps: the turntable sweep's
                and the hand-held views' (``handheld_board``) together
    turntable   axis, angle model and world frame from the same target at several turntable
                readings (the frames' read-backs)
    lights      one point light per spheres step (mirror spheres of known radius)
    positioner  arm kinematics fitted to those lights: a light position for every step
    polarization  diffuse / specular separation check (parallel/crossed or N analyser angles)
    gray_card   absolute scale from the 18 % card
    mirror_probe  lat-long environment map from mirror-sphere captures (lab frame)

This module only orchestrates: the image analysis is ``calibration``'s. A stage whose inputs
are missing is *skipped* with the reason; a stage that bad data fails (a
:class:`~calibration.errors.CalibrationError`, a :class:`StageDataError`, a store error) records
the error (naming the frame) and the others continue. Bad data never raises: only an unknown
session (:class:`SessionNotFound`) and a session with nothing to calibrate
(:class:`NothingToCalibrate`) do; any other exception is a bug and propagates.

Images: :class:`capture.pipeline.images.SessionImages` (the one HDR path, shared with processing),
with the master darks this run's dark stage computes. Radiance unit: DN per second, camera RGB,
float32 H x W x 3. Calibration steps' images stay in memory during a run; measurement steps are
merged for their figures and dropped (the polarization check merges the few poses it looks at
again).

Frames: pixels x right, y down; camera frame OpenCV, mm. The *lab frame* is the world frame of
DESIGN.md, fixed in the room: origin on the turntable axis at the platter surface, +z up the
axis, +x horizontal from the axis towards the camera (azimuth 0 = the camera's side), +y = z x x.
It comes from the turntable fit (axis, a point on it) plus two facts the images cannot give: the
height of the board's corner-grid centre above the platter (:class:`capture.lab.LabTargets`) and the
convention that azimuth 0 faces the camera. Fixed things (lights, sphere centres, the probe's
room) are reported in the lab and camera frames; the object frame at turntable reading r is
the lab frame turned about +z by the platter angle (``TurntableFit.platter_angle_deg``) plus
the fit's angle at the first board view.

Lights: with :attr:`LabTargets.sphere_centres_mm` the spheres' centres come from the lab frame (Lensch et al. 2003 Sec. 4.1: spheres of
known radius and position); without them, from their silhouettes against a lit backdrop. Each
light is the least-squares intersection of the rays reflected at the highlights
(:func:`calibration.lights.triangulate_point_light`); of the bright spots on each ball (the lamp,
and the lamp again through a neighbouring ball) the combination whose rays meet best is used
(:func:`calibration.spheres.pick_lamp_highlights`).
Expose the spheres short enough that the lamp's image does not clip.
"""
from __future__ import annotations

import io
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import cv2
import numpy as np

from calibration.errors import CalibrationError, TargetNotFound
from calibration.hdr import master_frame
from calibration.intrinsics import IntrinsicsResult, calibrate_intrinsics
from calibration.lights import (PositionerModel, detect_sphere, fit_positioner_model, ray_weights, sphere_center_from_silhouette,
                                triangulate_point_light)
from calibration.polarization import fit_polarization, separate_parallel_crossed
from calibration.probe import merge_probes, mirror_sphere_to_latlong
from calibration.raw import demosaic_smooth_hue
from calibration.radiometry import find_gray_card, gray_card_scale
from calibration.spheres import (find_mirror_sphere, lamp_spots, pick_lamp_highlights, project_spheres,
                                 sphere_silhouettes)
from calibration.targets import TargetDetection, detect_charuco, detect_chessboard, make_charuco_board, to_gray_u8
from calibration.turntable import TurntableFit, consistent_corner_order, fit_turntable, lab_frame
from rig import LightTarget

from ..plan import CALIBRATION_KINDS
from ..lab import LabTargets, TargetsNeeded
from ..lab_resolver import resolve_lab
from ..store import FrameRecord, SessionNotFound, Store, StoreError, crash
from .calibration_record import frames_digest, record_run
from .images import FrameDataError, SessionImages, dark_artifact_name, exposure_s
from .process import object_pose
from .progress import Progress, ProgressSink
from .stage_records import (CalibrationRun, CardReading, DarkExposure, DarkRecord, EnvironmentRecord, GrayCardRecord,
                            HdrRecord, HdrStep, IntrinsicsRecord, LightsRecord, LocatedLight, PolarizationPose,
                            PolarizationRecord, Pose, PositionerRecord, ProbeView, StageRecord, StageRun, StepLight,
                            TurntableRecord, UnseenLight)

__all__ = ["STAGES", "CALIBRATION_STEP_KINDS", "LabTargets", "StageResult", "CalibrationReport",
           "NothingToCalibrate", "TargetsNeeded", "calibrate_session", "SessionNotFound"]

#: stage names, in the order they run
STAGES = ("dark", "hdr", "intrinsics", "turntable", "lights", "positioner", "polarization",
          "gray_card", "mirror_probe")
#: below this fraction of coverage-grid cells holding corners, the intrinsics fit falls back to a
#: constrained model (principal point at the image centre, no tangential terms, k1 only): a
#: board seen only near the image centre (turntable sweeps) cannot separate those parameters
MIN_COVERAGE_FULL_MODEL = 0.5
#: the arm model fails when its RMS residual exceeds this fraction of its radius (seen: 1 % at
#: 1200 x 800; a mirrored solution of scattered 320 x 240 lights: 40 %)
MAX_ARM_RMS_FRACTION = 0.1
#: poses (turntable angle x light) the polarization check separates, spread over the session
POLARIZATION_POSES = 4
#: least lat-long environment map height (width is twice), pixels; a larger sphere image keeps
#: its own resolution (one map row per pixel of sphere radius: the reflection sweeps 180 deg
#: of elevation over the radius)
MIN_PROBE_HEIGHT = 128
_CONSTRAINED_FLAGS = (cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2
                      | cv2.CALIB_FIX_K3)


@dataclass
class StageResult:
    """Outcome of one stage.

    Attributes
    ----------
    stage : str
        One of :data:`STAGES`.
    status : {'ok', 'skipped', 'failed'}
    reason : str
        Why it was skipped or what failed (names the frame where one is to blame).
    figures : dict
        Key numbers for the summary table (JSON-able).
    calibration_id : int or None
        The stored result's id (``Store.results``).
    seconds : float
        Wall time the stage took, seconds.
    """

    stage: str
    status: str
    reason: str = ""
    figures: dict[str, Any] = field(default_factory=dict)
    calibration_id: int | None = None
    seconds: float = 0.0


@dataclass
class StageOutput:
    """What a stage hands :func:`calibrate_session` to store (``Store.add_calibration``).

    Attributes
    ----------
    result : StageRecord
        The stored result (:mod:`capture.pipeline.stage_records`).
    figures : dict
        Key numbers for the summary table.
    input_frames : list of int
        Ids of the frames the result was computed from (provenance).
    artifacts : dict of str -> bytes
        Files stored beside the result.
    params : dict
        Parameters the stage ran with (provenance).
    errors : list of str
        Inputs the stage lost (each names its frame): the result is stored for the rest but the
        stage reports ``failed``.
    """

    result: StageRecord
    figures: dict[str, Any]
    input_frames: list[int]
    artifacts: dict[str, bytes] = field(default_factory=dict)
    params: dict[str, Any] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class LabFrame:
    """Lab -> camera pose (module docstring): ``X_cam = R @ X_lab + t_mm``; the turntable turns
    by ``angle_scale * reading`` degrees about the lab's +z."""

    R: np.ndarray
    t_mm: np.ndarray
    angle_scale: float = 1.0

    def to_lab(self, x_cam_mm: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) mm -> lab frame (..., 3) mm."""
        return (np.asarray(x_cam_mm) - self.t_mm) @ self.R

    def to_camera(self, x_lab_mm: np.ndarray, reading_deg: float | None = None) -> np.ndarray:
        """Lab-frame points (..., 3) mm -> camera frame; with ``reading_deg``, points of something
        standing on the turntable, given at reading 0, turned to that reading first."""
        x = np.asarray(x_lab_mm, float)
        if reading_deg is not None:
            x = x @ object_pose(self.angle_scale * reading_deg)[:3, :3].T
        return x @ self.R.T + self.t_mm


class StageDataError(ValueError):
    """The session's stored data cannot feed a stage: a step without the read-back or planned
    value a stage needs (the message names it)."""


@dataclass
class CalibrationReport:
    """Everything one :func:`calibrate_session` run produced.

    ``plots`` holds in-memory arrays for :func:`capture.pipeline.calibration_report.write_report`
    (per-view errors, coverage grid, example images); they are not persisted beyond what the
    stages store.
    """

    session: str
    stages: list[StageResult] = field(default_factory=list)
    plots: dict[str, Any] = field(default_factory=dict)

    def stage(self, name: str) -> StageResult:
        for s in self.stages:
            if s.stage == name:
                return s
        raise KeyError(f"no stage {name!r}; stages: {', '.join(STAGES)}")

    @property
    def ran(self) -> list[StageResult]:
        return [s for s in self.stages if s.status != "skipped"]

    @property
    def failed(self) -> list[StageResult]:
        return [s for s in self.stages if s.status == "failed"]


#: step kinds that hold calibration captures
CALIBRATION_STEP_KINDS = tuple(CALIBRATION_KINDS)


class NothingToCalibrate(ValueError):
    """The session has no stored calibration captures (the message says what to add)."""


class _Skip(Exception):
    """Internal: the stage lacks its inputs (the message says which)."""


#: detectors see the HDR image scaled so this percentile is white (hot pixels and highlights do
#: not crush the contrast)
DETECTION_WHITE_PERCENTILE = 99.5


# -- the session as the stages see it ----------------------------------------------------------
class _Context:
    def __init__(self, store: Store, name: str, targets: LabTargets, measure_hdr: bool) -> None:
        self.store = store
        self.measure_hdr = measure_hdr
        self.images = SessionImages(store, name)          # darks: filled by the dark stage
        self.info = self.images.info
        self.targets = targets
        self.steps = self.images.steps
        self.frames: dict[int, list[FrameRecord]] = self.images.by_step
        self.hdr: dict[int, np.ndarray] = {}           # calibration step -> (H, W, 3) radiance
        self.bad_steps: set[int] = set()               # steps whose frames could not be merged
        self.tick: Callable[[int, int], None] = lambda done, total: None  # progress inside a stage
        # what the stages made for the later ones (None: that stage did not succeed)
        self.intrinsics: IntrinsicsResult | None = None
        self.detections: dict[int, TargetDetection] = {}    # checkerboard step -> corners
        self.detector: str | None = None                    # 'charuco' or 'chessboard'
        self.lab: LabFrame | None = None
        #: each light the lights stage located, with the reflected rays (points mm, unit directions;
        #: camera frame) it was triangulated from: the positioner stage fits the arm to them
        self.lights: list[tuple[LocatedLight, tuple[np.ndarray, np.ndarray]]] | None = None
        self.positioner: PositionerModel | None = None

    def steps_of(self, kind: str) -> list[int]:
        """Indices of steps of ``kind`` that have frames, in order."""
        return [i for i, d in sorted(self.steps.items()) if d.kind == kind and self.frames.get(i)]

    def frame_ids(self, steps) -> list[int]:
        return [f.id for s in steps for f in self.frames[s]]

    def merged_steps(self, kind: str) -> list[int]:
        """Steps of ``kind`` with an HDR image; skips the stage when there are none."""
        steps = self.steps_of(kind)
        if not steps:
            raise _Skip(f"no {kind} captures in this session")
        merged = [s for s in steps if s in self.hdr]
        if not merged:
            raise _Skip(f"none of the {len(steps)} {kind} steps has an HDR image (see the hdr stage)")
        return merged

    def reading(self, step: int, key: str) -> float:
        vals = [f.positions.get(key) for f in self.frames[step]]
        vals = [v for v in vals if v is not None]
        if not vals:
            planned = getattr(self.steps[step], key)
            if planned is None:
                raise StageDataError(f"step {step}: frames have no {key!r} read-back and the plan names none")
            return float(planned)
        return float(np.mean(vals))


# -- stages -------------------------------------------------------------------------------------
def _stage_dark(ctx: _Context, rep: CalibrationReport) -> StageOutput:
    steps = ctx.steps_of("dark")
    if not steps:
        raise _Skip("no dark (lens-cap) captures in this session")
    by_t: dict[float, list[FrameRecord]] = {}
    for s in steps:
        for f in ctx.frames[s]:
            by_t.setdefault(round(exposure_s(f), 9), []).append(f)
    out, artifacts, scatter = [], {}, []
    for t, frames in sorted(by_t.items()):
        raws = [ctx.images.raw(f) for f in frames]
        stack = np.stack([r.data for r in raws]).astype(np.float32)
        master = master_frame(stack, "mean")
        ctx.images.darks[t] = master
        if len(frames) > 1:  # temporal scatter about the master: read noise (+ dark shot noise)
            scatter.append(float(np.std(stack - master)) * np.sqrt(len(frames) / (len(frames) - 1)))
        above = master - raws[0].black_level
        buf = io.BytesIO()
        np.save(buf, master)
        artifacts[dark_artifact_name(t)] = buf.getvalue()
        out.append(DarkExposure(t, len(frames), float(above.mean()), float(above.std()), int(np.count_nonzero(
            above > above.mean() + 8 * max(float(above.std()), 1e-6)))))
    noise = ctx.images.read_noise_dn = float(np.median(scatter)) if scatter else None
    figures = {"exposures": len(out),
               "mean_above_black_dn": round(float(np.mean([o.mean_above_black_dn for o in out])), 3),
               "read_noise_dn": None if noise is None else round(noise, 2)}
    return StageOutput(DarkRecord(tuple(out), noise), figures, ctx.frame_ids(steps), artifacts)


def _stage_hdr(ctx: _Context, rep: CalibrationReport) -> StageOutput:
    steps = [s for s in sorted(ctx.frames) if ctx.steps[s].kind != "dark"
             and (ctx.measure_hdr or ctx.steps[s].kind != "measure")]
    if not steps:
        raise _Skip("no frames besides dark frames in this session")
    per_step, example, errors = [], None, []
    for k, s in enumerate(steps):
        ctx.tick(k + 1, len(steps))
        try:
            im = ctx.images.merge(s)
        except (CalibrationError, FrameDataError) as exc:  # an unreadable frame loses its step only
            errors.append(str(exc))
            ctx.bad_steps.add(s)
            continue
        # calibration images stay in memory for the later stages; measurement steps (a session
        # can hold thousands, hundreds of MB each) are merged again where a stage needs them
        if ctx.steps[s].kind != "measure":
            ctx.hdr[s] = im.radiance
        per_step.append(HdrStep(s, im.spec.kind, len(im.frame_ids), tuple(im.exposures_s), im.dark_subtracted,
                                im.saturated_fraction, im.dynamic_range_stops))
        if example is None or len(im.exposures_s) > len(example.exposures_s):
            example = im
    if example is None:
        raise CalibrationError("no step could be merged: " + "; ".join(errors))
    rep.plots["hdr_example"] = {"step": example.step, "image": example.radiance,
                                "exposures_s": example.exposures_s}
    figures = {"steps": len(per_step), "failed_steps": len(errors),
               "max_saturated_pct": round(100 * max(m.saturated_fraction for m in per_step), 3),
               "dark_subtracted_frames": sum(m.dark_subtracted for m in per_step)}
    return StageOutput(HdrRecord(tuple(per_step), ctx.images.read_noise_dn or 1.0, tuple(errors)), figures,
                       ctx.frame_ids([m.step for m in per_step]), errors=errors)


def _detector(ctx: _Context):
    t = ctx.targets
    board = make_charuco_board(t.charuco_squares, t.charuco_square_mm, t.charuco_marker_mm,
                               t.charuco_dictionary) if t.has_board("charuco") else None

    def detect(img, frame):
        # ChArUco first: its corner ids stay consistent as the board turns (the turntable fit
        # needs that); a plain chessboard otherwise
        if board is not None:
            try:
                return detect_charuco(img, board, frame=frame), "charuco"
            except TargetNotFound:
                if not t.has_board("chessboard"):
                    raise
        return detect_chessboard(img, t.chessboard_inner, t.chessboard_square_mm, frame=frame), "chessboard"
    return detect


#: the step kinds whose board views the intrinsics use: the turntable sweep (also the axis's
#: views) and the free, hand-held views that tilt about both axes and reach the frame's corners
INTRINSICS_KINDS = ("checkerboard", "handheld_board")


def _board_steps(ctx: _Context) -> list[int]:
    """The merged steps of :data:`INTRINSICS_KINDS`; skips the stage when there are none."""
    steps, reasons = [], []
    for kind in INTRINSICS_KINDS:
        try:
            steps += ctx.merged_steps(kind)
        except _Skip as exc:
            reasons.append(str(exc))
    if not steps:
        raise _Skip("; ".join(reasons))
    return sorted(steps)


def _stage_intrinsics(ctx: _Context, rep: CalibrationReport) -> StageOutput:
    steps = _board_steps(ctx)
    detect = _detector(ctx)
    dets, kinds, det_steps, missing = [], [], [], []
    for s in steps:
        name = f"frame {ctx.frames[s][0].id} (step {s})"
        try:
            d, kind = detect(to_gray_u8(ctx.hdr[s].mean(axis=2), white_percentile=DETECTION_WHITE_PERCENTILE), name)
        except TargetNotFound as exc:
            missing.append(str(exc))
            continue
        dets.append(d)
        kinds.append(kind)
        det_steps.append(s)
    if len({*kinds}) > 1:  # two target types in one session: keep the majority
        major = max(set(kinds), key=kinds.count)
        keep = [i for i, k in enumerate(kinds) if k == major]
        dets, det_steps = [dets[i] for i in keep], [det_steps[i] for i in keep]
        kinds = [major] * len(keep)
    if len(dets) < 3:
        raise CalibrationError(f"a board was found in {len(dets)} of {len(steps)} board steps "
                               f"(need 3): {'; '.join(missing) or 'no views'}")
    flags = ctx.targets.intrinsics_flags
    res = calibrate_intrinsics(dets, flags=flags)
    model = "full"
    if res.coverage_fraction < MIN_COVERAGE_FULL_MODEL:
        # K starts at the image centre (calibrateCamera's own guess), so FIX_PRINCIPAL_POINT
        # keeps it there
        flags |= _CONSTRAINED_FLAGS
        model = (f"constrained (principal point at the image centre, k1 only): corners cover "
                 f"{100 * res.coverage_fraction:.0f}% of the image (< {100 * MIN_COVERAGE_FULL_MODEL:.0f}%); "
                 "add board views across the whole frame for the full model")
        res = calibrate_intrinsics(dets, flags=flags)
    ctx.intrinsics = res
    # the turntable stage reads the sweep's views alone: the hand-held ones did not turn with it
    ctx.detections = {s: d for s, d in zip(det_steps, dets) if ctx.steps[s].kind == "checkerboard"}
    kept = {d.frame for d in dets} - {r.frame for r in res.rejected}
    views = {kind: sum(ctx.steps[s].kind == kind and d.frame in kept for s, d in zip(det_steps, dets))
             for kind in INTRINSICS_KINDS}
    ctx.detector = kinds[0]
    rep.plots["intrinsics"] = {"frames": res.frames, "per_view_rms_px": res.per_view_rms_px,
                               "coverage": res.coverage, "image_size": res.image_size,
                               "points": [d.image_points for d in dets if d.frame in kept]}
    result = IntrinsicsRecord(K=res.K, dist=res.dist, image_size=tuple(res.image_size), rms_px=res.rms_px,
                              K_std=res.K_std, dist_std=res.dist_std, per_view_rms_px=res.per_view_rms_px,
                              views=tuple(res.frames), views_by_kind=views, rejected=tuple(res.rejected),
                              not_found=tuple(missing), target=kinds[0], coverage=res.coverage,
                              coverage_fraction=res.coverage_fraction, model=model, flags=flags,
                              distortion_note=res.model_note)
    figures = {"rms_px": round(res.rms_px, 3), "fx_px": round(float(res.K[0, 0]), 2),
               "fy_px": round(float(res.K[1, 1]), 2), "cx_px": round(float(res.K[0, 2]), 2),
               "cy_px": round(float(res.K[1, 2]), 2), "views": len(res.frames),
               **{f"views_{kind}": n for kind, n in views.items()},
               "coverage_pct": round(100 * res.coverage_fraction),
               "model": "full" if model == "full" else "constrained"}
    params = {"targets": asdict(ctx.targets), "detector": kinds[0], "flags": flags}
    return StageOutput(result, figures, ctx.frame_ids(det_steps), params=params)


def _need(product, stage: str, why: str):
    """``product`` of an earlier stage, or skip naming that stage."""
    if product is None:
        raise _Skip(f"needs the {stage} stage ({why}), which did not succeed")
    return product


def _lab_frame(fit: TurntableFit, targets: LabTargets, detector: str) -> LabFrame:
    """The lab frame (module docstring) from a turntable fit and the board's stated height."""
    if detector == "charuco":  # OpenCV's ChArUco corners run from one square in to one square short
        (cols, rows), sq = targets.charuco_squares, targets.charuco_square_mm
        grid_centre, height = [cols * sq / 2, rows * sq / 2, 0.0], targets.charuco_centre_height_mm
    else:  # chessboard object points start at the first inner corner
        (cols, rows), sq = targets.chessboard_inner, targets.chessboard_square_mm
        grid_centre, height = [(cols - 1) * sq / 2, (rows - 1) * sq / 2, 0.0], targets.chessboard_centre_height_mm
    return LabFrame(*lab_frame(fit, grid_centre, height), angle_scale=fit.angle_scale)


def _stage_turntable(ctx: _Context, rep: CalibrationReport) -> StageOutput:
    if not ctx.steps_of("checkerboard"):
        raise _Skip("no checkerboard captures in this session")
    intr = _need(ctx.intrinsics, "intrinsics", "camera matrix")
    kept = set(intr.frames)
    steps = [s for s, d in ctx.detections.items() if d.frame in kept]
    dets_by_step = dict(zip(steps, consistent_corner_order([ctx.detections[s] for s in steps], intr.K, intr.dist)))
    readings = [ctx.reading(s, "turntable_deg") for s in steps]
    if len(set(np.round(readings, 3))) < 2:
        raise _Skip(f"the target was seen at {len(set(np.round(readings, 3)))} turntable "
                    "angle(s); the axis needs captures at several angles")
    fit = fit_turntable([dets_by_step[s] for s in steps], intr.K, intr.dist, angles_deg=readings)
    ctx.lab = _lab_frame(fit, ctx.targets, ctx.detector)
    R_lab, t_lab = ctx.lab.R, ctx.lab.t_mm
    rep.plots["turntable"] = {"readings_deg": np.array(readings), "per_view_rms_px": fit.per_view_rms_px,
                              "view_angles_deg": fit.view_angles_deg}
    tilt = float(np.degrees(np.arccos(abs(fit.axis_camera[1]))))
    camera_lab = -R_lab.T @ t_lab
    result = TurntableRecord(lab_to_camera=Pose(R_lab, t_lab), angle_scale=fit.angle_scale,
                             axis_camera=fit.axis_camera, origin_camera_mm=fit.origin_camera, R_ref=fit.R_ref,
                             angle_offset_deg=fit.angle_offset_deg, fit_status=fit.fit_status,
                             fit_message=fit.fit_message, readings_deg=np.array(readings),
                             view_angles_deg=fit.view_angles_deg, per_view_rms_px=fit.per_view_rms_px,
                             rms_px=fit.rms_px, axis_std_deg=fit.axis_std_deg,
                             target_in_world=Pose(*fit.target_in_world), camera_centre_lab_mm=camera_lab)
    figures = {"rms_px": round(fit.rms_px, 3), "axis": [round(float(v), 4) for v in fit.axis_camera],
               "axis_std_deg": round(fit.axis_std_deg, 3), "axis_from_image_y_deg": round(tilt, 2),
               "views": len(steps), "camera_lab_mm": [round(float(v), 1) for v in camera_lab]}
    return StageOutput(result, figures, ctx.frame_ids(steps),
                       params={"angles_from": "frame read-backs turntable_deg"})


#: a sphere shows the lamp when its brightest pixel is at least this many times the frame's 99th
#: luminance percentile (lit surfaces: a mirror shows them dimmer than they are, while the lamp's
#: image is ~50-200x brighter than a white card it lights, though the HDR merge may clip it)
#: and at least MIN_HIGHLIGHT_FRACTION of the frame's brightest highlight;
#: other spheres (shadowed by the object, the lamp behind them, or a highlight smaller than a
#: pixel that the pixel grid missed) sit that light out
MIN_LAMP_CONTRAST = 2.0
MIN_HIGHLIGHT_FRACTION = 0.25


def _known_spheres(ctx: _Context, K, dist, radius: float, shape: tuple[int, int], frame: str,
                   reading: float | None):
    """The spheres at their configured lab positions (``LabTargets.sphere_centres_mm`` through
    the lab frame, turned to the turntable ``reading`` when they stand on it) that the image
    holds whole and unoccluded: camera-frame centres (M, 3) mm, their image discs and their
    indices in the configured list."""
    centres = ctx.lab.to_camera(np.asarray(ctx.targets.sphere_centres_mm, float),
                                reading if ctx.targets.spheres_on_turntable else None)
    spheres, inside = project_spheres(centres, radius, K, dist, (shape[1], shape[0]))
    keep: list[int] = []  # a sphere partly behind a nearer one shows a clipped disc: left out
    for k in np.argsort(np.linalg.norm(centres[inside], axis=1)):
        if all(np.hypot(*(spheres[k].center_px - spheres[j].center_px)) >= spheres[k].radius_px + spheres[j].radius_px
               for j in keep):
            keep.append(int(k))
    keep.sort()
    if len(keep) < 2:
        raise TargetNotFound(f"{len(keep)} of the {len(centres)} configured spheres project whole and unoccluded "
                             "inside the image (need 2); check LabTargets.sphere_centres_mm", frame=frame)
    return centres[inside[keep]], [spheres[k] for k in keep], inside[keep]


def _sphere_views(ctx: _Context, steps: list[int], K, dist, radius: float) -> tuple[dict, str, list[str]]:
    """Each spheres step's spheres: ``{step: (camera centres (M, 3) mm, SphereImage list,
    configured indices)}``, where the centres came from, and why steps were left out (known
    positions: a turntable angle at which fewer than two balls show whole loses only its step)."""
    shape = ctx.hdr[steps[0]].shape[:2]
    name = {s: f"frame {ctx.frames[s][0].id} (step {s})" for s in steps}
    turning = ctx.targets.spheres_on_turntable
    known = ctx.targets.sphere_centres_mm is not None
    if known and ctx.lab is not None:
        views, errors = {}, []
        for s in steps:
            try:
                views[s] = _known_spheres(ctx, K, dist, radius, shape, name[s],
                                          ctx.reading(s, "turntable_deg") if turning else None)
            except TargetNotFound as exc:
                errors.append(str(exc))
        if not views:
            raise TargetNotFound(f"no spheres step shows two configured spheres whole: {errors[0]}")
        return views, "known positions (LabTargets.sphere_centres_mm, lab frame)", errors
    # no positions, or no lab frame to place them: the silhouettes against a backdrop, found in
    # the steps of one turntable angle together (the spheres stand still between them)
    groups: dict[float, list[int]] = {}
    for s in steps:
        groups.setdefault(round(ctx.reading(s, "turntable_deg"), 3) if turning else 0.0, []).append(s)
    views = {}
    for group in groups.values():
        blobs = sphere_silhouettes([ctx.hdr[s] for s in group], ctx.targets.sphere_reflectance)
        if len(blobs) < 2:
            why = ("the turntable stage gave no lab frame to place LabTargets.sphere_centres_mm, and "
                   if known else "no LabTargets.sphere_centres_mm, and ")
            raise TargetNotFound(f"{why}{len(blobs)} mirror sphere silhouette(s) were found in the spheres "
                                 "steps (need 2 against a lit backdrop)", frame=name[group[0]])
        spheres = [detect_sphere(b, frame=name[group[0]]) for b in blobs]
        centres = np.array([sphere_center_from_silhouette(sp, K, dist, radius) for sp in spheres])
        views.update({s: (centres, spheres, np.arange(len(spheres))) for s in group})
    return views, "silhouettes", []


def _light_key(light: LightTarget | None, step: int) -> LightTarget | str:
    """Steps that commanded the same light see the same lamp (a step without one: its own)."""
    return f"step {step}" if light is None else light


def _stage_lights(ctx: _Context, rep: CalibrationReport) -> StageOutput:
    steps = ctx.merged_steps("spheres")
    intr = _need(ctx.intrinsics, "intrinsics", "camera matrix")
    K, dist, radius = intr.K, intr.dist, ctx.targets.sphere_radius_mm
    if radius is None:
        raise _Skip("LabTargets states no sphere_radius_mm (the light-calibration spheres)")
    views, source, errors = _sphere_views(ctx, steps, K, dist, radius)
    h, w = ctx.hdr[steps[0]].shape[:2]
    yy, xx = np.indices((h, w))
    seen: dict[LightTarget | str, dict[str, list]] = {}   # light -> its steps' highlights, centres, sphere ids
    unseen = []
    for s in views:
        name = f"frame {ctx.frames[s][0].id} (step {s})"
        centres, spheres, index = views[s]
        lum = ctx.hdr[s].mean(axis=2)
        try:  # one bad view loses its step; the others still locate the lights
            discs = [(xx - sp.center_px[0]) ** 2 + (yy - sp.center_px[1]) ** 2 < sp.radius_px ** 2 for sp in spheres]
            peak = max(float(lum[d].max()) for d in discs)
            level = max(MIN_HIGHLIGHT_FRACTION * peak, MIN_LAMP_CONTRAST * float(np.percentile(lum, 99)))
            spots = [lamp_spots(lum, sp, level, frame=name) for sp in spheres]
            use = np.array([i for i, ss in enumerate(spots) if ss], int)
            if len(use) >= 2:
                hl, kept = pick_lamp_highlights([spots[i] for i in use], centres[use], radius, K, dist)
                use = use[kept]
        except CalibrationError as exc:
            errors.append(f"{name}: {exc}" if name not in str(exc) else str(exc))
            continue
        if len(use) < 2:  # not a fault: from here the lamp cannot be seen in two spheres
            unseen.append(UnseenLight(s, ctx.frames[s][0].id, ctx.steps[s].light, len(use)))
            continue
        got = seen.setdefault(_light_key(ctx.steps[s].light, s),
                              {"steps": [], "highlights": [], "centres": [], "spheres": []})
        got["steps"].append(s)
        got["highlights"].append(hl)
        got["centres"].append(centres[use])
        got["spheres"].append(index[use])
    lights, rows, measured = [], [], []
    for got in seen.values():
        s = got["steps"][0]
        hl, centres = np.concatenate(got["highlights"]), np.concatenate(got["centres"])
        try:
            pl = triangulate_point_light(hl, centres, radius, K, dist)
        except CalibrationError as exc:
            errors.append(f"frame {ctx.frames[s][0].id} (step {s}) and the other steps of its light: {exc}")
            continue
        p_lab = None if ctx.lab is None else ctx.lab.to_lab(pl.position_mm)
        rows.append(LocatedLight(step=s, position_camera_mm=pl.position_mm, commanded=ctx.steps[s].light,
                                 position_lab_mm=p_lab, steps=tuple(got["steps"]), frame=ctx.frames[s][0].id,
                                 std_mm=pl.std_mm, residuals_mm=pl.residuals_mm, highlights_px=hl,
                                 spheres_used=tuple(np.concatenate(got["spheres"]).tolist()),
                                 readback_mm=_readback_light(ctx, s)))
        lights.append(pl)
        measured.append((rows[-1], (pl.surface_points_mm, pl.directions)))
    if not rows:
        raise CalibrationError(f"no light could be located: {len(unseen)} of {len(steps)} spheres steps show "
                               "the lamp in fewer than 2 spheres" + "".join(f"; {e}" for e in errors))
    ctx.lights = measured
    res = np.concatenate([pl.residuals_mm for pl in lights])
    first = views[min(views)]
    result = LightsRecord(lights=tuple(rows), sphere_radius_mm=radius, sphere_centres_camera_mm=first[0],
                          sphere_centres_lab_mm=None if ctx.lab is None else ctx.lab.to_lab(first[0]),
                          sphere_centres_from=source, spheres_on_turntable=ctx.targets.spheres_on_turntable,
                          sphere_radii_px=tuple(sp.radius_px for sp in first[1]), errors=tuple(errors),
                          unseen=tuple(unseen))
    figures = {"lights": len(rows), "steps": len(steps), "failed": len(errors), "unseen": len(unseen),
               "spheres": len(first[1]), "rays": len(res),
               "centres": "known" if source.startswith("known") else "silhouettes",
               "ray_residual_rms_mm": round(float(np.sqrt(np.mean(res ** 2))), 3),
               "max_std_mm": round(float(max(pl.std_mm.max() for pl in lights)), 2)}
    return StageOutput(result, figures, ctx.frame_ids([s for m, _ in measured for s in m.steps]),
                       params={"sphere_radius_mm": radius, "sphere_centres_from": source}, errors=errors)


def _readback_light(ctx: _Context, step: int) -> np.ndarray | None:
    vals = [f.positions.get("light_mm") for f in ctx.frames[step] if f.positions.get("light_mm")]
    return np.mean(np.array(vals, float), axis=0) if vals else None


def _stage_positioner(ctx: _Context, rep: CalibrationReport) -> StageOutput:
    measured = _need(ctx.lights, "lights", "measured light positions")
    lab = _need(ctx.lab, "turntable", "the lab frame: azimuth and elevation are about the turntable axis")
    use = [(m, rays) for m, rays in measured if m.commanded is not None and m.commanded.xyz_mm is None]
    if len(use) < 3:
        raise _Skip(f"{len(use)} spheres steps with commanded azimuth/elevation (need 3; "
                    "xyz_mm light targets have no arm model)")
    az = np.array([m.commanded.azimuth_deg for m, _ in use])
    el = np.array([m.commanded.elevation_deg for m, _ in use])
    X = np.array([m.position_lab_mm for m, _ in use])
    # the rays in the lab frame, each tagged with its light's pose
    P = np.concatenate([lab.to_lab(points) for _, (points, _) in use])
    D = np.concatenate([dirs @ lab.R for _, (_, dirs) in use])
    pose = np.concatenate([np.full(len(points), i) for i, (_, (points, _)) in enumerate(use)])
    weight = np.concatenate([ray_weights(*rays, np.zeros(3)) for _, rays in use])
    model = fit_positioner_model(az, el, X, rays=(P, D, pose, weight))
    if model.radius_mm <= 0 or model.rms_mm > MAX_ARM_RMS_FRACTION * model.radius_mm:
        # LM can settle on a mirrored arm (negative radius) when the lights scatter in distance
        raise CalibrationError(
            f"the arm model does not fit the {len(use)} measured lights (radius {model.radius_mm:.0f} mm, "
            f"rms {model.rms_mm:.0f} mm): their distances scatter too much (lights stage max_std_mm); "
            "image the spheres at a higher resolution or add light poses")
    d = X - model.centre_mm
    rep.plots["lights"] = {"commanded_az": az, "commanded_el": el,
                           "measured_az": np.degrees(np.arctan2(d[:, 1], d[:, 0])) - model.azimuth_offset_deg,
                           "measured_el": np.degrees(np.arcsin(np.clip(
                               d[:, 2] / np.linalg.norm(d, axis=1), -1, 1))),
                           "residuals_mm": model.residuals_mm}
    per_step = []
    for idx, st in sorted(ctx.steps.items()):
        light = st.light
        if light is None or light.xyz_mm is not None:
            continue
        p_lab = model.position(light.azimuth_deg, light.elevation_deg)
        per_step.append(StepLight(idx, p_lab, lab.R @ p_lab + lab.t_mm))
    ctx.positioner = model
    result = PositionerRecord(step_lights=tuple(per_step), centre_lab_mm=model.centre_mm, radius_mm=model.radius_mm,
                              azimuth_offset_deg=model.azimuth_offset_deg,
                              elevation_offset_deg=model.elevation_offset_deg, param_std=model.param_std,
                              fit_status=model.fit_status, fit_message=model.fit_message,
                              residuals_mm=model.residuals_mm, rms_mm=model.rms_mm, ray_rms_deg=model.ray_rms_deg)
    figures = {"rms_mm": round(model.rms_mm, 2), "ray_rms_deg": round(model.ray_rms_deg, 3),
               "radius_mm": round(model.radius_mm, 1),
               "el_offset_deg": round(model.elevation_offset_deg, 2), "steps_with_light": len(per_step)}
    params = {"model": "arm (centre, radius, azimuth/elevation offsets)", "fitted_to": "reflected rays"}
    return StageOutput(result, figures, ctx.frame_ids([m.step for m, _ in use]), params=params)


def _stage_polarization(ctx: _Context, rep: CalibrationReport) -> StageOutput:
    groups: dict[tuple, list[int]] = {}
    for s in sorted(ctx.frames):
        st = ctx.steps[s]
        if st.polarizer_deg is None or st.kind == "dark" or s in ctx.bad_steps:
            continue
        groups.setdefault((st.kind, st.turntable_deg, st.light), []).append(s)
    if not groups:
        raise _Skip("no captures with a polarizer (analyser) angle in this session")
    groups = {k: v for k, v in groups.items()
              if len({round(ctx.reading(s, "polarizer_deg") % 180, 1) for s in v}) >= 2}
    if not groups:
        raise _Skip("no pose was captured at two or more analyser angles")
    out, example, used = [], None, []
    # a check, not the separation of the whole session: a few poses spread over the session
    keys = list(groups)
    pick = np.unique(np.linspace(0, len(keys) - 1, min(len(keys), POLARIZATION_POSES)).round().astype(int))
    keys = [keys[i] for i in pick]
    for steps in (groups[k] for k in keys):
        # analyser angle relative to the light's polarizer (the lab mounts it at 0 deg)
        angles = np.array([ctx.reading(s, "polarizer_deg") for s in steps])
        distinct = np.unique(np.round(angles % 180, 1))
        stack = np.stack([ctx.hdr[s] if s in ctx.hdr else ctx.images.merge(s).radiance for s in steps])
        if len(distinct) == 2 and abs(abs(distinct[1] - distinct[0]) - 90) < 1:
            par = int(np.argmin(np.abs(((angles + 90) % 180) - 90)))   # nearest 0 mod 180
            cro = int(np.argmin(np.abs((angles % 180) - 90)))
            sep = separate_parallel_crossed(stack[par], stack[cro], read_sigma=0.0)
            diffuse, specular, method = sep.diffuse, sep.specular, "parallel/crossed"
            misfit = float("nan")
        elif len(distinct) >= 3:
            fit = fit_polarization(stack, angles)
            diffuse, specular, method = fit.diffuse, fit.specular, f"{len(distinct)}-angle sinusoid"
            misfit = float(fit.residual_rms.mean() / max(float(stack.mean()), 1e-12))
        else:
            continue  # two angles that are not 90 deg apart do not separate
        total = float(stack.mean(axis=0).sum())
        # parallel must carry at least as much light as crossed; below 1 the analyser (or the
        # light's polarizer) is not where the read-backs say
        ratio = float(stack[par].mean() / max(float(stack[cro].mean()), 1e-12)) \
            if method == "parallel/crossed" else float("nan")
        out.append(PolarizationPose(tuple(steps), angles, method, float(specular.sum() / max(2 * total, 1e-12)),
                                    diffuse.mean(axis=(0, 1)), specular.mean(axis=(0, 1)), ratio, misfit))
        used += steps
        if example is None:
            example = {"diffuse": diffuse, "specular": specular, "steps": steps, "method": method}
    if not out:
        raise _Skip("no pose captured at analyser angles that separate (0/90 deg, or 3+ angles)")
    rep.plots["polarization"] = example
    figures = {"poses": len(out), "method": out[0].method,
               "specular_pct": round(100 * float(np.mean([r.specular_fraction for r in out])), 2)}
    return StageOutput(PolarizationRecord(tuple(out)), figures, ctx.frame_ids(used), params={"light_polarizer_deg": 0.0})


def _stage_gray_card(ctx: _Context, rep: CalibrationReport) -> StageOutput:
    steps = ctx.merged_steps("gray_card")
    albedo = ctx.targets.gray_card_albedo
    model = ctx.positioner
    rows = []
    for s in steps:
        name = f"frame {ctx.frames[s][0].id} (step {s})"
        img = ctx.hdr[s]
        card = find_gray_card(img, frame=name)
        rgb = np.median(img[card], axis=0)
        light = ctx.steps[s].light
        d, brdf_scale = None, None
        if model is not None and light is not None and light.xyz_mm is None:
            # absolute scale: the card stands at the lab origin facing the light (assumed)
            d = float(np.linalg.norm(model.position(light.azimuth_deg, light.elevation_deg)))
            brdf_scale = np.array([gray_card_scale(img[card][:, c], reflectance=albedo,
                                                   light_distance_mm=d).scale for c in range(3)])
        rows.append(CardReading(s, rgb, int(card.sum()), albedo / rgb,
                                float(np.std(img[card].mean(axis=1)) / max(float(rgb.mean()), 1e-12)),
                                d, brdf_scale))
    scale = np.median(np.array([r.relative_scale_rgb for r in rows]), axis=0)
    result = GrayCardRecord(albedo, tuple(rows), scale)
    figures = {"cards": len(rows), "relative_scale_rgb": [float(f"{v:.4g}") for v in scale],
               "spread_pct": round(100 * max(r.relative_spread for r in rows), 2),
               "absolute": all(r.brdf_scale_rgb is not None for r in rows)}
    return StageOutput(result, figures, ctx.frame_ids(steps), params={"albedo": albedo})


def _probe_image(ctx: _Context, step: int) -> np.ndarray:
    """A mirror-probe step's radiance demosaiced for light sources smaller than a photosite
    (:func:`calibration.raw.demosaic_smooth_hue`): the ball squeezes the room's windows into
    single photosites, which the session's bilinear demosaic turns green. The mosaic is the
    merged image's own channel at each photosite (bilinear interpolation keeps it)."""
    channels = ctx.images.raw(ctx.frames[step][0]).channels
    mosaic = np.take_along_axis(ctx.hdr[step], channels[..., None].astype(np.intp), axis=2)[..., 0]
    return demosaic_smooth_hue(mosaic, channels)


def _stage_mirror_probe(ctx: _Context, rep: CalibrationReport) -> StageOutput:
    steps = ctx.merged_steps("mirror_probe")
    # the room is fixed in the lab: map it in the lab frame when the turntable gave one
    R, frame = (ctx.lab.R, "lab") if ctx.lab is not None else (np.eye(3), "camera")
    images = {s: _probe_image(ctx, s) for s in steps}
    spheres = {s: find_mirror_sphere(images[s], frame=f"frame {ctx.frames[s][0].id} (step {s})") for s in steps}
    height = max(MIN_PROBE_HEIGHT, int(np.ceil(max(sp.radius_px for sp in spheres.values()))))
    probes = [mirror_sphere_to_latlong(images[s], sp.center_px, sp.radius_px, R, height=height)
              for s, sp in spheres.items()]
    rows = [ProbeView(s, sp.center_px, sp.radius_px) for s, sp in spheres.items()]
    probe = merge_probes(probes)
    buf = io.BytesIO()
    np.savez_compressed(buf, env=probe.env, weight=probe.weight, mask=probe.valid)
    rep.plots["probe"] = {"env": probe.env, "weight": probe.weight}
    result = EnvironmentRecord(frame, height, tuple(rows), float(probe.valid.mean()),
                               probe.env[probe.valid].mean(axis=0))
    figures = {"views": len(rows), "frame": frame, "valid_pct": round(100 * float(probe.valid.mean()), 1),
               "sphere_radius_px": round(rows[0].radius_px, 1)}
    artifacts = {"environment.npz": buf.getvalue()}
    return StageOutput(result, figures, ctx.frame_ids(steps), artifacts, {"height": height})


_RUNNERS: dict[str, Callable[[_Context, CalibrationReport], StageOutput]] = {
    "dark": _stage_dark, "hdr": _stage_hdr, "intrinsics": _stage_intrinsics,
    "turntable": _stage_turntable, "lights": _stage_lights, "positioner": _stage_positioner,
    "polarization": _stage_polarization, "gray_card": _stage_gray_card,
    "mirror_probe": _stage_mirror_probe,
}

def _run_stage(ctx: _Context, rep: CalibrationReport, name: str, wanted: bool) -> StageResult:
    if not wanted:
        return StageResult(name, "skipped", "not requested")
    # bad data fails the stage (the error names the frame); anything else is a bug and raises
    try:
        out = _RUNNERS[name](ctx, rep)
    except _Skip as skip:
        return StageResult(name, "skipped", str(skip))
    except (CalibrationError, StageDataError, FrameDataError, StoreError) as exc:
        return StageResult(name, "failed", f"{type(exc).__name__}: {exc}")
    cid = ctx.store.add_calibration(ctx.info.id, out.result.KIND, result=out.result.to_json(), params=out.params,
                                    input_frames=out.input_frames, artifacts=out.artifacts)
    # a stage that lost some inputs is stored for the rest but reported failed
    return StageResult(name, "failed" if out.errors else "ok", "; ".join(out.errors), out.figures, cid)


def calibrate_session(store: Store, session_name: str, *,
                      progress: ProgressSink | None = None,
                      targets: LabTargets | None = None, stages: tuple[str, ...] = STAGES,
                      measurement_hdr: bool = True) -> CalibrationReport:
    """Run every calibration the session's captures allow and store the results.

    Parameters
    ----------
    store : Store
        The session store (results are added with :meth:`Store.add_calibration`).
    session_name : str
    progress : callable(Progress), optional
        Receives ``Progress("calibration", i, total, part=stage)`` before each stage (``i``
        0-based of ``total`` stages), with ``part_done`` / ``part_total`` steps merged during the
        long hdr stage, and ``Progress("calibration", total, total)`` at the end.
    targets : LabTargets, optional
        Physical targets (board geometry, sphere radius, card albedo), usually
        ``SessionLab.targets`` (:func:`capture.lab_resolver.resolve_lab`); None: resolved here
        (the built-in simulated lab's for a session recorded in it, else :class:`TargetsNeeded`).
    stages : tuple of str
        Subset of :data:`STAGES` to run (later stages skip when an earlier one they need is
        left out).
    measurement_hdr : bool
        Also merge (and report) every measurement step's bracket: each step's frames decoded,
        dark-subtracted, merged and demosaiced (:meth:`SessionImages.merge`), so False keeps
        the hdr stage to the calibration steps for big sessions (the polarization check still
        merges the few poses it looks at; ``gonio process`` passes False).

    Returns
    -------
    CalibrationReport
        One :class:`StageResult` per stage: ``ok`` (stored), ``skipped`` (reason) or ``failed``
        (error naming the frame).

    Raises
    ------
    SessionNotFound
        No session of that name in the store.
    NothingToCalibrate
        The session has no stored frames, or none of a calibration kind.
    TargetsNeeded
        ``targets`` is None and the session was not recorded on the simulated lab.
    ValueError
        ``stages`` names an unknown stage.
    """
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
        raise ValueError(f"stages: unknown {unknown}; known: {', '.join(STAGES)}")
    ctx = _Context(store, session_name, targets, measurement_hdr)
    if not ctx.frames:
        raise NothingToCalibrate(f"session {session_name!r} has no stored frames yet; capture it first "
                                 f"(gonio capture run / resume)")
    if not any(ctx.steps_of(kind) for kind in CALIBRATION_STEP_KINDS):
        kinds = sorted({d.kind for i, d in ctx.steps.items() if ctx.frames.get(i)})
        raise NothingToCalibrate(
            f"session {session_name!r} has no calibration captures (its stored steps are "
            f"{', '.join(kinds)}); add [[calibration]] captures of kind "
            f"{', '.join(CALIBRATION_STEP_KINDS)} to the plan")
    if ctx.targets is None:
        ctx.targets = resolve_lab(store, session_name).require_targets()
    digest = frames_digest(store, ctx.info.id)   # of the frames this run reads
    rep = CalibrationReport(session=session_name)
    total = len(STAGES)
    threads = cv2.getNumThreads()
    # OpenCV's thread pool splits its solvers' sums in a varying order: re-calibrating one session
    # moved the figures by up to 0.15 % (benchmarks/reproducibility.py); on one thread the same
    # frames give the same bits, for ~1 s more on the quick demo (about 1 % of gonio process)
    cv2.setNumThreads(1)
    try:
        for i, name in enumerate(STAGES):
            crash.point(f"calibration {name}")   # stage boundaries of the crash test
            if progress is not None:
                progress(Progress("calibration", i, total, part=name))
                ctx.tick = lambda done, n, i=i, name=name: progress(
                    Progress("calibration", i, total, part=name, part_done=done, part_total=n))
            started = time.perf_counter()
            rep.stages.append(_run_stage(ctx, rep, name, name in stages))
            rep.stages[-1].seconds = round(time.perf_counter() - started, 3)
    finally:
        cv2.setNumThreads(threads)
    if set(stages) == set(STAGES):   # a whole calibration: gonio process may reuse it as it is
        record_run(store, ctx.info.id, CalibrationRun(tuple(StageRun(st.stage, st.status, st.reason, st.calibration_id)
                                                           for st in rep.stages), digest))
    if progress is not None:
        progress(Progress("calibration", total, total))
    return rep
