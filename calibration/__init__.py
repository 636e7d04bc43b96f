"""Rig calibration from its own captures. Pure: arrays in, results (with uncertainties) out.

Modules (one function per calibration step; each validates its input first and raises a
:class:`~calibration.errors.CalibrationError` subclass for an unusable capture or fit):

- :mod:`calibration.targets` — chessboard / ChArUco detection (``TargetDetection``)
- :mod:`calibration.intrinsics` — K and distortion with outlier-view rejection and coverage
- :mod:`calibration.turntable` — rotation axis, angle model, world (object) frame per reading
- :mod:`calibration.lights` — chrome/steel spheres: highlights, light directions and positions,
  Lensch's collinear spheres, positioner kinematics
- :mod:`calibration.spheres` — mirror spheres in images: one call from images to light directions
  (orthographic or perspective), silhouettes, known-position discs, lamp spots and their choice
- :mod:`calibration.polarization` — diffuse/specular separation
- :mod:`calibration.raw` — the one raw-file decoder (``read_raw``), Bayer channels, demosaic
- :mod:`calibration.hdr` — raw and 8-bit HDR merging, float32 TIFF / EXR output
- :mod:`calibration.radiometry` — flat field / vignetting, gray card, 1/r² normalisation
- :mod:`calibration.probe` — mirror-sphere light probes to world lat-long maps
"""
from .errors import CalibrationError, DegenerateFit, InvalidInput, NotConverged, TargetNotFound, TooFewViews
from .hdr import HDRImage, master_frame, merge_ldr, merge_raw_brackets, recover_response, write_hdr
from .intrinsics import IntrinsicsResult, RejectedView, calibrate_intrinsics, corner_coverage, detect_all
from .lights import (Highlight, PointLight, PositionerModel, SphereImage, detect_sphere, find_highlight,
                     fit_positioner_model, light_direction_orthographic, locate_collinear_spheres,
                     closest_point_to_lines, reflect_highlight, sphere_center_from_silhouette,
                     triangulate_point_light)
from .polarization import PolarizationFit, Separation, fit_polarization, separate_parallel_crossed
from .probe import (Probe, latlong_directions, merge_probes, mirror_sphere_to_latlong,
                    mirror_sphere_to_latlong_perspective)
from .raw import RawMosaic, cfa_channels, demosaic_bilinear, demosaic_smooth_hue, read_raw
from .radiometry import (GrayCard, VignettingModel, apply_flat, find_gray_card, fit_vignetting, flat_field_gain,
                         gray_card_scale, normalize_irradiance)
from .targets import (TargetDetection, as_points2d, chessboard_object_points, detect_charuco,
                      detect_chessboard, make_charuco_board)
from .spheres import (LampSpot, SphereLights, find_mirror_sphere, lamp_spots, light_directions_from_sphere,
                      pick_lamp_highlights, project_spheres, sphere_silhouettes)
from .turntable import TurntableFit, consistent_corner_order, fit_turntable, lab_frame

__all__ = [
    "CalibrationError", "DegenerateFit", "InvalidInput", "NotConverged", "TargetNotFound", "TooFewViews",
    "TargetDetection", "as_points2d", "chessboard_object_points", "detect_chessboard", "detect_charuco",
    "make_charuco_board",
    "IntrinsicsResult", "RejectedView", "calibrate_intrinsics", "corner_coverage", "detect_all",
    "TurntableFit", "fit_turntable", "consistent_corner_order", "lab_frame",
    "SphereImage", "Highlight", "PointLight", "PositionerModel", "detect_sphere", "find_highlight",
    "light_direction_orthographic", "sphere_center_from_silhouette", "reflect_highlight",
    "closest_point_to_lines", "triangulate_point_light", "locate_collinear_spheres", "fit_positioner_model",
    "SphereLights", "LampSpot", "light_directions_from_sphere", "find_mirror_sphere", "sphere_silhouettes",
    "project_spheres", "lamp_spots", "pick_lamp_highlights",
    "Separation", "PolarizationFit", "separate_parallel_crossed", "fit_polarization",
    "RawMosaic", "read_raw", "cfa_channels", "demosaic_bilinear", "demosaic_smooth_hue",
    "HDRImage", "master_frame", "merge_raw_brackets", "recover_response", "merge_ldr", "write_hdr",
    "VignettingModel", "GrayCard", "flat_field_gain", "fit_vignetting", "apply_flat", "find_gray_card",
    "gray_card_scale", "normalize_irradiance",
    "Probe", "latlong_directions", "mirror_sphere_to_latlong", "mirror_sphere_to_latlong_perspective",
    "merge_probes",
]
