"""A stored, calibrated session -> what the reconstruction methods take (once, for all of them).

:func:`read_calibration` gathers the session's stored calibration results (``Store.results``,
written by :func:`capture.pipeline.calibrate.calibrate_session`) into a :class:`SessionCalibration`: the
camera (intrinsics + lab -> camera pose), the turntable's angle model, a calibrated light
position for every step, the lamp's radiant intensity in HDR units (from the gray card) and the
mirror-probe environment map. :func:`session_inputs` then turns every measurement pose into a
:class:`reconstruct.lumitexels.View`:

- HDR radiance per step from the raw bracket (:mod:`capture.pipeline.images` with the master
  darks the dark stage stored), in DN/s of camera RGB;
- the object pose ``Rz(angle_scale * reading)`` about the lab's +z (the object frame is the lab
  frame at turntable reading 0, which is also the frame of the simulated lab's meshes);
- the light position from the positioner model (or the lights stage for the same commanded
  light), the camera from the intrinsics;
- parallel (analyser at the lamp polarizer's 0 deg) and crossed (90 deg) captures of one pose
  merged into one view whose ``radiance`` is their sum (what an unpolarised analyser sees),
  with ``diffuse = 2 crossed`` and ``specular = parallel - crossed``
  (:func:`calibration.polarization.separate_parallel_crossed`).

Measurement steps whose light the plan marks ``held_out`` become :attr:`ProcessInputs.held_out`
views: captured like the rest, never given to a fitter, used to score renders of the recovered
models. A ``passive_sphere`` capture (the lab's homogeneous sample sphere, lamp off, room lit)
or else a ``passive`` capture (the object) becomes a :class:`PassiveInput`: the image, the
normals and view directions per pixel (from the sphere's stated radius and centre, or from the
mesh), and the environment map, all in the lab frame.

Frames and units: the lab frame of :mod:`capture.pipeline.calibrate` (origin on the turntable axis at the
platter, +z up, +x towards the camera), mm; radiance in DN/s; light intensity in DN/s * mm^2 per
unit of ``f_r cos`` (so lumitexel reflectance is ``f_r cos theta_i``, 1/sr, when the gray card
gave the absolute scale).
"""
from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Callable, Sequence, TypeVar

import cv2
import numpy as np
import trimesh

from calibration.polarization import separate_parallel_crossed
from reconstruct.camera import CameraModel
from reconstruct.envmap import EnvironmentMap
from reconstruct.lumitexels import Lumitexels, View, assemble_lumitexels, footprint_normal_spread
from reconstruct.raycast import Mesh, Sphere, Surface, first_hits
from rig import LightTarget

from ..lab import GrayCardPose, LabTargets
from ..plan import Step
from ..store import ResultRecord, Store
from .calibration_record import stored_calibration
from .images import FrameDataError, SessionImages, StepImage
from .stage_records import (DarkRecord, EnvironmentRecord, GrayCardRecord, IntrinsicsRecord, LightsRecord,
                            PositionerRecord, RecordFormatError, StageRecord, TurntableRecord, read_record)

__all__ = ["ProcessError", "MissingCalibration", "GrayCardPose", "SessionCalibration",
           "PassiveInput", "SampleSphereGeometry", "sample_sphere_of", "sphere_passive_input", "ProcessInputs",
           "read_calibration", "session_images", "session_inputs",
           "PoseSpec", "ViewPlan", "view_plan", "pose_view", "merge_pose", "plan_inputs", "passive_input", "picture_radiance",
           "lumitexels_with_held_out", "split_samples", "select_samples", "object_pose"]

R = TypeVar("R", bound=StageRecord)


class ProcessError(ValueError):
    """The session cannot give reconstruction inputs; the message says what is missing."""


class MissingCalibration(ProcessError):
    """A calibration stage the inputs need has no stored result (run ``gonio calibrate``)."""


@dataclass(frozen=True)
class SessionCalibration:
    """The stored calibration of a session, in the form the reconstruction inputs need.

    Attributes
    ----------
    camera : CameraModel
        Calibrated intrinsics and distortion; pose lab -> camera (R, t mm).
    angle_scale : float
        Platter angle per turntable reading (the turntable fit's angle model; the object frame is
        the lab frame at reading 0, so the fit's offset drops out).
    lights_mm : dict of int -> ndarray of shape (3,)
        Calibrated light position per step index, lab frame, mm.
    light_source : str
        ``positioner`` (arm model: every step) or ``lights`` (per commanded light, from the
        spheres steps).
    light_intensity : ndarray of shape (3,)
        Lamp radiant intensity per camera channel in HDR units (DN/s * mm^2 per unit f_r cos).
    absolute : bool
        The intensity comes from the gray card (lumitexel reflectance is f_r cos theta_i in
        1/sr); False: relative units (intensity 1).
    environment : EnvironmentMap or None
        Mirror-probe lat-long map in the lab frame, DN/s (None: no probe calibration).
    environment_weight : ndarray of shape (He, We) or None
        The probe's per-texel confidence (0 in the blind cone behind the sphere).
    ids : dict of str -> int
        Stored calibration result id per kind (provenance of everything computed from this).
    """

    camera: CameraModel
    angle_scale: float
    lights_mm: dict[int, np.ndarray]
    light_source: str
    light_intensity: np.ndarray
    absolute: bool
    environment: EnvironmentMap | None
    environment_weight: np.ndarray | None
    ids: dict[str, int]

    def object_pose(self, reading_deg: float) -> np.ndarray:
        """Object -> lab 4x4 at turntable ``reading_deg``."""
        return object_pose(self.angle_scale * reading_deg)


def object_pose(angle_deg: float) -> np.ndarray:
    """4x4 rotation by ``angle_deg`` about the lab's +z (counter-clockwise seen from above)."""
    a = np.radians(angle_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


def _latest(store: Store, session_id: int) -> tuple[dict[str, ResultRecord], dict[str, str]]:
    """The stored calibration results by kind, and why each stage without one has none: those a
    complete calibration lists (:mod:`capture.pipeline.calibration_record`), else the newest of
    each kind (a session calibrated stage by stage)."""
    state = stored_calibration(store, session_id)
    if state.complete:
        return state.results, {s.stage: f"{s.status}: {s.reason}" for s in state.stages if not s.calibration_id}
    return {r.kind: r for r in store.results(session_id, "calibration")}, {}


def _need(stored: dict[str, ResultRecord], reasons: dict[str, str], record: type[R], why: str) -> R:
    """The stored result of ``record``'s stage, read; :class:`MissingCalibration` saying why not."""
    if record.KIND not in stored:
        stage = record.STAGE
        if stage in reasons:   # the calibration ran whole: say why that stage stored nothing
            raise MissingCalibration(f"no {stage} calibration ({why}): the session's calibration "
                                     f"{reasons[stage]}")
        raise MissingCalibration(f"no stored {stage} calibration ({why}); run `gonio calibrate` on the "
                                 "session and check that stage")
    return _read(stored[record.KIND])


def _read(result: ResultRecord):
    try:
        return read_record(result)
    except RecordFormatError as exc:
        raise ProcessError(f"{exc}; calibrate the session again (gonio calibrate, or gonio process "
                           "--force)") from None


def read_calibration(store: Store, session: str, *, gray_card: GrayCardPose | None = None,
                     probe_reflectance: float = 1.0) -> SessionCalibration:
    """Collect the session's stored calibration into a :class:`SessionCalibration`.

    ``gray_card`` is the card's pose (for the lamp's intensity); ``probe_reflectance`` the probe
    ball's mirror reflectance, divided out of the environment map (a chrome ball returns ~65 %:
    without it a passive BRDF comes out 1/0.65 too bright).

    Raises
    ------
    MissingCalibration
        The intrinsics, turntable or light calibration is not stored (names the stage).
    ProcessError
        A stored result does not read as its stage's record (names the result and the key).
    """
    info = store.session(session)
    res, reasons = _latest(store, info.id)
    intr = _need(res, reasons, IntrinsicsRecord, "the camera matrix")
    tt = _need(res, reasons, TurntableRecord, "the lab frame and the object's pose per turntable angle")
    w, h = intr.image_size
    camera = CameraModel(K=intr.K, width=int(w), height=int(h), dist=intr.dist,
                         R=tt.lab_to_camera.R, t=tt.lab_to_camera.t_mm)
    steps = {s.index: s.step for s in store.steps(info.id)}
    lights, source = _step_lights(res, reasons, steps)
    ids = {k: r.id for k, r in res.items()}
    gray = _read(res[GrayCardRecord.KIND]) if GrayCardRecord.KIND in res else None
    intensity, absolute = _light_intensity(gray, steps, lights, tt.angle_scale, gray_card)
    env, weight = None, None
    probe = res.get(EnvironmentRecord.KIND)
    if probe is not None and "environment.npz" in probe.artifacts:
        with np.load(io.BytesIO(store.read_object(probe.artifacts["environment.npz"]))) as z:
            if not 0 < probe_reflectance <= 1:
                raise ValueError(f"probe_reflectance must be in (0, 1], got {probe_reflectance!r}")
            env = EnvironmentMap(np.maximum(z["env"], 0.0) / probe_reflectance)
            weight = np.asarray(z["weight"])
    return SessionCalibration(camera=camera, angle_scale=tt.angle_scale, lights_mm=lights,
                              light_source=source, light_intensity=intensity, absolute=absolute,
                              environment=env, environment_weight=weight, ids=ids)


def _light_key(light: LightTarget | None) -> tuple | None:
    """Commanded lights equal to 1/1000 of a degree or mm are one light."""
    if light is None:
        return None
    if light.xyz_mm is not None:
        return ("xyz", *(round(float(v), 3) for v in light.xyz_mm))
    return round(float(light.azimuth_deg), 3), round(float(light.elevation_deg), 3), light.distance_mm


def _step_lights(res: dict, reasons: dict[str, str], steps: dict[int, Step]) -> tuple[dict[int, np.ndarray], str]:
    """A light position (lab, mm) for every step with a light: from the positioner model when it
    was fitted, else from the lights stage's measurement at the same commanded light."""
    if PositionerRecord.KIND in res:
        model: PositionerRecord = _read(res[PositionerRecord.KIND])
        return {r.step: r.position_lab_mm for r in model.step_lights}, "positioner"
    located = _need(res, reasons, LightsRecord, "where the lamp was for each capture")
    by_key = {}
    for r in located.lights:
        if r.position_lab_mm is not None and _light_key(r.commanded) is not None:
            by_key.setdefault(_light_key(r.commanded), []).append(r.position_lab_mm)
    out = {i: np.mean(by_key[_light_key(d.light)], axis=0) for i, d in steps.items()
           if _light_key(d.light) in by_key}
    return out, "lights"


def _light_intensity(gray: GrayCardRecord | None, steps: dict, lights: dict, angle_scale: float,
                     card: GrayCardPose | None) -> tuple[np.ndarray, bool]:
    """Lamp intensity per channel (DN/s mm^2 per unit f_r cos) from the gray card: a card of albedo
    rho reads ``M = (rho / pi) I cos_i / d^2``, halved when an analyser was in front of the lens
    (the card depolarises: any analyser passes half its light)."""
    if gray is None:
        return np.ones(3), False
    albedo = gray.albedo
    estimates = []
    for row in gray.cards:
        s = row.step
        analyser = 2.0 if steps[s].polarizer_deg is not None else 1.0
        M = row.value_rgb * analyser
        if card is not None and s in lights:
            reading = steps[s].turntable_deg or 0.0
            T = object_pose(angle_scale * reading)
            c = T[:3, :3] @ np.asarray(card.centre_mm, float)
            n = T[:3, :3] @ np.asarray(card.normal, float)
            to_l = lights[s] - c
            d = float(np.linalg.norm(to_l))
            cos = float(n @ to_l) / d
            if cos > 0.05:
                estimates.append(M * np.pi * d ** 2 / (albedo * cos))
        elif row.brdf_scale_rgb is not None:
            estimates.append(analyser / row.brdf_scale_rgb)
    if not estimates:
        return np.ones(3), False
    return np.median(np.array(estimates), axis=0), True


# -- the inputs of all methods -----------------------------------------------------------------
@dataclass(frozen=True)
class SampleSphereGeometry:
    """The homogeneous sample sphere of a ``passive_sphere`` capture as the lab states it: its
    ``radius_mm`` (measured with calipers) and ``centre_mm`` (3,) on its stand, lab frame, mm.

    The centre is the lab's fixture pose, not found in the image: the probe's circle detection
    (:func:`calibration.spheres.find_mirror_sphere`) locks onto the room's edges behind a glossy
    sample (on the demo's 320 x 240 image it found a circle 105 px from the ball), and the stand
    at the platter's centre is as well known as the lab frame the turntable calibration gives."""

    radius_mm: float
    centre_mm: np.ndarray


def sample_sphere_of(targets: LabTargets | None) -> SampleSphereGeometry | None:
    """The sample sphere the lab's targets state (None: none stated)."""
    if targets is None or targets.sample_sphere_radius_mm is None:
        return None
    return SampleSphereGeometry(float(targets.sample_sphere_radius_mm),
                                np.asarray(targets.sample_sphere_centre_mm, float))


@dataclass
class PassiveInput:
    """One image lit by the room (lamp off), ready for passive reflectometry: of the lab's
    homogeneous sample sphere (``sample_sphere`` its geometry) or, without one, of the object.

    ``image`` (H, W, 3) DN/s; ``normals`` (H, W, 3) unit, lab frame (zero outside ``mask``);
    ``mask`` (H, W) bool: the surface, unclipped; ``view_dirs`` (H, W, 3) unit, surface -> camera,
    lab frame; ``environment`` the probe map (lab frame, DN/s) and its ``weight``."""

    step: int
    image: np.ndarray
    normals: np.ndarray
    mask: np.ndarray
    view_dirs: np.ndarray
    environment: EnvironmentMap
    environment_weight: np.ndarray | None
    frame_ids: list[int]
    sample_sphere: SampleSphereGeometry | None = None


@dataclass
class ProcessInputs:
    """Everything the methods take, from one session.

    Attributes
    ----------
    calibration : SessionCalibration
    views, held_out : list of View
        Training and held-out measurement views (lab frame; ``radiance`` DN/s; polarization-
        separated ``diffuse`` / ``specular`` when the pose was captured parallel and crossed).
    view_steps, held_out_steps : list of tuple of int
        The step indices each view was made from.
    view_frames : list of int
        Every frame id the views were made from (provenance).
    passive : PassiveInput or None
    separated : bool
        Every view carries a diffuse / specular split.
    notes : list of str
        What was dropped or assumed, for the report.
    """

    calibration: SessionCalibration
    views: list[View]
    held_out: list[View]
    view_steps: list[tuple[int, ...]]
    held_out_steps: list[tuple[int, ...]]
    view_frames: list[int]
    passive: PassiveInput | None = None
    separated: bool = False
    notes: list[str] = field(default_factory=list)


def _analyser(angle: float | None) -> str | None:
    """``parallel`` / ``crossed`` relative to the lamp's polarizer at 0 deg, None otherwise."""
    if angle is None:
        return None
    a = float(angle) % 180.0
    if min(a, 180.0 - a) < 1.0:
        return "parallel"
    if abs(a - 90.0) < 1.0:
        return "crossed"
    return None


@dataclass(frozen=True)
class PoseSpec:
    """One measurement pose (turntable reading x light) before any image is read: its ``steps``
    (one per analyser state), which of them make the view (``used``: indices, parallel then
    crossed when both were captured), its calibrated light (lab, mm), whether it is held out and
    the frames of the used steps."""

    reading: float
    steps_all: tuple[int, ...]
    used: tuple[int, ...]
    light_mm: np.ndarray
    held_out: bool
    frame_ids: tuple[int, ...]

    @property
    def separated(self) -> bool:
        return len(self.used) == 2

    @property
    def steps(self) -> tuple[int, ...]:
        return tuple(self.steps_all[i] for i in self.used)


@dataclass(frozen=True)
class ViewPlan:
    """What the inputs are made of, before any image is read: the measurement ``poses`` in
    capture order and the ``passive`` step (None: none captured, or no mesh / probe map, with the
    reason in ``notes``), a ``passive_sphere`` step when there is one (then ``sample_sphere`` is
    its geometry), else a ``passive`` one (the object)."""

    poses: tuple[PoseSpec, ...]
    passive: int | None
    notes: tuple[str, ...]
    sample_sphere: SampleSphereGeometry | None = None

    @property
    def ordered(self) -> list[PoseSpec]:
        """Training poses then held-out ones: the view order of the lumitexels."""
        return [p for p in self.poses if not p.held_out] + [p for p in self.poses if p.held_out]


def view_plan(images: SessionImages, session: str, cal: SessionCalibration, *,
              mesh: trimesh.Trimesh | None = None, sample_sphere: SampleSphereGeometry | None = None) -> ViewPlan:
    """The session's measurement poses and passive step (no image is read): the sample sphere's
    ``passive_sphere`` capture when the session has one and the lab states the sphere
    (``sample_sphere``), else the object's ``passive`` capture.

    Raises
    ------
    ProcessError
        No measurement steps, a measurement step without a calibrated light, or every light
        held out.
    """
    frames = images
    measure = [i for i, d in sorted(frames.steps.items()) if d.kind == "measure" and frames.by_step.get(i)]
    passive = [i for i, d in sorted(frames.steps.items()) if d.kind == "passive" and frames.by_step.get(i)]
    on_sphere = [i for i, d in sorted(frames.steps.items()) if d.kind == "passive_sphere" and frames.by_step.get(i)]
    if not measure:
        raise ProcessError(f"session {session!r} has no stored measurement steps")
    missing = [i for i in measure if i not in cal.lights_mm]
    if missing:
        raise ProcessError(f"no calibrated light for measurement step(s) {missing[:5]} (commanded "
                           f"{frames.steps[missing[0]].light}): the {cal.light_source} calibration "
                           "does not cover them; add spheres captures at those lights")
    # poses: (turntable, light) -> the steps at each analyser angle
    grouped: dict[tuple, list[int]] = {}
    for i in measure:
        d = frames.steps[i]
        grouped.setdefault((d.turntable_deg, _light_key(d.light)), []).append(i)
    poses = []
    for (reading, _), steps in grouped.items():
        by = {_analyser(frames.steps[s].polarizer_deg): k for k, s in enumerate(steps)}
        if "parallel" in by and "crossed" in by:
            used = (by["parallel"], by["crossed"])
        else:  # one analyser state (or none): a plain view
            used = (next((by[a] for a in (None, "parallel") if a in by), 0),)
        first = steps[used[0]]
        poses.append(PoseSpec(reading or 0.0, tuple(steps), used, cal.lights_mm[first],
                              frames.steps[first].held_out,
                              tuple(f.id for i in used for f in frames.by_step[steps[i]])))
    if all(p.held_out for p in poses):
        raise ProcessError(f"session {session!r}: every measurement light is held out; nothing to fit")
    notes, p_step, sphere = [], None, None
    if on_sphere and sample_sphere is None:
        notes.append("passive_sphere capture present but the lab states no sample sphere "
                     "(sample_sphere_radius_mm and sample_sphere_centre_mm in --targets): not used")
    if (passive or (on_sphere and sample_sphere is not None)) and cal.environment is None:
        notes.append("passive capture present but no mirror-probe environment map is stored: "
                     "passive reflectometry skipped")
    elif on_sphere and sample_sphere is not None:
        p_step, sphere = on_sphere[0], sample_sphere
    elif passive:
        if mesh is None:
            notes.append("passive capture present but no mesh: passive reflectometry skipped")
        else:
            p_step = passive[0]
    return ViewPlan(tuple(poses), p_step, tuple(notes), sphere)


def pose_view(pose: PoseSpec, images: Sequence[StepImage], cal: SessionCalibration) -> View:
    """The view of one pose from its merged steps (``images`` in ``pose.steps_all``' order):
    parallel + crossed summed, with the polarization split, or the one plain image."""
    valid = np.logical_and.reduce([im.valid for im in images])
    if pose.separated:
        par, cro = (images[i] for i in pose.used)
        sep = separate_parallel_crossed(par.radiance, cro.radiance)
        radiance, diffuse, specular = par.radiance + cro.radiance, sep.diffuse, sep.specular
    else:
        radiance, diffuse, specular = images[pose.used[0]].radiance, None, None
    return View(camera=cal.camera, radiance=radiance, light_position=pose.light_mm,
                light_intensity=cal.light_intensity, object_to_world=cal.object_pose(pose.reading),
                valid=valid, diffuse=diffuse, specular=specular)


def merge_pose(images: SessionImages, pose: PoseSpec, cal: SessionCalibration) -> View:
    """One pose's view, its steps merged from the raw frames."""
    return pose_view(pose, [_merge(images, s) for s in pose.steps_all], cal)


def session_inputs(store: Store, session: str, *, calibration: SessionCalibration | None = None,
                   mesh: trimesh.Trimesh | None = None, sample_sphere: SampleSphereGeometry | None = None,
                   progress: Callable[[int, int], None] | None = None) -> ProcessInputs:
    """Turn a calibrated session's measurement (and passive) steps into method inputs, every
    view's images in memory (``gonio process`` streams instead:
    :mod:`capture.pipeline.lumitexel_arrays`).

    Parameters
    ----------
    store, session
        The session (calibrated: see :func:`read_calibration`).
    calibration : SessionCalibration, optional
        Default: :func:`read_calibration` (no gray-card pose).
    mesh : trimesh.Trimesh, optional
        The object's mesh (object frame, mm): needed for the object's passive input's normals.
    sample_sphere : SampleSphereGeometry, optional
        The lab's sample sphere (:func:`sample_sphere_of`): a ``passive_sphere`` capture's geometry.
    progress : callable(done, total), optional
        After each merged pose.

    Raises
    ------
    ProcessError
        No measurement steps, or a measurement step without a calibrated light.
    """
    cal = read_calibration(store, session) if calibration is None else calibration
    images = session_images(store, session)
    plan = view_plan(images, session, cal, mesh=mesh, sample_sphere=sample_sphere)
    return plan_inputs(images, plan, cal, mesh, images_of=range(len(plan.poses)), progress=progress)


def plan_inputs(images: SessionImages, plan: ViewPlan, cal: SessionCalibration, mesh: trimesh.Trimesh | None, *,
                images_of: Sequence[int] = (), passive: bool = True, picture_only: bool = False,
                progress: Callable[[int, int], None] | None = None) -> ProcessInputs:
    """The method inputs of ``plan``: the views ``images_of`` (indices in
    :attr:`ViewPlan.ordered`) merged from their raw frames, the others geometry only (camera,
    light, pose; ``radiance`` None: a streamed run, whose samples
    :mod:`capture.pipeline.lumitexel_arrays` holds, merges just the view the report draws); the
    passive input merged from its one image (:func:`passive_input`; ``passive`` False: left
    None, for a run that makes it when passive reflectometry runs). ``picture_only``: a merged
    view keeps only its radiance, as float32 (what the report's picture draws: a quarter of the
    view's images). ``progress(done, total)`` after each merged view."""
    views, held, vsteps, hsteps, frame_ids = [], [], [], [], []
    wanted = set(images_of)
    for k, pose in enumerate(plan.ordered):
        if k in wanted and not picture_only:
            view = merge_pose(images, pose, cal)
        else:
            view = View(camera=cal.camera, radiance=picture_radiance(images, pose) if k in wanted else None,
                        light_position=pose.light_mm, light_intensity=cal.light_intensity,
                        object_to_world=cal.object_pose(pose.reading))
        if k in wanted and progress is not None:
            progress(len(views) + len(held) + 1, len(plan.poses))
        (held if pose.held_out else views).append(view)
        (hsteps if pose.held_out else vsteps).append(pose.steps)
    for pose in plan.poses:
        frame_ids += pose.frame_ids
    return ProcessInputs(calibration=cal, views=views, held_out=held, view_steps=vsteps, held_out_steps=hsteps,
                         view_frames=frame_ids, passive=passive_input(images, plan, cal, mesh) if passive else None,
                         separated=all(p.separated for p in plan.poses), notes=list(plan.notes))


def picture_radiance(images: SessionImages, pose: PoseSpec) -> np.ndarray:
    """The radiance (H, W, 3) float32, DN/s, of one pose as :func:`merge_pose` makes it (parallel
    + crossed), its steps merged one at a time and nothing else kept: the same values, cast."""
    radiance = None
    for i in pose.used:
        r = _merge(images, pose.steps_all[i]).radiance
        radiance = r if radiance is None else radiance + r
    return np.asarray(radiance, np.float32)


def passive_input(images: SessionImages, plan: ViewPlan, cal: SessionCalibration,
                  mesh: trimesh.Trimesh | None) -> PassiveInput | None:
    """The passive input of ``plan`` merged from its one image (None: the plan has none)."""
    if plan.passive is None:
        return None
    if plan.sample_sphere is not None:
        return sphere_passive_input(_merge(images, plan.passive), cal, plan.sample_sphere)
    return _passive_input(_merge(images, plan.passive), cal, mesh)


def session_images(store: Store, session: str) -> SessionImages:
    """The session's images with the master darks and read noise its dark calibration stored
    (none stored: black level only, 1 DN read noise)."""
    images = SessionImages(store, session)
    stored = _latest(store, images.info.id)[0].get(DarkRecord.KIND)
    if stored is not None:
        dark: DarkRecord = _read(stored)
        images.use_stored_darks([row.exposure_s for row in dark.darks], stored.artifacts, dark.read_noise_dn)
    return images


def _merge(images: SessionImages, step: int) -> StepImage:
    try:
        return images.merge(step)
    except FrameDataError as exc:
        raise ProcessError(str(exc)) from None


def _passive_input(im: StepImage, cal: SessionCalibration, mesh: trimesh.Trimesh) -> PassiveInput:
    """Per-pixel lab-frame normals and view directions of the object in the passive image."""
    cam = cal.camera
    pose = cal.object_pose(im.spec.turntable_deg or 0.0)
    surface = Mesh(mesh, transform=pose)
    o, d = cam.pixel_rays()
    hits = first_hits([surface], o, d)
    H, W = cam.height, cam.width
    normals = np.zeros((H * W, 3))
    normals[hits.mask] = hits.normal[hits.mask]
    view = np.zeros((H * W, 3))
    view[hits.mask] = -d[hits.mask] / np.linalg.norm(d[hits.mask], axis=1, keepdims=True)
    mask = hits.mask.reshape(H, W) & im.valid
    return PassiveInput(step=im.step, image=im.radiance, normals=normals.reshape(H, W, 3), mask=mask,
                        view_dirs=view.reshape(H, W, 3), environment=cal.environment,
                        environment_weight=cal.environment_weight, frame_ids=im.frame_ids)


def sphere_passive_input(im: StepImage, cal: SessionCalibration, sphere: SampleSphereGeometry) -> PassiveInput:
    """Per-pixel lab-frame normals and view directions of the sample sphere in its image: the
    calibrated camera's rays on the stated sphere (fixed in the lab: no turntable pose). The
    mask leaves out the outline's pixels (their footprint mixes the sphere with the room
    behind it) and invalid (clipped) ones."""
    cam = cal.camera
    o, d = cam.pixel_rays()
    hits = first_hits([Sphere(sphere.radius_mm, sphere.centre_mm)], o, d)
    H, W = cam.height, cam.width
    normals = np.zeros((H * W, 3))
    normals[hits.mask] = hits.normal[hits.mask]
    view = np.zeros((H * W, 3))
    view[hits.mask] = -d[hits.mask] / np.linalg.norm(d[hits.mask], axis=1, keepdims=True)
    inside = cv2.erode(hits.mask.reshape(H, W).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    return PassiveInput(step=im.step, image=im.radiance, normals=normals.reshape(H, W, 3), mask=inside & im.valid,
                        view_dirs=view.reshape(H, W, 3), environment=cal.environment,
                        environment_weight=cal.environment_weight, frame_ids=im.frame_ids,
                        sample_sphere=sphere)


def lumitexels_with_held_out(mesh: trimesh.Trimesh | Surface, inputs: ProcessInputs, *,
                             progress: Callable[[int, int], None] | None = None
                             ) -> tuple[Lumitexels, Lumitexels]:
    """Lumitexels of the training views and, on the same texels, the held-out samples.

    Both come from one assembly over every view (so the texels are the same points), then the
    samples are split by view (:func:`split_samples`); texels without a training sample are
    dropped from both. Returns ``(train, held_out)``; ``held_out`` has no samples when the
    plan held no light out.
    """
    views = [*inputs.views, *inputs.held_out]
    # the depth/shadow-edge rejection box: 5 px at 1200 px wide (the assembly's default), at
    # least 3: at 320 x 240 a 5 px box dropped 40 % more samples for the same accuracy
    width = views[0].camera.width
    lt = assemble_lumitexels(mesh, views, reject_filter_px=max(3, int(round(5 * width / 1200)) | 1),
                             progress=progress)
    return split_samples(lt, lt.view >= len(inputs.views))


def split_samples(lt: Lumitexels, held: np.ndarray) -> tuple[Lumitexels, Lumitexels]:
    """Split ``lt``'s samples by the boolean mask ``held`` (S,) into (training, held-out)
    lumitexels over the same texels: those with at least one training sample."""
    held = np.asarray(held, bool)
    if held.shape != (lt.n_samples,):
        raise ValueError(f"held must have shape ({lt.n_samples},), got {held.shape}")
    keep = np.flatnonzero(np.bincount(lt.texel[~held], minlength=lt.n_texels) > 0)
    sub = lt.subset(keep)
    h = held[np.isin(lt.texel, keep)]  # subset keeps the samples' order
    train, held_out = select_samples(sub, ~h), select_samples(sub, h)
    # the footprint spread from the training samples alone, the same for both sets' texels
    train.footprint_spread_deg = held_out.footprint_spread_deg = footprint_normal_spread(train)
    return train, held_out


def select_samples(lt: Lumitexels, mask: np.ndarray) -> Lumitexels:
    """``lt`` with only the samples where ``mask`` (S,) is true; the texels stay as they are."""
    per_sample = {f: (None if getattr(lt, f) is None else getattr(lt, f)[mask])
                  for f in ("texel", "view", "wi", "wo", "reflectance", "weight", "diffuse", "specular")}
    return Lumitexels(position=lt.position, normal=lt.normal, best_view=lt.best_view, pixel=lt.pixel,
                      footprint_spread_deg=lt.footprint_spread_deg, **per_sample)
