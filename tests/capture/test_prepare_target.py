"""``OpenedRig.prepare_target``: the opened rig says who stages a scene target, instead of the
CLI and the console guessing it from the frame source's bound ``__self__``."""
from __future__ import annotations

import io

import numpy as np
import rawpy

from capture.cli.capture import _target_handler
from capture.rigs import open_rig
from capture.tui.backend import target_handler
from sims.ptp_sim import placeholder_frame


def _signal_dn(opened) -> float:
    """Mean raw signal above the per-channel black level of one capture, DN."""
    with rawpy.imread(io.BytesIO(opened.rig.camera.capture().data)) as raw:
        img = raw.raw_image_visible.astype(float)
        black = np.asarray(raw.black_level_per_channel, float)[raw.raw_colors_visible]
        return float(np.mean(img - black))


def test_simulated_camera_stages_each_target_in_the_rendered_scene():
    with open_rig("sim", fast=True, home=True) as opened:
        assert opened.prepare_target is not None
        assert _target_handler(opened, yes=True) is opened.prepare_target
        assert target_handler(opened, ask=lambda t, s: None) is opened.prepare_target
        opened.rig.camera.set_exposure(0.01)
        lit = _signal_dn(opened)
        opened.prepare_target("dark", None)  # lens cap on: read noise around the black level
        dark = _signal_dn(opened)
        opened.prepare_target("object", None)
        assert lit > 20 and abs(dark) < 2, (lit, dark)
        assert _signal_dn(opened) > 0.5 * lit


def test_plain_frame_source_has_no_scene_changer_so_the_operator_is_asked():
    def ask(target, step):
        pass

    with open_rig("sim", fast=True, frame_source=placeholder_frame) as opened:
        assert opened.prepare_target is None
        assert target_handler(opened, ask) is ask  # was None: nobody set the scene up
        assert _target_handler(opened, yes=True) is None  # --yes: a target line is printed

    staged = []
    with open_rig("sim", fast=True, frame_source=placeholder_frame,
                  prepare_target=lambda t, s: staged.append(t)) as opened:
        target_handler(opened, ask)("checkerboard", None)
    assert staged == ["checkerboard"]
