"""``gonio sim render``: writes a DNG rawpy reads and a PNG preview; clear errors."""
from __future__ import annotations

import json

import cv2
import numpy as np
import rawpy
from typer.testing import CliRunner

from capture.cli import app

runner = CliRunner()


def test_sim_render_writes_dng_png_and_truth(tmp_path):
    out = tmp_path / "frames"
    res = runner.invoke(app, ["sim", "render", "--object", "sphere", "--turntable", "30", "--light-az", "45",
                              "--light-el", "30", "--polarizer", "0", "--exposure", "0.05", "--width", "160",
                              "--height", "120", "--truth", "--out", str(out)])
    assert res.exit_code == 0, res.output
    stem = "sphere_tt30_az45_el30_pol0_e0.05"
    dng, png = out / f"{stem}.dng", out / f"{stem}.png"
    assert str(dng) in res.output and str(png) in res.output
    with rawpy.imread(str(dng)) as r:
        raw = r.raw_image_visible.copy()
        assert raw.shape == (120, 160) and r.white_level == 16383
    img = cv2.imread(str(png))
    assert img.shape == (120, 160, 3)
    truth = np.load(out / f"{stem}_truth.npz")
    assert np.allclose((truth["diffuse"] + truth["specular"])[truth["mask"]], truth["radiance"][truth["mask"]], atol=1e-5)
    meta = json.loads((out / f"{stem}.json").read_text())
    assert meta["state"]["turntable_deg"] == 30.0 and meta["state"]["polarizer_deg"] == 0.0
    az, el = np.radians(45), np.radians(30)
    assert np.allclose(meta["light_position_mm"], 500 * np.array([np.cos(el) * np.cos(az),
                                                                   np.cos(el) * np.sin(az), np.sin(el)]))
    # the preview is brighter where the truth is: object pixels vs the dark platter
    on = truth["surface_index"] == 0
    grey = img.mean(axis=2)
    assert on.sum() > 500 and grey[on].mean() > 3 * grey[~on].mean()
    # the raw frame is the one the truth describes (mean within 6 sigma per pixel, unsaturated)
    ok = ~truth["saturated"]
    z = (raw.astype(float) - truth["expected_dn"])[ok] / truth["sigma_dn"][ok]
    assert np.abs(z).max() < 6


def test_sim_render_target_scene(tmp_path):
    res = runner.invoke(app, ["sim", "render", "--scene", "checkerboard", "--object", "none", "--width", "64",
                              "--height", "48", "--name", "board", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "board.dng").is_file() and (tmp_path / "board.png").is_file()


def test_sim_render_bad_arguments(tmp_path):
    res = runner.invoke(app, ["sim", "render", "--object", "teapot", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "--object must be one of" in res.output
    res = runner.invoke(app, ["sim", "render", "--scene", "moon", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "--scene must be one of" in res.output
    res = runner.invoke(app, ["sim", "render", "--width", "33", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "even" in res.output
    res = runner.invoke(app, ["sim", "render", "--exposure", "0", "--width", "32", "--height", "32",
                              "--out", str(tmp_path)])
    assert res.exit_code == 2 and "--exposure must be in 1e-06..3600, got 0.0" in res.output
    res = runner.invoke(app, ["sim", "render", "--supersample", "0", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "--supersample must be in 1..8" in res.output
    res = runner.invoke(app, ["sim", "render", "--light-el", "100", "--width", "32", "--height", "32",
                              "--out", str(tmp_path)])
    assert res.exit_code == 2 and "--light-el must be in -90..90 degrees, got 100.0" in res.output


def test_sim_render_help_explains_outputs_frames_and_options():
    res = runner.invoke(app, ["sim", "render", "--help"], terminal_width=100)
    assert res.exit_code == 0
    text = " ".join(res.output.split())
    for phrase in ("NAME.dng and NAME.png", "white balance", "sensor white = display white",
                   "turntable frame", "azimuth 0", "Examples:", "Exit codes", "--object",
                   "--scene", "--light-az", "--polarizer", "--truth"):
        assert phrase in text, phrase
