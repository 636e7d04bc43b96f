"""Calibration targets: board textures and geometry, spheres, gray card, environments."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from reconstruct.brdf import Lambertian
from reconstruct.raycast import first_hits
from reconstruct.render import Mirror
from sims.targets import (PAPER_BLACK, PAPER_WHITE, CalibrationSphere, Checkerboard,
                          CharucoTarget, GrayCard, SphereRow, environment, pose_facing,
                          procedural_sky)


def test_checkerboard_texture_and_object_points():
    b = Checkerboard(inner_corners=(4, 3), square_mm=10.0, margin_mm=5.0, px_per_mm=4.0)
    tex = b.texture()
    # (4 + 1) x (3 + 1) squares of 10 mm + 5 mm margins at 4 px/mm
    assert tex.shape == ((4 * 10 + 10) * 4, (5 * 10 + 10) * 4)
    # first square (top-left as printed, texels 20..59) is black, its right neighbour white,
    # the margin white
    assert tex[40, 40] == 0 and tex[40, 80] == 255 and tex[5, 5] == 255
    pts = b.object_points()
    assert pts.shape == (12, 3)
    assert np.array_equal(pts[:5], [[0, 0, 0], [10, 0, 0], [20, 0, 0], [30, 0, 0], [0, 10, 0]])
    # the albedo of square centres in the board frame (origin = first inner corner)
    assert b.albedo_at([[-5, -5]])[0] == pytest.approx(PAPER_BLACK)
    assert b.albedo_at([[5, -5]])[0] == pytest.approx(PAPER_WHITE)
    assert b.albedo_at([[5, 5]])[0] == pytest.approx(PAPER_BLACK)
    assert b.albedo_at([[-18, 0], [500, 500]]) == pytest.approx([PAPER_WHITE, PAPER_WHITE])
    # a corner sits half-way between black and white
    assert b.albedo_at([[0.0, 0.0]])[0] == pytest.approx((PAPER_BLACK + PAPER_WHITE) / 2)


def test_charuco_texture_matches_board_geometry():
    """The corners OpenCV detects in the printed texture sit where the board frame puts them."""
    t = CharucoTarget(squares=(5, 4), square_mm=20.0, marker_mm=15.0, margin_mm=10.0, px_per_mm=6.0)
    tex = t.texture()
    assert tex.shape == (int(round((4 * 20 + 20) * 6)), int(round((5 * 20 + 20) * 6)))
    det = cv2.aruco.CharucoDetector(t.board())
    corners, ids, _, _ = det.detectBoard(cv2.GaussianBlur(tex, (0, 0), 1.0))
    assert ids is not None and len(ids) == 4 * 3
    obj = t.object_points()[ids.ravel()]
    x0, y0, _, _ = t.extent_mm
    # pixel centres at integers: board point x maps to (x - x0) * ppmm - 1/2
    expect = np.stack([(obj[:, 0] - x0) * 6 - 0.5, (obj[:, 1] - y0) * 6 - 0.5], axis=1)
    assert np.abs(corners.reshape(-1, 2) - expect).max() < 0.1


def test_board_surface_is_placed_by_pose():
    b = Checkerboard(inner_corners=(5, 4), square_mm=15.0)
    eye = np.array([400.0, 100.0, 250.0])
    pose = b.centered_pose(pose_facing((10.0, -20.0, 80.0), eye))
    surf = b.surface(pose)
    corners = b.corners_world(pose)
    # rays from the eye to the known corners hit the sheet exactly there, on its printed side
    d = corners - eye
    hits = first_hits([surf], eye, d / np.linalg.norm(d, axis=1, keepdims=True))
    assert hits.mask.all()
    assert np.abs(hits.position - corners).max() < 1e-6
    assert np.all(hits.normal @ pose[:3, 2] < -0.999)          # outward normal = -z of the board
    assert np.all(np.einsum("ij,ij->i", hits.normal, -d) > 0)  # facing the eye
    # the material's uv lookup gives the albedo at the hit's board coordinates
    brdf = b.material()(hits.position, hits.uv, hits.face_index)
    assert isinstance(brdf, Lambertian)
    inv = np.linalg.inv(pose)
    local = hits.position @ inv[:3, :3].T + inv[:3, 3]
    mid = (local + np.array([7.5, 7.5, 0]))[:, :2]  # centres of the squares below-right of the corners
    d2 = (pose[:3, :3] @ np.c_[mid, np.zeros(len(mid))].T).T + pose[:3, 3] - eye
    h2 = first_hits([surf], eye, d2 / np.linalg.norm(d2, axis=1, keepdims=True))
    alb = b.material()(h2.position, h2.uv, h2.face_index).albedo[:, 0]
    assert np.allclose(alb, b.albedo_at(mid), atol=1e-6)
    i, j = np.divmod(np.arange(len(mid)), 5)
    # the square below-right of inner corner (i, j) is square (i + 1, j + 1): black when i + j is even
    assert np.allclose(alb, np.where((i + j) % 2 == 0, PAPER_BLACK, PAPER_WHITE), atol=1e-6)


def test_gray_card_and_spheres():
    card = GrayCard()
    obj = card.scene_object(pose_facing((0, 0, 60), (500, 0, 60)))
    assert isinstance(obj.material, Lambertian) and obj.material.albedo == 0.18
    chrome = CalibrationSphere(25.4, "chrome").scene_object((0, 0, 25.4))
    assert isinstance(chrome.material, Mirror) and chrome.material.reflectance == 0.65
    matte = CalibrationSphere(20.0, "matte", albedo=0.7).scene_object((0, 0, 20.0))
    assert isinstance(matte.material, Lambertian)
    row = SphereRow(count=6, radius_mm=10.0, spacing_mm=40.0)
    c = row.centers((0, 0, 100), (0, 2, 0))
    assert c.shape == (6, 3)
    assert np.allclose(np.diff(c, axis=0), [0, 40, 0])
    objs = row.scene_objects((0, 0, 100), (0, 1, 0))
    assert len(objs) == 6 and all(isinstance(o.material, Mirror) for o in objs)
    assert np.allclose([o.surface.center for o in objs], c)


@pytest.mark.parametrize("make, match", [
    (lambda: Checkerboard(inner_corners=(1, 5)), "inner_corners"),
    (lambda: Checkerboard(square_mm=0), "square_mm"),
    (lambda: CharucoTarget(marker_mm=40.0), "marker_mm"),
    (lambda: CharucoTarget(dictionary="DICT_NOPE"), "dictionary"),
    (lambda: CalibrationSphere(-1.0), "radius_mm"),
    (lambda: CalibrationSphere(10.0, "glass"), "kind"),
    (lambda: SphereRow(count=2), "count"),
    (lambda: SphereRow(radius_mm=30, spacing_mm=40), "spacing_mm"),
    (lambda: GrayCard(size_mm=(0, 10)), "size_mm"),
    (lambda: Checkerboard().centered_pose(np.eye(3)), "pose"),
    (lambda: environment("mars"), "environment"),
])
def test_bad_target_parameters_are_named(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_real_light_probe_loads_as_rgb(shared_data):
    env = environment("grace", data_dir=shared_data)
    assert env.image.shape == (128, 256, 3) and env.image.dtype == np.float32
    raw = cv2.imread(str(shared_data / "probes" / "grace.hdr"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(env.image, raw[..., ::-1])  # OpenCV's BGR turned into RGB


def test_missing_probe_falls_back_to_the_sky(tmp_path):
    with pytest.warns(RuntimeWarning, match="procedural sky"):
        env = environment("uffizi", data_dir=tmp_path)
    assert env.image.shape == procedural_sky().image.shape


def test_procedural_sky_has_its_sun_where_asked():
    env = procedural_sky(sun_azimuth_deg=60.0, sun_elevation_deg=30.0)
    i, j = np.unravel_index(np.argmax(env.luminance()), env.shape)
    d = env.directions()[i, j]
    sun = np.array([np.cos(np.radians(30)) * np.cos(np.radians(60)),
                    np.cos(np.radians(30)) * np.sin(np.radians(60)), np.sin(np.radians(30))])
    assert np.degrees(np.arccos(d @ sun)) < 2.5
    # ground below the horizon is dark and uniform
    below = env.directions()[..., 2] < -0.05
    assert np.ptp(env.image[below], axis=0).max() == 0 and env.image[below].max() < 0.2


def test_pose_facing_reads_upright_from_the_viewer():
    eye = np.array([600.0, 0.0, 100.0])
    T = pose_facing((0.0, 0.0, 100.0), eye)
    assert np.allclose(T[:3, 2], [-1, 0, 0])          # into the board, away from the viewer
    assert np.allclose(T[:3, 1], [0, 0, -1])          # y down the sheet
    # x to the viewer's right: the camera at +x looking at -x with z up has right = +y
    assert np.allclose(T[:3, 0], [0, 1, 0])
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
