"""The simulated rig's scene against its own geometry: turntable pose, mirror highlights, board
corners (rendered through the distorted ground-truth camera)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from reconstruct.raycast import first_hits
from sims.objects import make_sphere
from sims.targets import Checkerboard, CharucoTarget
from sims.world import (SimWorld, board_on_turntable, default_camera, light_position,
                        sphere_target, spheres_target)


def _bisector_point(center, radius, eye, light):
    """Point of a sphere whose normal bisects the directions to ``eye`` and ``light`` (the
    mirror highlight), by fixed-point iteration."""
    n = (eye - center) / np.linalg.norm(eye - center)
    for _ in range(200):
        p = center + radius * n
        h = (eye - p) / np.linalg.norm(eye - p) + (light - p) / np.linalg.norm(light - p)
        n = h / np.linalg.norm(h)
    return center + radius * n


def _dark_blob_centroids(gt):
    """Centroids (x, y) of the dark marker dots inside the object's mask."""
    lum = gt.radiance.mean(axis=2).astype(float)
    local = ndimage.median_filter(lum, size=11)
    dots = gt.buffers.mask & (lum < 0.3 * local)
    lab, n = ndimage.label(dots)
    if n == 0:
        return np.zeros((0, 2))
    return np.array(ndimage.center_of_mass(local - lum, lab, range(1, n + 1)))[:, ::-1]


def test_object_pose_follows_the_turntable():
    cam = default_camera(320, 240, fov_deg=20.0, target_mm=(0.0, 0.0, 40.0))
    obj = make_sphere(40.0, marker_dirs=((1, 0, 0.3), (1, 0.8, 0.3), (1, -0.8, 0.3)),
                      marker_radius_mm=3.0)
    world = SimWorld(obj, camera=cam, platter=False, supersample=2)
    light = light_position(10.0, 40.0)
    previous = None
    for angle in (0.0, 30.0, -40.0):
        gt = world.ground_truth({"turntable_deg": angle, "light_position_mm": light})
        assert np.allclose(gt.object_pose[:2, :2], [[np.cos(np.radians(angle)), -np.sin(np.radians(angle))],
                                                     [np.sin(np.radians(angle)), np.cos(np.radians(angle))]])
        markers = obj.markers_world(angle)
        normals = (markers - [0, 0, 40.0]) / 40.0
        to_eye = cam.center - markers
        cos_view = np.einsum("ij,ij->i", normals, to_eye) / np.linalg.norm(to_eye, axis=1)
        clear = cos_view > 0.5  # clearly visible; near-grazing dots may or may not be found
        pred = cam.project(markers)
        found = _dark_blob_centroids(gt)
        assert clear.sum() >= 2
        dist = np.linalg.norm(found[:, None] - pred[None], axis=2)  # (found, marker)
        # every clearly visible marker is found: a 3 mm dot on a 40 mm sphere at 0.75 mm per
        # pixel, centroid within half a pixel of the projection of its centre
        err = dist[:, clear].min(axis=0)
        assert err.max() < 0.5, (angle, err)
        # every dark blob is a marker on the camera's side (near the limb a dot is foreshortened
        # into a sliver whose centroid drifts by a few pixels)
        assert np.all(cos_view[dist.argmin(axis=1)] > 0) and dist.min(axis=1).max() < 3.0
        # and the position buffer there holds the marker's world position (pixel footprint ~1 mm)
        px = np.rint(pred[clear]).astype(int)
        assert np.abs(gt.buffers.position[px[:, 1], px[:, 0]] - markers[clear]).max() < 1.5
        pred = pred[clear]
        if previous is not None:  # the turntable really moved the first marker
            assert np.linalg.norm(cam.project(markers[:1]) - previous) > 20
        previous = cam.project(obj.markers_world(angle))[0:1]


def test_chrome_sphere_highlight_moves_with_the_light():
    cam = default_camera(320, 240, fov_deg=9.0, target_mm=(0.0, 0.0, 25.4))
    world = SimWorld(None, camera=cam, targets=[sphere_target("chrome")], light_radius_mm=15.0,
                     supersample=2, platter=False)
    center = np.array([0.0, 0.0, 25.4])
    seen = []
    for az, el in ((20.0, 40.0), (-30.0, 25.0)):
        light = light_position(az, el)
        lum = world.radiance({"light_position_mm": light}).mean(axis=2)
        lab, n = ndimage.label(lum > 20.0)  # the lamp's reflection: ~100x the diffuse level
        assert n == 1
        found = np.array(ndimage.center_of_mass(lum, lab, 1))[::-1]
        pred = cam.project(_bisector_point(center, 25.4, cam.center, light))[0]
        assert np.linalg.norm(found - pred) < 0.3, (found, pred)
        seen.append(found)
    # the light moved 50 deg in azimuth: the highlight moved accordingly (tens of pixels)
    assert np.linalg.norm(seen[1] - seen[0]) > 20


def _match_either_order(found, truth):
    """Chessboard detections of a 180-degree-symmetric board may come in reverse order."""
    e1 = np.linalg.norm(found - truth, axis=1)
    e2 = np.linalg.norm(found[::-1] - truth, axis=1)
    return e1 if e1.mean() < e2.mean() else e2


@pytest.mark.parametrize("angle", [25.0, -30.0])
def test_checkerboard_corners_project_where_the_camera_model_says(angle):
    cam = default_camera(400, 300, fov_deg=22.0)
    assert np.any(cam.dist)  # the ground-truth lens distorts
    world = SimWorld(None, camera=cam, targets=[board_on_turntable(Checkerboard())], supersample=2)
    state = {"turntable_deg": angle, "light_position_mm": light_position(0, 45)}
    lum = world.radiance(state).mean(axis=2)
    img = np.clip(lum / lum.max() * 255, 0, 255).astype(np.uint8)
    ok, corners = cv2.findChessboardCornersSB(img, (9, 6), flags=cv2.CALIB_CB_ACCURACY)
    assert ok
    corners_world = world.targets[0].points_world(angle)
    truth = cam.project(corners_world)
    err = _match_either_order(corners.reshape(-1, 2), truth)
    # OpenCV's detector on ~12 px squares, 2x2-supersampled: 0.10-0.15 px RMS (seen; 0.05 px at
    # twice the resolution, so the scatter is the detector's, not the rendering's)
    assert np.sqrt(np.mean(err ** 2)) < 0.2 and err.max() < 0.5
    # exactness of the rendering itself: the surface point seen at a pixel centre projects back
    # onto that pixel centre through the distorted camera model
    px = np.rint(truth)
    seen = first_hits(world.scene(state).surfaces, *cam.pixel_rays(px)).position
    assert np.abs(cam.project(seen) - px).max() < 1e-3
    assert np.linalg.norm(seen - corners_world, axis=1).max() < 1.0  # within a pixel footprint


def test_charuco_corners_project_where_the_camera_model_says():
    cam = default_camera(400, 300, fov_deg=22.0)
    world = SimWorld(None, camera=cam, targets=[board_on_turntable(CharucoTarget())], supersample=2)
    lum = world.radiance({"turntable_deg": -20.0, "light_position_mm": light_position(0, 45)}).mean(axis=2)
    img = np.clip(lum / lum.max() * 255, 0, 255).astype(np.uint8)
    board = world.targets[0].spec
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board.board()).detectBoard(img)
    assert ids is not None and len(ids) >= 12
    truth = cam.project(world.targets[0].points_world(-20.0))[ids.ravel()]
    err = np.linalg.norm(corners.reshape(-1, 2) - truth, axis=1)
    assert np.sqrt(np.mean(err ** 2)) < 0.2 and err.max() < 0.5
    # the board stands upright: its first corner (top-left as printed) is up-left in the image
    c = corners.reshape(-1, 2)
    first, last = c[np.argmin(ids.ravel())], c[np.argmax(ids.ravel())]
    assert first[0] < last[0] and first[1] < last[1]


def test_steel_sphere_row_highlights_lamp_and_ring_flash():
    """Lensch et al. 2003 Sec. 4.1: the lamp's highlight on each of the six collinear balls sits
    where the normal bisects eye and light; the ring flash's on the ray through each centre."""
    cam = default_camera(600, 200, fov_deg=18.0, target_mm=(-80.0, 0.0, 120.0))
    row = spheres_target("steel")
    world = SimWorld(None, camera=cam, targets=[row], supersample=2, platter=False)
    centers = row.points_world(0.0)
    assert centers.shape == (6, 3) and np.allclose(np.diff(centers, axis=0), [0, 40, 0])
    light = light_position(30.0, 40.0)
    for flash in (False, True):
        lum = world.radiance({"light_position_mm": light, "ring_flash": flash}).mean(axis=2)
        lab, n = ndimage.label(lum > 5.0)
        found = np.array(ndimage.center_of_mass(lum, lab, range(1, n + 1)))[:, ::-1]
        pred = cam.project(centers) if flash else \
            cam.project(np.array([_bisector_point(c, 12.7, cam.center, light) for c in centers]))
        # (with the lamp, a ball also mirrors its neighbour's highlight: extra, fainter blobs)
        err = np.linalg.norm(found[:, None] - pred[None], axis=2).min(axis=0)
        assert err.max() < 0.3, (flash, err)


@pytest.mark.parametrize("angle", [-45.0, 0.0, 45.0])
def test_default_checkerboard_capture_is_detectable_at_full_resolution(angle):
    world = SimWorld.for_capture("checkerboard")
    assert (world.camera.width, world.camera.height) == (1200, 800)
    lum = world.radiance({"turntable_deg": angle, "light_position_mm": light_position(20, 45)}).mean(axis=2)
    img = np.clip(lum / lum.max() * 255, 0, 255).astype(np.uint8)
    ok, corners = cv2.findChessboardCornersSB(img, (9, 6), flags=cv2.CALIB_CB_ACCURACY)
    assert ok
    err = _match_either_order(corners.reshape(-1, 2), world.camera.project(world.targets[0].points_world(angle)))
    assert np.sqrt(np.mean(err ** 2)) < 0.2
