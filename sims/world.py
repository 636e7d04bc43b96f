"""The simulated lab's picture: rig state -> scene -> render -> sensor -> DNG.

:class:`SimWorld` holds the fixed rig (ground-truth camera with lens distortion, sensor, light
emitter, polarizer on the light) and what stands on the turntable (a ground-truth object and/or
calibration targets). For each capture it reads the rig state (turntable angle, light position,
analyser angle, exposure settings), builds the :class:`reconstruct.render.Scene`, renders it,
exposes the sensor and writes the DNG the simulated camera returns (:meth:`SimWorld.frame_source`).
:meth:`SimWorld.ground_truth` returns the same frame's noise-free radiance, geometry buffers,
light position and camera so the whole pipeline can be checked against truth.

Frames and units: world = turntable frame (origin on the axis at the platter surface, +z up,
mm); everything on the turntable turns by ``Rz(angle)`` (see :func:`sims.objects.turntable_pose`).
Radiance is in the renderer's units: the point light's radiant intensity over mm^2
(:data:`LIGHT_INTENSITY` gives a white Lambertian surface facing the lamp at 500 mm a radiance of
~0.95, about 40 % of the default sensor's full well at 1/100 s, f/8, ISO 100).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from datetime import datetime, timedelta
from typing import Any, Mapping, Sequence

import numpy as np

from reconstruct.camera import CameraModel
from reconstruct.envmap import EnvironmentMap
from reconstruct.render import PointLight, PrimaryHits, RenderResult, Scene, SceneObject, render
from reconstruct.raycast import Plane
from reconstruct.brdf import Lambertian

from .handheld import handheld_board_pose, handheld_view
from .objects import GroundTruthObject, make_object, turntable_pose
from .sensor import ExpectedRaw, SensorModel
from .targets import (CalibrationSphere, Checkerboard, CharucoTarget, GrayCard, PrintedBoard, SampleSphere,
                      environment, SphereRow)

#: Radiant intensity of the rig's lamp (renderer units per sr), RGB (a slightly warm white).
LIGHT_INTENSITY = (8.0e5, 7.5e5, 6.8e5)
#: The ring flash around the lens: intensity (renderer units / sr) and radius of its emitter, mm.
RING_FLASH_INTENSITY = 2.0e5
RING_FLASH_RADIUS_MM = 40.0
#: What the simulated camera's clock reads at its first capture (see :func:`camera_clock`).
CAMERA_CLOCK_START = datetime(2026, 1, 1)
#: Default light arm: radius about its centre (mm) and the centre (world, mm).
ARM_RADIUS_MM = 500.0
ARM_CENTER_MM = (0.0, 0.0, 0.0)
#: Scene kinds :meth:`SimWorld.for_capture` knows.
#: the scenes the simulated camera can show; the plan's scene targets (capture.plan.SCENE_TARGETS)
#: under the same names, and simulator-only ones (charuco, chrome, flat)
CAPTURE_KINDS = ("object", "checkerboard", "handheld_board", "charuco", "chrome", "spheres", "gray_card",
                 "mirror_probe", "passive", "passive_sphere", "dark", "flat")
#: the scenes lit by the room alone (Grace Cathedral), lamp off, no cloth under them
ROOM_LIT_KINDS = ("mirror_probe", "passive", "passive_sphere")
#: where the sample sphere (:class:`sims.targets.SampleSphere`, 30 mm radius) sits: on a 25 mm
#: stand at the platter's centre, its centre on the turntable axis (so no reading moves it), lab
#: frame, mm
SAMPLE_SPHERE_CENTRE_MM = (0.0, 0.0, 55.0)


def light_position(azimuth_deg: float, elevation_deg: float, *, radius_mm: float = ARM_RADIUS_MM,
                   center_mm=ARM_CENTER_MM) -> np.ndarray:
    """World position (mm) of a light on a sphere of ``radius_mm`` about ``center_mm``:
    azimuth from world +x towards +y, elevation above the xy-plane (degrees) -> (3,)."""
    if not (np.isfinite(azimuth_deg) and -90 <= elevation_deg <= 90):
        raise ValueError(f"light azimuth must be finite and elevation in [-90, 90] deg, got "
                         f"{azimuth_deg!r}, {elevation_deg!r}")
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.asarray(center_mm, float) + radius_mm * np.array(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def default_camera(width: int = 1200, height: int = 800, *, fov_deg: float = 32.0,
                   eye_mm=(650.0, 0.0, 260.0), target_mm=(0.0, 0.0, 55.0),
                   dist=(-0.08, 0.06, 0.0005, -0.0003, 0.0)) -> CameraModel:
    """The rig's fixed camera (ground truth): on the world +x side (azimuth 0) looking down at
    the turntable centre, ~1 MP, with mild barrel distortion (OpenCV k1, k2, p1, p2, k3)."""
    return CameraModel.look_at(eye_mm, target_mm, width=width, height=height, fov_deg=fov_deg,
                               dist=np.asarray(dist, float))


@dataclass(frozen=True)
class RigState:
    """What the camera sees depends on (units: degrees, mm, seconds).

    ``polarizer_deg`` is the analyser on the lens (None: no analyser in the path).
    ``ring_flash``: a ring flash on the lens fires instead of the lamp (Lensch et al. 2003,
    Sec. 4.1: its highlight sits at the centre of each mirror sphere as seen by the camera).
    """

    turntable_deg: float = 0.0
    light_position_mm: tuple[float, float, float] = tuple(light_position(0.0, 30.0))
    polarizer_deg: float | None = None
    exposure_s: float = 0.01
    iso: float = 100.0
    fnumber: float = 8.0
    ring_flash: bool = False

    @classmethod
    def from_state(cls, state: Mapping[str, Any] | None) -> "RigState":
        """Read a frame-source state dict: camera settings ``exposure_s``, ``iso``, ``fnumber``
        and the rig state, flat (``turntable_deg`` / ``turntable_angle_deg``,
        ``light_position_mm``, ``polarizer_deg`` / ``polarizer_angle_deg``) or nested per role
        (``{"turntable": {"angle_deg": ..}, "light": {"position_mm": ..}, "polarizer":
        {"angle_deg": ..}}``), and ``ring_flash`` (bool). Missing entries keep their defaults."""
        s = dict(state or {})
        nested = {k: v for k, v in s.items() if isinstance(v, Mapping)}

        def pick(*keys, role=None, sub=()):
            for k in keys:
                if k in s and not isinstance(s[k], Mapping) and s[k] is not None:
                    return s[k]
            if role in nested:
                for k in sub:
                    if nested[role].get(k) is not None:
                        return nested[role][k]
            return None

        d = cls()
        out = {}
        v = pick("turntable_deg", "turntable_angle_deg", role="turntable",
                 sub=("angle_deg", "position"))
        if v is not None:
            out["turntable_deg"] = _finite("turntable angle", v)
        v = pick("light_position_mm", role="light", sub=("position_mm", "light_position_mm"))
        if v is not None:
            p = np.asarray(v, dtype=float)
            if p.shape != (3,) or not np.all(np.isfinite(p)):
                raise ValueError(f"state light_position_mm must be 3 finite numbers (mm), got {v!r}")
            out["light_position_mm"] = tuple(p)
        v = pick("polarizer_deg", "polarizer_angle_deg", role="polarizer", sub=("angle_deg", "position"))
        if v is not None:
            out["polarizer_deg"] = _finite("polarizer angle", v)
        if "ring_flash" in s:
            out["ring_flash"] = bool(s["ring_flash"])
        for key in ("exposure_s", "iso", "fnumber"):
            v = pick(key, role="camera", sub=(key,))
            if v is not None:
                val = _finite(key, v)
                if val <= 0:
                    raise ValueError(f"state {key} must be > 0, got {v!r}")
                out[key] = val
        return replace(d, **out)


def _finite(name, v) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"state {name} must be a number, got {v!r}") from None
    if not np.isfinite(f):
        raise ValueError(f"state {name} must be finite, got {v!r}")
    return f


@dataclass
class GroundTruth:
    """Everything true about one simulated frame.

    Attributes
    ----------
    state : RigState
    radiance : ndarray of shape (H, W, 3), float32
        The noise-free radiance the sensor integrated (supersampled, analyser applied).
    diffuse, specular : ndarray of shape (H, W, 3), float32
        Its body (depolarised) and interface (polarisation-preserving, incl. mirrors) parts, after
        the analyser: ``radiance = diffuse + specular`` on surfaces (truth for polarisation
        separation).
    buffers : RenderResult
        Geometry buffers at the pixel centres (mask, world normal, position mm, depth mm, uv,
        face and surface index into ``scene.objects``; its ``radiance`` is the pixel-centre
        sample). With an odd ``supersample`` they come from the same render (its middle
        sub-pixels), otherwise from a second one.
    scene : Scene
        The rendered scene (surfaces placed for this state).
    camera : CameraModel
        The ground-truth camera (intrinsics, distortion, world -> camera pose).
    light_position_mm : ndarray of shape (3,)
    object_pose : ndarray of shape (4, 4)
        Turntable (object frame) -> world.
    expected : ExpectedRaw
        Mean, sigma and saturation of the raw frame the sensor produces.
    """

    state: RigState
    radiance: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    buffers: RenderResult
    scene: Scene
    camera: CameraModel
    light_position_mm: np.ndarray
    object_pose: np.ndarray
    expected: ExpectedRaw


@dataclass
class Target:
    """A calibration target placed on the turntable (it turns with it) or fixed in the world.

    ``scene_objects(angle_deg)`` gives its surfaces for a turntable angle; ``points_world``
    (angle_deg) its known feature points (board corners, sphere centres) in the world frame;
    ``spec`` is the target's description (a board, a sphere row ...)."""

    name: str
    objects_at: Any
    points_at: Any
    on_turntable: bool = True
    spec: Any = None

    def scene_objects(self, angle_deg: float) -> list[SceneObject]:
        return self.objects_at(angle_deg if self.on_turntable else 0.0)

    def points_world(self, angle_deg: float) -> np.ndarray:
        return self.points_at(angle_deg if self.on_turntable else 0.0)


def standing_pose(center_height_mm: float, *, tilt_deg: float = 25.0, facing_deg: float = 0.0) -> np.ndarray:
    """4x4 pose (board axes, see :mod:`sims.targets`) of a sheet's centre standing on the
    turntable at angle 0: above the axis at ``center_height_mm``, printed face towards azimuth
    ``facing_deg`` (0: the default camera), leaning back by ``tilt_deg`` (face turned up)."""
    a, t = np.radians(facing_deg), np.radians(tilt_deg)
    z = -np.array([np.cos(a) * np.cos(t), np.sin(a) * np.cos(t), np.sin(t)])  # into the sheet
    x = np.cross(z, [0.0, 0.0, 1.0])  # right as seen from the front, so y points down the sheet
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, (0.0, 0.0, center_height_mm)
    return T


def board_on_turntable(board: PrintedBoard, *, tilt_deg: float = 25.0, height_mm: float | None = None,
                       facing_deg: float = 0.0, name: str | None = None) -> Target:
    """A printed board standing on the turntable (it turns with it), centred at ``height_mm``
    (default: half its height plus 10 mm); see :func:`standing_pose`."""
    zc = board.size_mm[1] / 2 + 10.0 if height_mm is None else height_mm
    pose0 = board.centered_pose(standing_pose(zc, tilt_deg=tilt_deg, facing_deg=facing_deg))
    name = name or type(board).__name__.lower()
    return Target(name, lambda ang: [board.scene_object(turntable_pose(ang) @ pose0, name)],
                  lambda ang: board.corners_world(turntable_pose(ang) @ pose0), True, board)


def handheld_board(board: PrintedBoard, camera: CameraModel, name: str | None = None, **pose) -> Target:
    """The board held in front of ``camera``, fixed in the world at
    :func:`sims.handheld.handheld_board_pose` (``pose``: its keyword arguments)."""
    T = handheld_board_pose(board, camera, **pose)
    name = name or type(board).__name__.lower()
    return Target(name, lambda ang: [board.scene_object(T, name)], lambda ang: board.corners_world(T), False, board)


def spheres_target(kind: str = "steel", *, count: int = 6, radius_mm: float = 12.7,
                   spacing_mm: float = 40.0, start_mm=(-80.0, -100.0, 120.0),
                   direction=(0.0, 1.0, 0.0), on_turntable: bool = False) -> Target:
    """A row of mirror spheres (Lensch et al. 2003 Sec. 4.1: 1-inch bearing balls on a bar),
    behind and above the object so the default camera sees them above it; ``kind`` ``"steel"``
    or ``"chrome"``. Capture once with the lamp and once with ``ring_flash`` in the state (the
    flash's highlights mark the sphere centres' viewing rays, Eq. 1). ``start_mm`` and
    ``direction`` are world coordinates at turntable angle 0; with ``on_turntable`` the fixture
    stands on the platter and turns with it (captures at several angles spread the spheres around
    the axis: a wider baseline for triangulating the lamp), else it is fixed in the world."""
    row = SphereRow(count=count, radius_mm=radius_mm, spacing_mm=spacing_mm, kind=kind)
    start, d = np.asarray(start_mm, float), np.asarray(direction, float)

    def turned(ang):
        R = turntable_pose(ang)[:3, :3]
        return R @ start, R @ d
    return Target(f"{kind}_spheres", lambda ang: row.scene_objects(*turned(ang)),
                  lambda ang: row.centers(*turned(ang)), on_turntable, row)


def sphere_target(kind: str = "chrome", *, radius_mm: float = 25.4,
                  center_mm=(0.0, 0.0, 25.4)) -> Target:
    """One calibration sphere fixed in the world (default: resting on the platter centre)."""
    ball = CalibrationSphere(radius_mm, kind)
    c = np.asarray(center_mm, float)
    return Target(f"{kind}_sphere", lambda ang: [ball.scene_object(c)], lambda ang: c[None], False, ball)


def sample_sphere_target(sphere: SampleSphere | None = None, *, center_mm=SAMPLE_SPHERE_CENTRE_MM) -> Target:
    """The homogeneous sample sphere on its stand (default :class:`sims.targets.SampleSphere` at
    :data:`SAMPLE_SPHERE_CENTRE_MM`), fixed in the world; its point is its centre."""
    ball = SampleSphere() if sphere is None else sphere
    c = np.asarray(center_mm, float)
    return Target("sample_sphere", lambda ang: [ball.scene_object(c)], lambda ang: c[None], False, ball)


def gray_card_target(*, tilt_deg: float = 25.0) -> Target:
    """The 18 % gray card standing on the turntable like a board; its points are its corners."""
    card = GrayCard()
    w, h = card.size_mm
    pose0 = standing_pose(h / 2 + 10.0, tilt_deg=tilt_deg)
    corners = np.array([[-w / 2, -h / 2, 0], [w / 2, -h / 2, 0], [w / 2, h / 2, 0], [-w / 2, h / 2, 0]])

    def points(ang):
        T = turntable_pose(ang) @ pose0
        return corners @ T[:3, :3].T + T[:3, 3]

    return Target("gray_card", lambda ang: [card.scene_object(turntable_pose(ang) @ pose0)], points, True, card)


class SimWorld:
    """The simulated rig as the camera sees it.

    Parameters
    ----------
    object : GroundTruthObject, str or None
        What stands on the turntable: an object, a name from ``sims.objects.OBJECTS``, or None.
    camera : CameraModel, optional
        Ground-truth camera; default :func:`default_camera` (1200 x 800).
    sensor : SensorModel, optional
        Default :meth:`SensorModel.full_frame`.
    targets : sequence of Target, optional
        Calibration targets in the scene (see :func:`board_on_turntable`, :func:`spheres_target`,
        :func:`sphere_target`, :func:`gray_card_target`).
    environment : EnvironmentMap, optional
        Lights the scene besides the lamp (passive reflectometry, light probes); also seen in
        mirrors and as the background.
    light_intensity : float or (3,)
        Lamp radiant intensity (renderer units / sr); 0 switches the lamp off.
    light_radius_mm : float
        Radius of the lamp's emitter as mirrors see it (the highlight on chrome spheres; 25 mm:
        a 50 mm diffuser, whose highlight on a 1-inch ball spans a few pixels).
    light_polarizer_deg : float or None
        Linear polarizer on the lamp (degrees, same reference as the lens analyser); None: none.
    platter : bool
        A dark matte cloth (albedo 3 %) on the plane z = 0 under everything.
    supersample : int
        Rays per pixel side (1: one ray through each pixel centre; 2: 2 x 2 box-filtered).
    env_samples : int
        Monte-Carlo environment samples per pixel (with ``environment``).
    flash_lit : bool
        The ring flash on the lens fires for every frame instead of the lamp (a board held in
        front of the camera: the lamp, wherever the positioner left it, may be behind it).
    seed : int or numpy.random.Generator
        Source of the sensor noise; each frame draws fresh noise from it.
    """

    def __init__(self, object: GroundTruthObject | str | None = "sphere", camera: CameraModel | None = None,
                 sensor: SensorModel | None = None, targets: Sequence[Target] = (), *,
                 environment: EnvironmentMap | None = None, light_intensity=LIGHT_INTENSITY,
                 light_radius_mm: float = 25.0, light_polarizer_deg: float | None = 0.0,
                 platter: bool = True, supersample: int = 1, env_samples: int = 32,
                 flash_lit: bool = False, seed: int | np.random.Generator = 0) -> None:
        self.object = make_object(object) if isinstance(object, str) else object
        if self.object is not None and not isinstance(self.object, GroundTruthObject):
            raise TypeError(f"object must be a GroundTruthObject, a name or None, got {type(object).__name__}")
        self.camera = default_camera() if camera is None else camera
        if not isinstance(self.camera, CameraModel):
            raise TypeError(f"camera must be a CameraModel, got {type(camera).__name__}")
        self.sensor = SensorModel.full_frame() if sensor is None else sensor
        self.targets = list(targets)
        for i, t in enumerate(self.targets):
            if not isinstance(t, Target):
                raise TypeError(f"targets[{i}] must be a sims.world.Target, got {type(t).__name__}")
        self.environment = environment
        self.light_intensity = light_intensity
        if not light_radius_mm >= 0:
            raise ValueError(f"light_radius_mm must be >= 0, got {light_radius_mm!r}")
        self.light_radius_mm = float(light_radius_mm)
        self.light_polarizer_deg = light_polarizer_deg
        self.platter = bool(platter)
        self.flash_lit = bool(flash_lit)
        if int(supersample) < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample!r}")
        self.supersample = int(supersample)
        self.env_samples = int(env_samples)
        self._rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        self._lock = threading.Lock()  # the camera sim may call frame_source from its own thread
        self.dark = False
        self.flat_radiance: float | None = None
        # the last frame's (render key, radiance): a bracket's exposures see the same radiance
        self._last_radiance: tuple[tuple, np.ndarray] | None = None
        # the last pose's (geometry key, camera rays' first hits): its lights and analyser angles
        self._last_primary: tuple[tuple, PrimaryHits] | None = None
        # what set_scene("object") puts back
        self._home = dict(object=self.object, environment=environment, light_intensity=light_intensity,
                          supersample=self.supersample, env_samples=self.env_samples,
                          platter=self.platter, flash_lit=self.flash_lit)

    _SCENE_FIELDS = ("object", "targets", "environment", "light_intensity", "platter", "dark", "flat_radiance",
                     "supersample", "flash_lit", "env_samples")
    #: Monte-Carlo environment samples per pixel a capture kind needs: a glossy lobe under the
    #: room sparkles at the default 32 (a 320 x 240 sample-sphere image left passive
    #: reflectometry a 22-57 % residual and a 150 % Eq. 1 error; 256: 9-16 % and 30 %)
    KIND_ENV_SAMPLES = {"passive_sphere": 256}
    #: pixel-area integration per capture kind: one ray per pixel aliases sharp print edges by
    #: ~0.25 px and the ~1 px lamp highlight on a small steel ball enough to move a triangulated
    #: light by ~2 % (3 x 3 brings it under 0.4 %, tests/calibration)
    KIND_SUPERSAMPLE = {"checkerboard": 2, "charuco": 2, "spheres": 3, "chrome": 2}
    #: 4 x 4 brings the hand-held views' ChArUco corners from 0.21 to 0.14 px rms (320 x 240),
    #: which the principal point needs
    KIND_SUPERSAMPLE["handheld_board"] = 4
    #: rays across the mirror probe's disc: the ball squeezes the whole room into it, so a
    #: point-sampled pixel hits or misses the small bright sources that carry most of the light
    #: (Grace's windows) at random; a 20 px ball at 1 ray per pixel gave a map whose irradiance
    #: was 60 % off, 320 rays across brings it within 5 % (tests/sims/test_probe_capture.py)
    PROBE_RAYS_ACROSS = 320

    @classmethod
    def _kind_supersample(cls, kind: str, camera: CameraModel | None) -> int:
        """Rays per pixel side a capture ``kind`` needs through ``camera`` (pixel-area integration)."""
        if kind != "mirror_probe":
            return cls.KIND_SUPERSAMPLE.get(kind, 1)
        cam = default_camera() if camera is None else camera
        ball = sphere_target("chrome")
        centre = ball.points_world(0.0)[0]
        d = np.linalg.norm(cam.R @ centre + cam.t)
        r_px = cam.K[0, 0] * ball.spec.radius_mm / np.sqrt(d * d - ball.spec.radius_mm ** 2)
        return int(np.clip(np.ceil(cls.PROBE_RAYS_ACROSS / (2 * r_px)), 1, 8))

    def set_scene(self, kind: str) -> None:
        """Change what stands in front of the camera to the scene of capture ``kind`` (see
        :meth:`for_capture`; the names of a plan's scene targets), keeping the camera, sensor,
        lamp polarizer and noise stream. ``"object"`` puts this world's own object back."""
        keep = dict(camera=self.camera, sensor=self.sensor, light_radius_mm=self.light_radius_mm,
                    light_polarizer_deg=self.light_polarizer_deg,
                    env_samples=self.KIND_ENV_SAMPLES.get(kind, self._home["env_samples"]),
                    supersample=max(self._home["supersample"], self._kind_supersample(kind, self.camera)))
        home = dict(self._home)
        obj = home.pop("object")
        home.pop("supersample")
        home.pop("env_samples")
        if kind in ROOM_LIT_KINDS:  # they bring their own lighting and no cloth
            home = {"environment": home["environment"]} if home["environment"] is not None else {}
        if kind == "handheld_board":  # so does the held board (the ring flash, the air behind it)
            home = {k: v for k, v in home.items() if k not in ("platter", "flash_lit")}
        other = SimWorld.for_capture(kind, obj, **keep, **home)
        with self._lock:
            for name in self._SCENE_FIELDS:
                setattr(self, name, getattr(other, name))

    def prepare_target(self, target: str, step=None) -> None:
        """``capture.runner.Runner(prepare_target=world.prepare_target)``: the simulated operator
        sets up ``target`` before the steps that need it (see :meth:`set_scene`); for
        ``handheld_board`` it holds the board at the step's ``view`` of ``views``."""
        self.set_scene(target)
        if target == "handheld_board":
            self.hold_board(CAPTURE_CHARUCO, step)

    def hold_board(self, board: PrintedBoard, step) -> None:
        """Put ``board`` in front of the camera at hand-held view ``step.view`` of ``step.views``
        (:func:`sims.handheld.handheld_view`) as this world's only target."""
        view, views = getattr(step, "view", None), getattr(step, "views", None)
        if view is None or views is None:
            raise ValueError("a handheld_board step must say which view it is (step.view of step.views)")
        target = handheld_board(board, self.camera, **handheld_view(view, views).pose_options())
        with self._lock:
            self.targets = [target]

    # -- preset scenes ------------------------------------------------------------------------
    @classmethod
    def for_capture(cls, kind: str, object: GroundTruthObject | str | None = "sphere", **kwargs) -> "SimWorld":
        """The scene of one kind of capture: ``"object"`` (the object alone), ``"checkerboard"``
        / ``"charuco"`` (:data:`CAPTURE_CHARUCO` standing on the turntable; 2 x 2 supersampled by
        default, since one ray per pixel aliases the print's edges by ~0.25 px), ``"chrome"`` (one chrome sphere),
        ``"spheres"`` (Lensch's row of six steel spheres, beside the object), ``"gray_card"``,
        ``"mirror_probe"`` (a chrome sphere under the Grace Cathedral probe, no lamp), ``"passive"``
        (the object under that probe, no lamp: passive reflectometry), ``"passive_sphere"`` (the
        homogeneous sample sphere under that probe, no lamp: :func:`sample_sphere_target`), ``"dark"`` (lens
        cap on: sensor dark frame), ``"flat"`` (a uniform white field)."""
        if kind not in CAPTURE_KINDS:
            raise ValueError(f"capture kind must be one of {CAPTURE_KINDS}, got {kind!r}")
        if kind == "object":
            return cls(object, **kwargs)
        kwargs.setdefault("supersample", cls._kind_supersample(kind, kwargs.get("camera")))
        if kind in cls.KIND_ENV_SAMPLES:
            kwargs.setdefault("env_samples", cls.KIND_ENV_SAMPLES[kind])
        if kind in ("checkerboard", "charuco"):
            return cls(None, targets=[board_on_turntable(CAPTURE_CHARUCO)], **kwargs)
        if kind == "handheld_board":  # held in the air: no cloth; the ring flash lights it
            kwargs.setdefault("platter", False)
            kwargs.setdefault("flash_lit", True)
            world = cls(None, **kwargs)
            world.targets = [handheld_board(CAPTURE_CHARUCO, world.camera)]
            return world
        if kind == "chrome":
            return cls(None, targets=[sphere_target("chrome")], **kwargs)
        if kind == "spheres":
            return cls(object, targets=[spheres_target("steel")], **kwargs)
        if kind == "gray_card":
            return cls(None, targets=[gray_card_target()], **kwargs)
        if kind in ROOM_LIT_KINDS:
            if "environment" not in kwargs:
                kwargs["environment"] = environment("grace")
            kwargs.setdefault("light_intensity", 0.0)
            kwargs.setdefault("platter", False)
            if kind == "passive":
                return cls(object, **kwargs)
            if kind == "passive_sphere":
                return cls(None, targets=[sample_sphere_target()], **kwargs)
            return cls(None, targets=[sphere_target("chrome")], **kwargs)
        world = cls(None, **kwargs)
        if kind == "dark":
            world.dark = True
        else:
            world.flat_radiance = 0.4
        return world

    # -- scene --------------------------------------------------------------------------------
    def scene(self, state: RigState | Mapping | None = None) -> Scene:
        """The render scene for a rig state (world frame)."""
        st = state if isinstance(state, RigState) else RigState.from_state(state)
        sc = Scene(environment=self.environment)
        if self.object is not None:
            sc.objects.extend(self.object.scene_objects(st.turntable_deg))
        for t in self.targets:
            sc.objects.extend(t.scene_objects(st.turntable_deg))
        if self.platter:
            sc.add(Plane((800.0, 800.0)), Lambertian(0.03), "platter")
        if st.ring_flash or self.flash_lit:  # around the lens: at the camera centre, unpolarised
            sc.add_light(PointLight(self.camera.center, RING_FLASH_INTENSITY, radius=RING_FLASH_RADIUS_MM))
        elif np.any(np.asarray(self.light_intensity, float) > 0):
            sc.add_light(PointLight(st.light_position_mm, self.light_intensity,
                                    radius=self.light_radius_mm, polarizer=self.light_polarizer_deg))
        return sc

    def _render(self, sc: Scene, st: RigState, camera: CameraModel, seed, components: bool = False,
                primary: PrimaryHits | None = None) -> RenderResult:
        return render(sc, camera, shadows=True, polarizer=st.polarizer_deg,
                      env_samples=self.env_samples, rng=seed, components=components, primary=primary)

    def radiance(self, state: RigState | Mapping | None = None, *, seed: int = 0) -> np.ndarray:
        """Noise-free radiance (H, W, 3) float32 the sensor integrates for ``state``."""
        st = state if isinstance(state, RigState) else RigState.from_state(state)
        return self._frame(st, seed, truth=False)[0]

    def _frame(self, st: RigState, seed, *, truth: bool, primary: PrimaryHits | None = None):
        """(radiance, diffuse, specular, buffers) of a frame: the radiance box-filtered over the
        supersample grid; with ``truth`` also its diffuse / specular parts (same filter) and the
        geometry buffers at the pixel centres (None otherwise). ``primary``: the supersampled
        camera's first hits kept for this pose (see :class:`reconstruct.render.PrimaryHits`)."""
        H, W = self.camera.height, self.camera.width
        sc = self.scene(st)
        if self.dark or self.flat_radiance is not None:  # lens cap / uniform field: no render
            rad = np.full((H, W, 3), 0.0 if self.dark else self.flat_radiance, np.float32)
            if not truth:
                return rad, None, None, None
            return rad, rad, np.zeros_like(rad), self._render(sc, st, self.camera, seed)
        s = self.supersample
        hi = self._render(sc, st, self.camera if s == 1 else supersampled_camera(self.camera, s), seed,
                          components=truth, primary=primary)

        def box(a):
            return a if s == 1 else a.reshape(H, s, W, s, 3).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)

        rad = box(hi.radiance)
        if not truth:
            return rad, None, None, None
        if s == 1:
            buffers = hi
        elif s % 2:  # the middle sub-pixel of an odd grid sits on the pixel centre
            c = s // 2
            buffers = RenderResult(**{f: None if getattr(hi, f) is None else getattr(hi, f)[c::s, c::s]
                                      for f in RenderResult.__dataclass_fields__})
        else:
            buffers = self._render(sc, st, self.camera, seed)
        return rad, box(hi.diffuse), box(hi.specular), buffers

    # -- the camera's frame source ------------------------------------------------------------
    def frame_source(self, state: Mapping[str, Any] | None = None) -> bytes:
        """DNG bytes of the frame the camera takes in rig ``state`` (see
        :meth:`RigState.from_state` for the keys). Thread-safe; each call draws fresh noise."""
        st = RigState.from_state(state)
        with self._lock:  # one frame at a time: a scene change (set_scene) waits for it
            rad = self._bracket_radiance(st)
            raw = self.sensor.expose(rad, st.exposure_s, st.iso, self._rng, **self._optics(st))
        return self.sensor.to_dng(raw, exposure_s=st.exposure_s, iso=st.iso, fnumber=st.fnumber,
                                  datetime=camera_clock(state))

    __call__ = frame_source

    def _bracket_radiance(self, st: RigState) -> np.ndarray:
        """:meth:`radiance` of ``st``, rendered once for consecutive frames that differ only in
        exposure time, ISO or aperture (a bracket: the render does not depend on them, and
        the sensor draws each frame's own noise). The key holds the scene's parts themselves
        and is compared by identity, so a scene change or a replaced part renders afresh.
        Call with the lock held."""
        key = (replace(st, exposure_s=1.0, iso=1.0, fnumber=1.0), self.camera, self.light_radius_mm,
               self.light_polarizer_deg, self.env_samples, *(getattr(self, f) for f in self._SCENE_FIELDS),
               *self.targets)
        if _same_key(self._last_radiance, key):
            return self._last_radiance[1]
        rad = self._frame(st, 0, truth=False, primary=self._primary_hits(st))[0]
        rad.flags.writeable = False  # shared by the bracket's frames
        self._last_radiance = (key, rad)
        return rad

    #: the most camera rays whose first hits are kept between frames (~130 bytes each)
    PRIMARY_HITS_MAX_RAYS = 1 << 20

    def _primary_hits(self, st: RigState) -> PrimaryHits | None:
        """The kept first hits of this pose's camera rays (empty for a new pose), shared by the
        frames of one pose under other lights, the ring flash or analyser angles: what the camera
        rays hit depends on the turntable angle, the camera and what stands in the scene only.
        None past :attr:`PRIMARY_HITS_MAX_RAYS`. Call with the lock held."""
        key = (st.turntable_deg, self.camera, self.supersample, self.object, self.platter, self.targets,
               *self.targets)
        if _same_key(self._last_primary, key):
            return self._last_primary[1]
        self._last_primary = None  # let the last pose's hits go before the new ones are traced
        if self.camera.width * self.camera.height * self.supersample ** 2 > self.PRIMARY_HITS_MAX_RAYS:
            return None
        self._last_primary = (key, PrimaryHits())
        return self._last_primary[1]

    def _optics(self, st: RigState) -> dict:
        K = self.camera.K
        return dict(fnumber=st.fnumber, focal_px=float(np.sqrt(K[0, 0] * K[1, 1])),
                    principal_point=(float(K[0, 2]), float(K[1, 2])))

    def ground_truth(self, state: Mapping[str, Any] | RigState | None = None) -> GroundTruth:
        """Truth of the frame :meth:`frame_source` makes for ``state`` (without its noise)."""
        st = state if isinstance(state, RigState) else RigState.from_state(state)
        rad, diffuse, specular, buffers = self._frame(st, 0, truth=True)
        expected = self.sensor.expected_raw(rad, st.exposure_s, st.iso, **self._optics(st))
        return GroundTruth(state=st, radiance=rad, diffuse=diffuse, specular=specular, buffers=buffers,
                           scene=self.scene(st), camera=self.camera,
                           light_position_mm=np.asarray(st.light_position_mm, float),
                           object_pose=turntable_pose(st.turntable_deg), expected=expected)


#: the board :meth:`SimWorld.for_capture` stands on the turntable for ``checkerboard`` (and
#: ``charuco``) captures: a ChArUco, whose corner ids stay put as the board turns and which is
#: found when partly outside the frame, large enough to cover much of the image and to tilt
#: visibly as the turntable turns it through +-60 deg (a careful lab's board views; a 9 x 6
#: chessboard of 15 mm squares was found in 3 of 13 such views at 320 x 240, and a bigger one
#: flipped its corner order between views)
CAPTURE_CHARUCO = CharucoTarget(squares=(10, 7), square_mm=28.0, marker_mm=21.0)
#: a printed chessboard of the simulated lab (not in a capture scene: tests, ``gonio sim``)
CAPTURE_CHESSBOARD = Checkerboard(square_mm=15.0, margin_mm=10.0)


def capture_targets(spheres: Target | None = None) -> dict[str, Any]:
    """What the simulated lab's calibration targets are, for a calibration to look for (mm, world
    frame = the lab frame: origin on the axis at the platter, +z up): :data:`CAPTURE_CHARUCO`'s
    geometry and the height of its corner grid's centre as it stands on the turntable, the
    light-calibration spheres' radius, mirror reflectance and centres at turntable reading 0
    (``spheres``: default the steel-ball row of :meth:`SimWorld.for_capture`'s ``spheres``
    scene), the gray card's albedo, the sample sphere's radius (calipers) and its stand's centre.
    Keys are the field names of a calibration's target description (``capture.lab.LabTargets``)."""
    charuco = board_on_turntable(CAPTURE_CHARUCO)
    balls = spheres_target("steel") if spheres is None else spheres
    return {"charuco_squares": CAPTURE_CHARUCO.squares, "charuco_square_mm": CAPTURE_CHARUCO.square_mm,
            "charuco_marker_mm": CAPTURE_CHARUCO.marker_mm, "charuco_dictionary": CAPTURE_CHARUCO.dictionary,
            "charuco_centre_height_mm": float(charuco.points_world(0.0).mean(axis=0)[2]),
            "sphere_radius_mm": balls.spec.radius_mm,
            "sphere_reflectance": CalibrationSphere(balls.spec.radius_mm, balls.spec.kind).reflectance,
            "sphere_centres_mm": tuple(map(tuple, balls.points_world(0.0).tolist())),
            "gray_card_albedo": gray_card_target().spec.albedo,
            "sample_sphere_radius_mm": sample_sphere_target().spec.radius_mm,
            "sample_sphere_centre_mm": SAMPLE_SPHERE_CENTRE_MM}


def _same_key(kept: tuple | None, key: tuple) -> bool:
    """Whether ``kept``'s key is ``key``: its first entry (a value) equal, the rest (the scene's
    parts) the same objects."""
    return kept is not None and len(kept[0]) == len(key) and kept[0][0] == key[0] \
        and all(a is b for a, b in zip(kept[0][1:], key[1:]))


def camera_clock(state: Mapping[str, Any] | None) -> str:
    """The DNG ``DateTime`` of a frame: the simulated camera's clock, never set, reads
    :data:`CAMERA_CLOCK_START` plus one second per capture (``state["capture_number"]``), so the
    same plan captured twice gives byte-identical files (the store records the real times)."""
    n = int((state or {}).get("capture_number", 0))
    return (CAMERA_CLOCK_START + timedelta(seconds=n)).strftime("%Y:%m:%d %H:%M:%S")


def supersampled_camera(camera: CameraModel, s: int) -> CameraModel:
    """The camera with ``s`` x ``s`` sub-pixels per pixel: hi-res pixel X maps to the low-res
    coordinate (X + 1/2) / s - 1/2, the lens distortion (in normalised coordinates) unchanged."""
    K = camera.K.copy()
    K[0, 0] *= s
    K[1, 1] *= s
    K[0, 1] *= s
    K[0, 2] = s * (K[0, 2] + 0.5) - 0.5
    K[1, 2] = s * (K[1, 2] + 0.5) - 0.5
    return replace(camera, K=K, width=camera.width * s, height=camera.height * s)
