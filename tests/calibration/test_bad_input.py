"""Every public calibration function rejects unusable input up front with a CalibrationError
(``InvalidInput``) that names the argument, instead of a traceback from deep inside numpy or
OpenCV, or NaNs in the result."""
from __future__ import annotations

import numpy as np
import pytest

import calibration as c
from calibration.targets import to_gray_u8
from calibration.errors import CalibrationError, InvalidInput

K = np.array([[1000.0, 0, 320], [0, 1000, 240], [0, 0, 1]])
NAN_K = np.where(np.eye(3) == 1, np.nan, K)
SPH = c.SphereImage(np.array([50.0, 50]), 20.0, None, np.zeros((0, 2)))
DET = c.TargetDetection(np.random.default_rng(0).random((20, 2)) * 100, np.random.default_rng(1).random((20, 3)),
                        (640, 480))
U16 = np.zeros((4, 4), np.uint16)

CASES = [
    ("image", lambda: c.detect_chessboard(np.zeros((0, 0), np.uint8), (9, 6))),
    ("image", lambda: c.detect_chessboard("left01.jpg", (9, 6))),
    ("board", lambda: c.detect_charuco(np.zeros((50, 50), np.uint8), None)),
    ("detections[0].image_points",
     lambda: c.calibrate_intrinsics([c.TargetDetection(np.full((20, 2), np.nan), np.zeros((20, 3)), (640, 480))] * 3)),
    ("detections[0].object_points",
     lambda: c.calibrate_intrinsics([c.TargetDetection(np.zeros((20, 2)), np.zeros((19, 3)), (640, 480))] * 3)),
    ("detections[1]", lambda: c.calibrate_intrinsics([DET, "not a detection", DET])),
    ("image_points[0]", lambda: c.corner_coverage([np.zeros((3, 3))], (640, 480))),
    ("K", lambda: c.fit_turntable([DET] * 3, NAN_K)),
    ("dist", lambda: c.fit_turntable([DET] * 3, K, dist=[1, 2])),
    ("angles_deg", lambda: c.fit_turntable([DET] * 3, K, angles_deg=[0, np.nan, 20])),
    ("mask", lambda: c.detect_sphere(np.zeros((0, 0)))),
    ("rel_threshold", lambda: c.find_highlight(np.ones((10, 10)), rel_threshold=2)),
    ("radius_px", lambda: c.SphereImage(np.zeros(2), -1.0)),
    ("sphere", lambda: c.find_highlight(np.ones((10, 10)), (np.zeros(2), 5.0))),
    ("highlight_xy", lambda: c.light_direction_orthographic([1, 2, 3], SPH)),
    ("K", lambda: c.sphere_center_from_silhouette(
        c.SphereImage(np.array([50.0, 50]), 20.0, None, np.random.default_rng(2).random((30, 2)) * 100), NAN_K)),
    ("K", lambda: c.reflect_highlight([[1, 2]], [[0, 0, 500]], 10, np.eye(2))),
    ("radius_mm", lambda: c.reflect_highlight([[320, 240]], [[0, 0, 500]], -10, K)),
    ("center_mm", lambda: c.reflect_highlight([[320, 240]], [[0, 0, np.nan]], 10, K)),
    ("center_mm", lambda: c.reflect_highlight([[320, 240]], [[0, 0, 5]], 10, K)),
    ("sigma_px", lambda: c.triangulate_point_light([[320, 240], [330, 240]], [[0, 0, 500], [50, 0, 500]], 10, K,
                                                   sigma_px=-1)),
    ("highlights_xy", lambda: c.triangulate_point_light([[np.nan, 240], [330, 240]], [[0, 0, 500], [50, 0, 500]],
                                                        10, K)),
    ("flash_highlights_xy", lambda: c.locate_collinear_spheres(np.zeros((3, 3)), 10, K)),
    ("spacing_mm", lambda: c.locate_collinear_spheres(np.zeros((3, 2)), np.nan, K)),
    ("positions_mm", lambda: c.fit_positioner_model([0, 30, 60, 90], [10, 20, 30, 40], np.full((4, 3), np.nan))),
    ("parallel", lambda: c.separate_parallel_crossed(np.full((4, 4), np.nan), np.ones((4, 4)))),
    ("read_sigma", lambda: c.separate_parallel_crossed(np.ones((4, 4)), np.ones((4, 4)), read_sigma=np.nan)),
    ("angles_deg", lambda: c.fit_polarization(np.ones((3, 4, 4)), [0, np.nan, 90])),
    ("frames", lambda: c.merge_raw_brackets([U16, np.zeros((5, 4), np.uint16)], [0.1, 0.2], white_level=100)),
    ("white_level", lambda: c.merge_raw_brackets([U16], [0.1], white_level=np.nan)),
    ("darks", lambda: c.merge_raw_brackets([U16], [0.1], white_level=100, darks=np.zeros((3, 3)))),
    ("black_level", lambda: c.merge_raw_brackets([U16], [0.1], white_level=100, black_level=np.zeros((3, 3)))),
    ("nonexistent.dng", lambda: c.read_raw("/nonexistent.dng")),
    ("frames", lambda: c.master_frame(np.full((2, 3, 3), np.nan))),
    ("images", lambda: c.merge_ldr([np.zeros((4, 4), np.uint8), np.zeros((5, 4), np.uint8)], [0.1, 0.2], np.ones(256))),
    ("response", lambda: c.merge_ldr([np.zeros((4, 4), np.uint8)] * 2, [0.1, 0.2], np.ones(255))),
    ("8-bit", lambda: c.recover_response([np.zeros((4, 4, 3))] * 2, [0.1, 0.2])),
    ("path", lambda: c.write_hdr("/nonexistent_dir/x.tif", np.zeros((4, 4), np.float32))),
    ("dark", lambda: c.flat_field_gain(np.ones((2, 4, 4)), dark=np.ones((3, 3)))),
    ("gain", lambda: c.fit_vignetting(np.full((10, 10), np.nan))),
    ("gain", lambda: c.apply_flat(np.ones((4, 4)), np.full((4, 4), np.nan))),
    ("light_distance_mm", lambda: c.gray_card_scale([1, 2], light_distance_mm=np.nan)),
    ("light_mm", lambda: c.normalize_irradiance(np.ones((4, 4)), np.zeros((4, 4, 3)), [1, 2])),
    ("center_px", lambda: c.mirror_sphere_to_latlong(np.ones((10, 10)), [1, 2, 3], 5, np.eye(3))),
    ("height", lambda: c.mirror_sphere_to_latlong(np.ones((10, 10)), [5, 5], 5, np.eye(3), height="a")),
    ("image", lambda: c.mirror_sphere_to_latlong(np.full((10, 10), np.nan), [5, 5], 5, np.eye(3))),
    ("R_world_to_camera", lambda: c.mirror_sphere_to_latlong(np.ones((10, 10)), [5, 5], 5, -np.eye(3))),
    ("K", lambda: c.mirror_sphere_to_latlong_perspective(np.ones((10, 10)), np.eye(2), None, [0, 0, 500], 10,
                                                         np.eye(3))),
    ("probes[0]", lambda: c.merge_probes([1, 2])),
    ("reflectance", lambda: c.find_mirror_sphere(np.ones((50, 50)), reflectance=1.5)),
    ("window", lambda: c.demosaic_smooth_hue(np.ones((4, 4)), np.zeros((4, 4), int), window=4)),
    ("channels", lambda: c.demosaic_smooth_hue(np.ones((4, 4)), np.zeros((3, 3), int))),
    ("source", lambda: c.read_raw(3.5)),
    ("images[1]", lambda: c.light_directions_from_sphere([np.ones((8, 8)), np.full((8, 8), np.nan)])),
    ("reflectance", lambda: c.sphere_silhouettes([np.ones((8, 8))], 1.5)),
    ("centers_mm", lambda: c.project_spheres([[0, 0, 1.0]], 5.0, K, None, (640, 480))),
    ("sphere", lambda: c.lamp_spots(np.ones((8, 8)), "not a sphere", 0.5)),
    ("min_pixels", lambda: c.find_gray_card(np.ones((8, 8)), min_pixels=0)),
    ("detections[0]", lambda: c.consistent_corner_order(["x"], K)),
    ("fit", lambda: c.lab_frame(None, [0, 0, 0], 1.0)),
    ("white_percentile", lambda: to_gray_u8(np.ones((4, 4)), white_percentile=0)),
    ("height", lambda: c.latlong_directions("x")),
]


@pytest.mark.parametrize("argument, call", CASES, ids=[f"{i}-{a}" for i, (a, _) in enumerate(CASES)])
def test_bad_input_is_a_calibration_error_naming_the_argument(argument, call):
    with pytest.raises(CalibrationError) as info:
        call()
    assert isinstance(info.value, InvalidInput)
    assert argument in str(info.value)
    assert isinstance(info.value, ValueError)  # callers that catch ValueError keep working
