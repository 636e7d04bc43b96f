"""A stored, calibrated session -> what the reconstruction methods take (once, for all of them).

:func:`read_calibration` gathers the session's stored calibration results (``Store.results``,
written by :func:`capture.calibrate.calibrate_session`) into a :class:`SessionCalibration`: the
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
models. A ``passive`` capture (lamp off, room lit) becomes a :class:`PassiveInput`: the image,
the object's normals and view directions per pixel from the mesh, and the environment map, all
in the lab frame.

Frames and units: the lab frame of :mod:`capture.pipeline.calibrate` (origin on the turntable axis at the
platter, +z up, +x towards the camera), mm; radiance in DN/s; light intensity in DN/s * mm^2 per
unit of ``f_r cos`` (so lumitexel reflectance is ``f_r cos theta_i``, 1/sr, when the gray card
gave the absolute scale).
"""
from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import trimesh

from calibration.polarization import separate_parallel_crossed
from reconstruct.camera import CameraModel
from reconstruct.envmap import EnvironmentMap
from reconstruct.lumitexels import Lumitexels, View, assemble_lumitexels
from reconstruct.raycast import Mesh, Surface, first_hits

from ..store import ResultRecord, Store
from .images import FrameDataError, SessionImages, StepImage

__all__ = ["ProcessError", "MissingCalibration", "GrayCardPose", "SessionCalibration",
           "PassiveInput", "ProcessInputs", "read_calibration", "session_images", "session_inputs",
           "lumitexels_with_held_out", "split_samples", "select_samples", "object_pose", "load_mesh"]

class ProcessError(ValueError):
    """The session cannot give reconstruction inputs; the message says what is missing."""


class MissingCalibration(ProcessError):
    """A calibration stage the inputs need has no stored result (run ``gonio calibrate``)."""


@dataclass(frozen=True)
class GrayCardPose:
    """Where the gray card stands at turntable reading 0, lab frame, mm (it turns with the
    platter): its centre and unit normal (printed side). With it the lamp's intensity follows from
    the card's exact distance and incidence angle; without it the calibration's own assumption
    (card at the lab origin facing the light) is used."""

    centre_mm: tuple[float, float, float]
    normal: tuple[float, float, float]


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


def _latest(store: Store, session_id: int) -> dict[str, ResultRecord]:
    """The newest stored calibration result of each kind."""
    return {r.kind: r for r in store.results(session_id, "calibration")}


def _need(results: dict[str, ResultRecord], kind: str, stage: str, why: str) -> ResultRecord:
    if kind not in results:
        raise MissingCalibration(f"no stored {stage} calibration ({why}); run `gonio calibrate` on the "
                                 "session and check that stage")
    return results[kind]


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
    """
    info = store.session(session)
    res = _latest(store, info.id)
    intr = _need(res, "intrinsics", "intrinsics", "the camera matrix").result
    tt = _need(res, "turntable", "turntable", "the lab frame and the object's pose per turntable angle").result
    w, h = intr["image_size"]
    lab = tt["lab_to_camera"]
    camera = CameraModel(K=np.array(intr["K"]), width=int(w), height=int(h), dist=np.array(intr["dist"]),
                         R=np.array(lab["R"]), t=np.array(lab["t_mm"]))
    steps = {i: d for i, d, _ in store.steps(info.id)}
    lights, source = _step_lights(res, steps)
    ids = {k: r.id for k, r in res.items()}
    intensity, absolute = _light_intensity(res, steps, lights, tt, gray_card)
    env, weight = None, None
    if "environment_map" in res and "environment.npz" in res["environment_map"].artifacts:
        with np.load(io.BytesIO(store.read_object(res["environment_map"].artifacts["environment.npz"]))) as z:
            if not 0 < probe_reflectance <= 1:
                raise ValueError(f"probe_reflectance must be in (0, 1], got {probe_reflectance!r}")
            env = EnvironmentMap(np.maximum(z["env"], 0.0) / probe_reflectance)
            weight = np.asarray(z["weight"])
    return SessionCalibration(camera=camera, angle_scale=float(tt.get("angle_scale", 1.0)), lights_mm=lights,
                              light_source=source, light_intensity=intensity, absolute=absolute,
                              environment=env, environment_weight=weight, ids=ids)


def _light_key(light: dict | None) -> tuple | None:
    if not light:
        return None
    if "xyz_mm" in light:
        return ("xyz", *(round(float(v), 3) for v in light["xyz_mm"]))
    return (round(float(light["azimuth_deg"]), 3), round(float(light["elevation_deg"]), 3),
            light.get("distance_mm"))


def _step_lights(res: dict, steps: dict[int, dict]) -> tuple[dict[int, np.ndarray], str]:
    """A light position (lab, mm) for every step with a light: from the positioner model when it
    was fitted, else from the lights stage's measurement at the same commanded light."""
    if "positioner_model" in res:
        rows = res["positioner_model"].result["step_lights"]
        return {int(r["step"]): np.asarray(r["position_lab_mm"], float) for r in rows}, "positioner"
    rows = _need(res, "light_positions", "lights", "where the lamp was for each capture").result["lights"]
    by_key = {}
    for r in rows:
        if "position_lab_mm" in r and _light_key(r.get("commanded")) is not None:
            by_key.setdefault(_light_key(r["commanded"]), []).append(np.asarray(r["position_lab_mm"], float))
    out = {i: np.mean(by_key[_light_key(d["light"])], axis=0) for i, d in steps.items()
           if _light_key(d.get("light")) in by_key}
    return out, "lights"


def _light_intensity(res: dict, steps: dict, lights: dict, tt: dict,
                     card: GrayCardPose | None) -> tuple[np.ndarray, bool]:
    """Lamp intensity per channel (DN/s mm^2 per unit f_r cos) from the gray card: a card of albedo
    rho reads ``M = (rho / pi) I cos_i / d^2``, halved when an analyser was in front of the lens
    (the card depolarises: any analyser passes half its light)."""
    gc = res.get("gray_card")
    if gc is None:
        return np.ones(3), False
    r = gc.result
    albedo = float(r["albedo"])
    estimates = []
    for row in r["cards"]:
        s = int(row["step"])
        analyser = 2.0 if steps[s].get("polarizer_deg") is not None else 1.0
        M = np.asarray(row["value_rgb"], float) * analyser
        if card is not None and s in lights:
            reading = steps[s].get("turntable_deg") or 0.0
            T = object_pose(float(tt.get("angle_scale", 1.0)) * reading)
            c = T[:3, :3] @ np.asarray(card.centre_mm, float)
            n = T[:3, :3] @ np.asarray(card.normal, float)
            to_l = lights[s] - c
            d = float(np.linalg.norm(to_l))
            cos = float(n @ to_l) / d
            if cos > 0.05:
                estimates.append(M * np.pi * d ** 2 / (albedo * cos))
        elif "brdf_scale_rgb" in row:
            estimates.append(analyser / np.asarray(row["brdf_scale_rgb"], float))
    if not estimates:
        return np.ones(3), False
    return np.median(np.array(estimates), axis=0), True


# -- the inputs of all methods -----------------------------------------------------------------
@dataclass
class PassiveInput:
    """One image of the object lit by the room (lamp off), ready for passive reflectometry.

    ``image`` (H, W, 3) DN/s; ``normals`` (H, W, 3) unit, lab frame (zero outside ``mask``);
    ``mask`` (H, W) bool: the object, unclipped; ``view_dirs`` (H, W, 3) unit, surface -> camera,
    lab frame; ``environment`` the probe map (lab frame, DN/s) and its ``weight``."""

    step: int
    image: np.ndarray
    normals: np.ndarray
    mask: np.ndarray
    view_dirs: np.ndarray
    environment: EnvironmentMap
    environment_weight: np.ndarray | None
    frame_ids: list[int]


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


def load_mesh(path) -> trimesh.Trimesh:
    """The object's mesh from any file trimesh reads, in the object frame (mm).

    Raises
    ------
    ProcessError
        The file is missing or holds no triangles (names the path).
    """
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except (OSError, ValueError) as exc:
        raise ProcessError(f"--mesh {path}: cannot read a mesh ({exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ProcessError(f"--mesh {path}: holds no triangle mesh")
    return mesh


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


def session_inputs(store: Store, session: str, *, calibration: SessionCalibration | None = None,
                   mesh: trimesh.Trimesh | None = None,
                   progress: Callable[[int, int], None] | None = None) -> ProcessInputs:
    """Turn a calibrated session's measurement (and passive) steps into method inputs.

    Parameters
    ----------
    store, session
        The session (calibrated: see :func:`read_calibration`).
    calibration : SessionCalibration, optional
        Default: :func:`read_calibration` (no gray-card pose).
    mesh : trimesh.Trimesh, optional
        The object's mesh (object frame, mm): needed for the passive input's normals.
    progress : callable(done, total), optional
        After each merged step.

    Raises
    ------
    ProcessError
        No measurement steps, or a measurement step without a calibrated light.
    """
    cal = read_calibration(store, session) if calibration is None else calibration
    frames = session_images(store, session)
    measure = [i for i, d in sorted(frames.steps.items()) if d["kind"] == "measure" and frames.by_step.get(i)]
    passive = [i for i, d in sorted(frames.steps.items()) if d["kind"] == "passive" and frames.by_step.get(i)]
    if not measure:
        raise ProcessError(f"session {session!r} has no stored measurement steps")
    missing = [i for i in measure if i not in cal.lights_mm]
    if missing:
        raise ProcessError(f"no calibrated light for measurement step(s) {missing[:5]} (commanded "
                           f"{frames.steps[missing[0]].get('light')}): the {cal.light_source} calibration "
                           "does not cover them; add spheres captures at those lights")
    # poses: (turntable, light) -> the steps at each analyser angle
    poses: dict[tuple, list[int]] = {}
    for i in measure:
        d = frames.steps[i]
        poses.setdefault((d.get("turntable_deg"), repr(_light_key(d["light"]))), []).append(i)
    total = len(measure) + len(passive)
    done = 0
    views, held, vsteps, hsteps, frame_ids, notes = [], [], [], [], [], []
    separated_all = True
    for (reading, _), steps in poses.items():
        imgs = []
        for s in steps:
            imgs.append(_merge(frames, s))
            done += 1
            if progress is not None:
                progress(done, total)
        by = {_analyser(im.spec.get("polarizer_deg")): im for im in imgs}
        valid = np.logical_and.reduce([im.valid for im in imgs])
        if "parallel" in by and "crossed" in by:
            par, cro = by["parallel"], by["crossed"]
            sep = separate_parallel_crossed(par.radiance, cro.radiance)
            radiance, diffuse, specular = par.radiance + cro.radiance, sep.diffuse, sep.specular
            used = [par, cro]
        else:  # one analyser state (or none): a plain view
            im = by.get(None) or by.get("parallel") or imgs[0]
            radiance, diffuse, specular, used = im.radiance, None, None, [im]
            separated_all = False
        spec = used[0].spec
        view = View(camera=cal.camera, radiance=radiance, light_position=cal.lights_mm[used[0].step],
                    light_intensity=cal.light_intensity, object_to_world=cal.object_pose(reading or 0.0),
                    valid=valid, diffuse=diffuse, specular=specular)
        ids = tuple(im.step for im in used)
        if spec.get("held_out"):
            held.append(view)
            hsteps.append(ids)
        else:
            views.append(view)
            vsteps.append(ids)
        frame_ids += [f for im in used for f in im.frame_ids]
    if not views:
        raise ProcessError(f"session {session!r}: every measurement light is held out; nothing to fit")
    p_input = None
    if passive:
        if cal.environment is None:
            notes.append("passive capture present but no mirror-probe environment map is stored: "
                         "passive reflectometry skipped")
        elif mesh is None:
            notes.append("passive capture present but no mesh: passive reflectometry skipped")
        else:
            im = _merge(frames, passive[0])
            done += 1
            if progress is not None:
                progress(done, total)
            p_input = _passive_input(im, cal, mesh)
    return ProcessInputs(calibration=cal, views=views, held_out=held, view_steps=vsteps, held_out_steps=hsteps,
                         view_frames=frame_ids, passive=p_input, separated=separated_all, notes=notes)


def session_images(store: Store, session: str) -> SessionImages:
    """The session's images with the master darks and read noise its dark calibration stored
    (none stored: black level only, 1 DN read noise)."""
    images = SessionImages(store, session)
    dark = _latest(store, images.info.id).get("dark")
    if dark is not None:
        images.use_stored_darks([row["exposure_s"] for row in dark.result["darks"]],
                                dark.artifacts, dark.result.get("read_noise_dn"))
    return images


def _merge(images: SessionImages, step: int) -> StepImage:
    try:
        return images.merge(step)
    except FrameDataError as exc:
        raise ProcessError(str(exc)) from None


def _passive_input(im: StepImage, cal: SessionCalibration, mesh: trimesh.Trimesh) -> PassiveInput:
    """Per-pixel lab-frame normals and view directions of the object in the passive image."""
    cam = cal.camera
    pose = cal.object_pose(im.spec.get("turntable_deg") or 0.0)
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
    return select_samples(sub, ~h), select_samples(sub, h)


def select_samples(lt: Lumitexels, mask: np.ndarray) -> Lumitexels:
    """``lt`` with only the samples where ``mask`` (S,) is true; the texels stay as they are."""
    per_sample = {f: (None if getattr(lt, f) is None else getattr(lt, f)[mask])
                  for f in ("texel", "view", "wi", "wo", "reflectance", "weight", "diffuse", "specular")}
    return Lumitexels(position=lt.position, normal=lt.normal, best_view=lt.best_view, pixel=lt.pixel,
                      **per_sample)
