"""The simulated lab: scenes per target, the lab's target sizes, and the truth.

:class:`DemoLab` is what the simulated camera of ``--rig sim`` (:func:`capture.rigs.open_rig`)
and ``gonio demo`` renders, at :data:`FAST_RESOLUTION` or :data:`FULL_RESOLUTION` (or any
``resolution=``). It is the camera's frame source: it renders the scene of whatever target the
runner asked the operator to set up (``prepare_target``), all through one camera, sensor and lamp:

==============  ==============================================================================
``object``      the object (default: the bumpy three-material sphere, else the four-material bunny)
``dark``        dark frames (lens cap on)
``checkerboard``  a 10 x 7 ChArUco of 28 mm squares standing on the turntable (fills much of
                the frame: a turntable sweep otherwise only sees the image centre)
``handheld_board``  the same ChArUco held in front of the camera at the step's view
                (:func:`sims.handheld.handheld_view`: tilted 45° about both image axes, pushed
                into the corners and edges), lit by the ring flash on the lens
``spheres``     three 25 mm chrome balls on a bar standing on the turntable (it turns them
                around the axis) before a lit white backdrop, lamp behind a 120 mm diffuser
                (Lensch et al. 2003 Sec. 4.1)
``gray_card``   the 18 % card standing on the turntable
``mirror_probe``  a chrome ball under the Grace Cathedral probe, lamp off
``passive``     the object under that probe, lamp off (passive reflectometry outside its
                assumption: the object has several materials)
``passive_sphere``  the homogeneous sample sphere (:class:`sims.targets.SampleSphere`: 30 mm
                radius, the glossy Cook-Torrance :data:`sims.targets.SAMPLE_MATERIAL`) on a
                stand at the platter's centre under that probe, lamp off (passive
                reflectometry within its assumption)
==============  ==============================================================================

:meth:`DemoLab.targets` states these targets as the calibration reads them
(:class:`capture.lab.LabTargets`), :meth:`DemoLab.gray_card_pose` the card's pose, and
:meth:`DemoLab.truth` the ground truth the report compares against. Frames: the sims' world
frame, which is the calibration's lab frame (origin on the turntable axis at the platter, +z up,
+x towards the camera), mm.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh

from calibration.raw import read_raw
from reconstruct.brdf import BRDF, Lambertian
from reconstruct.camera import CameraModel
from reconstruct.envmap import EnvironmentMap
from reconstruct.raycast import Mesh, Plane
from reconstruct.render import SceneObject
from rig import LightTarget
from sims.lab import LAB_NAME
from sims.objects import MULTI_MATERIALS, OBJECTS, GroundTruthObject, make_object, region_ids
from sims.targets import CHROME_REFLECTANCE, GrayCard, SampleSphere, environment
from sims.world import (CAPTURE_CHARUCO, LIGHT_INTENSITY, SimWorld, Target, capture_targets, default_camera,
                        light_position, sample_sphere_target, spheres_target, standing_pose)

from ..lab import GrayCardPose, LabTargets, SessionLab

#: the simulated camera's resolution (width, height) with instant motion (tests, ``gonio demo
#: --quick``) and with modelled motion (``--no-fast``, ``gonio demo``): the sizes the lab's targets
#: and the demo plans are made and tested for. Not the ground-truth camera's 1200 x 800: a board or
#: spheres frame takes 14 s / 9 s to render there on one core (640 x 480: 3.6 s / 4.3 s; 320 x
#: 240: ~1 s), an hour for examples/demo.toml.
FAST_RESOLUTION = (320, 240)
FULL_RESOLUTION = (640, 480)
SPHERE_RADIUS_MM = 25.0
#: the lamp's diffuser radius as the spheres see it: its highlight spans a few pixels
SPHERES_LAMP_RADIUS_MM = 60.0
#: the room light the sample sphere's recovered BRDF is also rendered under (the captures are lit
#: by Grace Cathedral): a held-out environment, and its map height (texels: 16 rows, 512 texels, keep
#: its two renders of the sample sphere under 1 s)
HELD_OUT_PROBE = ("uffizi", 16)


def _backdrop() -> Target:
    """A white matte board behind the sphere row facing the camera: the spheres show as dark
    discs against it."""
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = (0, 1, 0), (0, 0, 1), (1, 0, 0), (-400, 0, 150)
    obj = SceneObject(Plane((1200.0, 700.0), pose), Lambertian(0.8), "backdrop")
    return Target("backdrop", lambda ang: [obj], lambda ang: np.zeros((0, 3)), False)


@dataclass(frozen=True)
class DemoTruth:
    """What the simulated lab really is (for the report's truth columns).

    ``camera`` the true camera (lab -> camera pose), ``object`` the object with its true
    materials, ``light_intensity`` the lamp's (renderer units / sr, RGB), ``sensor_dn_per_radiance``
    (3,) the camera's DN/s per unit of renderer radiance at the image centre (so calibrated
    intensities in DN/s mm^2 compare with the truth), ``sample_sphere`` the sample sphere of the
    ``passive_sphere`` capture (its radius and its one true material)."""

    camera: CameraModel
    object: GroundTruthObject
    light_intensity: np.ndarray
    sensor_dn_per_radiance: np.ndarray
    sample_sphere: SampleSphere

    @staticmethod
    def light_position(light: LightTarget) -> np.ndarray:
        """True lab position (mm) of a step's commanded light (azimuth and elevation: the
        positioner's own distance)."""
        return light_position(light.azimuth_deg, light.elevation_deg)

    def materials(self, points: np.ndarray) -> tuple[np.ndarray, tuple[BRDF, ...]]:
        """True material id per object-frame point (N, 3) mm and the materials by id."""
        if hasattr(self.object, "material_at"):   # the bumpy object states its own truth
            return self.object.material_at(points), tuple(self.object.materials)
        if self.object.name != "multi":
            raise ValueError(f"no per-point material truth for object {self.object.name!r}")
        return region_ids(points, self.object.height_mm), MULTI_MATERIALS

    @staticmethod
    def held_out_environment() -> EnvironmentMap:
        """A room the passive captures never saw (:data:`HELD_OUT_PROBE`), lab frame."""
        name, height = HELD_OUT_PROBE
        return environment(name).resized(height)

    def normals(self, points: np.ndarray) -> np.ndarray | None:
        """True unit normals (N, 3) at object-frame points where the rendered surface has detail
        the fitter's mesh lacks; None where the mesh is the truth."""
        return self.object.normal_at(points) if hasattr(self.object, "normal_at") else None


class DemoLab:
    """Frame source of the demo's simulated camera (see the module docstring).

    Parameters
    ----------
    width, height : int
        Camera resolution, pixels, even (a Bayer mosaic); the fast lab's 320 x 240 by default.
    object : str or GroundTruthObject
        What stands on the turntable.
    seed : int
        Sensor-noise seed (each scene draws from its own stream).
    """

    def __init__(self, width: int = 320, height: int = 240, *, object: str | GroundTruthObject | None = None,
                 seed: int = 0) -> None:
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 16 or value % 2:
                raise ValueError(f"DemoLab: {name} must be an even number of pixels >= 16 (a Bayer "
                                 f"mosaic), got {value!r}")
        if object is None:   # the multi-material object with detail its mesh lacks, where it exists
            object = "bumpy" if "bumpy" in OBJECTS else "multi"
        self.camera = default_camera(width, height)
        self.object = make_object(object) if isinstance(object, str) else object
        cam = self.camera
        self.worlds = {
            "object": SimWorld(self.object, camera=cam, seed=seed + 1),
            "dark": SimWorld.for_capture("dark", camera=cam, seed=seed + 2),
            "checkerboard": SimWorld.for_capture("checkerboard", camera=cam, seed=seed + 3),
            "handheld_board": SimWorld.for_capture("handheld_board", camera=cam, seed=seed + 8),
            "spheres": SimWorld(None, camera=cam, targets=[self._spheres(), _backdrop()],
                                light_radius_mm=SPHERES_LAMP_RADIUS_MM, supersample=2, seed=seed + 4),
            "gray_card": SimWorld.for_capture("gray_card", camera=cam, seed=seed + 5),
            "mirror_probe": SimWorld.for_capture("mirror_probe", None, camera=cam, seed=seed + 6),
            "passive": SimWorld.for_capture("passive", self.object, camera=cam, seed=seed + 7),
            "passive_sphere": SimWorld.for_capture("passive_sphere", camera=cam, seed=seed + 9),
        }
        self.current = self.worlds["object"]

    @staticmethod
    def _spheres() -> Target:
        return spheres_target("chrome", count=3, radius_mm=SPHERE_RADIUS_MM, spacing_mm=90.0,
                              start_mm=(-120.0, -90.0, 110.0), on_turntable=True)

    def __call__(self, state) -> bytes:
        return self.current.frame_source(state)

    def prepare_target(self, target: str, step=None) -> None:
        """``Runner(prepare_target=...)``: the simulated operator sets up ``target`` (for a
        ``handheld_board`` step: holds the board at the step's ``view`` of ``views``)."""
        if target not in self.worlds:
            raise ValueError(f"the demo lab has no scene for target {target!r}; it has {', '.join(self.worlds)}")
        if target == "handheld_board":
            self.worlds[target].hold_board(CAPTURE_CHARUCO, step)
        self.current = self.worlds[target]

    # -- what the lab states about itself ---------------------------------------------------------
    def targets(self) -> LabTargets:
        """The lab's calibration targets as :func:`capture.pipeline.calibrate.calibrate_session`
        reads them: those of :func:`sims.world.capture_targets` with this lab's chrome balls,
        which stand on the turntable."""
        return LabTargets(**capture_targets(self._spheres()), spheres_on_turntable=True)

    @staticmethod
    def gray_card_pose() -> GrayCardPose:
        """Centre and printed-side normal of the card at turntable reading 0 (lab frame)."""
        w, h = GrayCard().size_mm
        pose = standing_pose(h / 2 + 10.0)
        return GrayCardPose(tuple(pose[:3, 3]), tuple(-pose[:3, 2]))

    def session_lab(self, session: str) -> SessionLab:
        """This lab as a session recorded in it is processed: the fitter's mesh, the targets, the
        gray card's pose, the probe ball's mirror reflectance, the truth and the
        :meth:`method_options`."""
        return SessionLab(session, True, self.targets(), fitter_mesh(self.object), self.gray_card_pose(),
                          CHROME_REFLECTANCE, self.truth(), self.method_options(), (LAB_NAME,))

    def method_options(self) -> dict[str, dict[str, Any]]:
        """Methods' options for this lab's sessions: reflectance sharing's RBF centres, 300 at
        320 x 240 (~7 s instead of ~100 s for the paper's 1000 on 140k samples; held-out error
        0.51 instead of 0.44 on the bunny), 2000 above (the full demo's 710 k samples underfit at
        500: held out 0.378 / 0.282 / 0.235 at 500 / 1000 / 2000, 27 / 37 / 53 s; docs/zoo.md)."""
        small = self.camera.width * self.camera.height <= FAST_RESOLUTION[0] * FAST_RESOLUTION[1]
        return {"sharing": {"max_centers": 300 if small else 2000}}

    def truth(self, fnumber: float = 8.0, iso: float = 100.0) -> DemoTruth:
        """The ground truth; ``fnumber`` / ``iso`` the camera settings the captures used."""
        sensor = self.worlds["object"].sensor
        # camera equation at the principal point (no vignetting): DN/s per unit radiance
        dn = (np.asarray(sensor.quantum_efficiency) * np.pi / (4.0 * fnumber ** 2) * sensor.photon_flux
              * sensor.pixel_pitch_um ** 2 / sensor.e_per_dn(iso))
        return DemoTruth(camera=self.camera, object=self.object,
                         light_intensity=np.broadcast_to(np.asarray(LIGHT_INTENSITY, float), (3,)).copy(),
                         sensor_dn_per_radiance=dn, sample_sphere=sample_sphere_target().spec)


def demo_lab_for(store, session: str) -> DemoLab:
    """The demo lab a stored session was captured in, at the resolution of its frames."""
    frames = store.frames(store.session(session).id)
    if not frames:
        raise ValueError(f"session {session!r} has no frames")
    h, w = read_raw(store.read_object(frames[0].sha256)).data.shape
    return DemoLab(w, h)


def fitter_mesh(obj: GroundTruthObject) -> trimesh.Trimesh:
    """The mesh a fitter is given for a simulated object: its (smooth) triangle mesh in the
    object frame. An object whose rendered geometry carries detail the mesh lacks states the
    smooth one as ``fitter_mesh``."""
    smooth = getattr(obj, "fitter_mesh", None)
    if smooth is not None:
        return smooth
    meshes = [p.surface for p in obj.parts if isinstance(p.surface, Mesh)]
    if not meshes:
        raise ValueError(f"object {obj.name!r} has no triangle mesh; give one with --mesh")
    return trimesh.util.concatenate([m.mesh.copy().apply_transform(m.transform) for m in meshes])
