"""``--rig sim`` renders the built-in lab (``DemoLab``) at a resolution one can pick, and says so in
its rig config, which is how a stored session is later known to be the lab's."""
from __future__ import annotations

import io

import pytest
import rawpy
from typer.testing import CliRunner

from capture.cli import app
from capture.pipeline.demo_lab import FAST_RESOLUTION, FULL_RESOLUTION, DemoLab
from capture.rigs import BUILT_IN_SCENE, open_rig, recorded_in_built_in_lab
from capture.store import Store
from sims.lab import LAB_NAME
from sims.ptp_sim import placeholder_frame

TINY_PLAN = """name = "tiny"
[turntable]
angles_deg = [0]
[light]
azimuth_deg = [0]
elevation_deg = [30]
[exposure]
base_s = 0.01
"""


def test_the_simulated_camera_renders_the_demo_lab_at_the_chosen_resolution():
    with open_rig("sim", fast=True, resolution=(64, 48)) as opened:
        lab = opened.lab.frame_source
        assert isinstance(lab, DemoLab) and opened.prepare_target == lab.prepare_target
        opened.rig.camera.set_exposure(0.01)
        with rawpy.imread(io.BytesIO(opened.rig.camera.capture().data)) as raw:
            assert raw.raw_image_visible.shape == (48, 64)
        assert opened.rig.config["rig"] == {"name": LAB_NAME, "fast": True, "camera_scene": BUILT_IN_SCENE,
                                            "camera_resolution": [64, 48]}
    for fast, size in ((True, FAST_RESOLUTION), (False, FULL_RESOLUTION)):
        with open_rig("sim", fast=fast, connect=False) as opened:
            cam = opened.lab.frame_source.camera
            assert (cam.width, cam.height) == size


def test_a_frame_source_of_ones_own_is_not_the_built_in_lab():
    with open_rig("sim", fast=True, connect=False, frame_source=placeholder_frame) as opened:
        assert "camera_scene" not in opened.rig.config["rig"]
        snapshot = {"config": opened.rig.config}
    assert not recorded_in_built_in_lab([snapshot])
    assert not recorded_in_built_in_lab([])
    with open_rig("sim", fast=True, connect=False, options={"camera": {"frame_source": placeholder_frame}}) as opened:
        assert "camera_scene" not in opened.rig.config["rig"] and opened.prepare_target is None


@pytest.mark.parametrize("kwargs, match", [
    ({"resolution": (640, 480), "frame_source": placeholder_frame}, "resolution: sets the built-in"),
    ({"resolution": (63, 48)}, "resolution: DemoLab: width must be an even number"),
    ({"resolution": (64, 8)}, "height must be an even number of pixels >= 16"),
    ({"resolution": "640x480"}, "resolution: \\(width, height\\)"),
])
def test_bad_resolutions_are_refused_naming_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        open_rig("sim", connect=False, **kwargs)


def test_capture_run_with_sim_camera_stores_frames_of_that_size(tmp_path):
    plan = tmp_path / "tiny.toml"
    plan.write_text(TINY_PLAN)
    store = tmp_path / "store"
    r = CliRunner().invoke(app, ["capture", "run", str(plan), "--rig", "sim", "--sim-camera", "64x48",
                                 "--store", str(store), "--session", "tiny", "-q"])
    assert r.exit_code == 0, r.output
    with Store(store) as st:
        info = st.session("tiny")
        assert recorded_in_built_in_lab(st.rig_snapshots(info.id))
        with rawpy.imread(io.BytesIO(st.read_object(st.frames(info.id)[0].sha256))) as raw:
            assert raw.raw_image_visible.shape == (48, 64)
    r = CliRunner().invoke(app, ["capture", "plan", str(plan), "--sim-camera", "64x48"])
    assert r.exit_code == 2 and "--sim-camera" in r.output and "--rig sim" in r.output, r.output
    r = CliRunner().invoke(app, ["capture", "plan", str(plan), "--rig", "sim", "--sim-camera", "64by48"])
    assert r.exit_code == 2 and "WIDTHxHEIGHT" in r.output, r.output
    r = CliRunner().invoke(app, ["capture", "plan", str(plan), "--rig", "sim", "--sim-camera", "65x48"])
    assert r.exit_code == 2 and "each even" in r.output and "65x48" in r.output, r.output
