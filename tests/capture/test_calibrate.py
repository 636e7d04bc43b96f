"""``calibrate_session`` and ``gonio calibrate`` end to end on the simulated lab.

A small plan (320 x 240 sims, a few views) is captured with the Runner on the simulated rig (real
drivers over the real wire protocols); the runner's ``prepare_target`` hook swaps the simulated
scene the way an operator swaps targets. The pipeline's results are checked against the
SimWorld's ground-truth camera, turntable axis and light positions.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from capture.calibrate import LabTargets, STAGES, calibrate_session
from capture.cli import app
from capture.plan import Plan
from capture.rigs import open_rig
from capture.runner import Runner, create_session
from capture.store import SessionNotFound, Store
from reconstruct.brdf import Lambertian
from reconstruct.raycast import Plane
from reconstruct.render import SceneObject
from sims.targets import CharucoTarget
from sims.world import SimWorld, Target, board_on_turntable, default_camera, spheres_target

W, H = 320, 240
SPHERE_RADIUS_MM = 25.0
#: a board that fills much of the frame (a turntable sweep only ever shows the board near the centre)
BOARD = CharucoTarget(squares=(10, 7), square_mm=28.0, marker_mm=21.0)
TARGETS = LabTargets(charuco_squares=BOARD.squares, charuco_square_mm=BOARD.square_mm,
                     charuco_marker_mm=BOARD.marker_mm, sphere_radius_mm=SPHERE_RADIUS_MM)
PLAN = {
    "name": "cal", "turntable": {"angles_deg": [0]},
    "light": {"azimuth_deg": [-40, 0, 40], "elevation_deg": [20, 50]},
    "polarizer": {"angles_deg": [0, 90]},
    "exposure": {"base_s": 0.02, "stops": [-2, 0]},
    "calibration": [
        {"kind": "dark", "frames": 2},
        {"kind": "checkerboard", "turntable_angles_deg": [300, 310, 320, 330, 340, 350, 0, 10, 20, 30, 40, 50, 60], "exposure_s": 0.02,
         "lights": "first"},
        {"kind": "spheres", "lights": "grid"},
        {"kind": "gray_card", "lights": "first"},
        {"kind": "mirror_probe", "when": "after"},
    ],
}


def _backdrop() -> Target:
    """A white matte board behind the sphere row, facing the camera (+x): the spheres show as
    dark discs against it."""
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = (0, 1, 0), (0, 0, 1), (1, 0, 0), (-400, 0, 150)
    obj = SceneObject(Plane((1200.0, 700.0), pose), Lambertian(0.8), "backdrop")
    return Target("backdrop", lambda ang: [obj], lambda ang: np.zeros((0, 3)), False)


class SceneSwitch:
    """The camera's frame source: renders the scene of the target the runner asked for."""

    def __init__(self) -> None:
        self.camera = default_camera(W, H)
        spheres = spheres_target("chrome", count=3, radius_mm=SPHERE_RADIUS_MM, spacing_mm=90.0,
                                 start_mm=(-120.0, -90.0, 110.0))
        self.worlds = {
            "object": SimWorld("sphere", camera=self.camera, seed=1),
            "lens_cap": SimWorld.for_capture("dark", camera=self.camera, seed=2),
            "checkerboard": SimWorld(None, camera=self.camera, targets=[board_on_turntable(BOARD)],
                                     supersample=2, seed=3),
            "spheres": SimWorld(None, camera=self.camera, targets=[spheres, _backdrop()], light_radius_mm=60.0, seed=4),
            "gray_card": SimWorld.for_capture("graycard", camera=self.camera, seed=6),
            "mirror_probe": SimWorld.for_capture("probe", None, camera=self.camera, seed=5),
        }
        self.current = self.worlds["object"]

    def __call__(self, state):
        return self.current.frame_source(state)

    def prepare(self, target, step) -> None:
        self.current = self.worlds[target]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("cal")
    scenes = SceneSwitch()
    with open_rig("sim", fast=True, home=True, frame_source=scenes) as opened:
        store = Store(root / "store", durable=False)
        create_session(store, Plan.from_dict(PLAN), opened.rig, name="cal", reserve_bytes=0)
        assert Runner(opened.rig, store, "cal", reserve_bytes=0, prepare_target=scenes.prepare).run() == "done"
        report = calibrate_session(store, "cal", targets=TARGETS)
        yield store, report, scenes, root
        store.close()


def test_pipeline_stages(session):
    store, report, scenes, _ = session
    status = {s.stage: s.status for s in report.stages}
    print({s.stage: (s.status, s.reason, s.figures) for s in report.stages})
    assert [s.stage for s in report.stages] == list(STAGES)
    for stage in ("dark", "hdr", "intrinsics", "turntable", "lights", "positioner", "polarization"):
        assert status[stage] == "ok", report.stage(stage).reason
    assert "no gray_card captures" in report.stage("gray_card").reason
    assert "no mirror_probe captures" in report.stage("mirror_probe").reason
