"""Ground-truth objects: their materials follow the object (not the world), the roughness ramp and
material regions are what the truth functions say, the bunny sits on the platter."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.brdf import CookTorrance
from reconstruct.render import MaterialMap, Scene, render
from sims.objects import (MULTI_MATERIALS, OBJECTS, RoughnessRamp, _load_mesh, bunny_mesh,
                          make_hemisphere, make_multi_material, make_object, region_ids,
                          turntable_pose)
from sims.world import default_camera


def _to_object(points_world, angle):
    T = np.linalg.inv(turntable_pose(angle))
    return points_world @ T[:3, :3].T + T[:3, 3]


def test_turntable_pose_is_a_right_handed_rotation_about_z():
    T = turntable_pose(90.0)
    assert np.allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0])  # counter-clockwise seen from above
    assert np.allclose(T[:3, 3], 0) and np.allclose(T[:3, :3] @ [0, 0, 1], [0, 0, 1])
    with pytest.raises(ValueError, match="turntable angle"):
        turntable_pose(float("nan"))


def test_roughness_ramp_is_linear_in_object_y():
    ramp = RoughnessRamp(radius_mm=40.0, alpha_left=0.4, alpha_right=0.05)
    y = np.linspace(-40, 40, 9)
    pts = np.stack([np.full(9, 7.0), y, np.zeros(9)], axis=1)
    assert np.allclose(ramp.alpha_at(pts), 0.4 + (0.05 - 0.4) * (y + 40) / 80)
    with pytest.raises(ValueError, match="alpha_left"):
        RoughnessRamp(alpha_left=0.0)


@pytest.mark.parametrize("angle", [0.0, 90.0])
def test_hemisphere_roughness_turns_with_the_turntable(angle):
    """The SVBRDF the renderer looks up at each pixel is the ramp at the point's *object-frame*
    position, whatever the turntable angle."""
    obj = make_hemisphere()
    ramp = obj.parts[0].material
    cam = default_camera(160, 120, fov_deg=14.0, target_mm=(0, 0, 20))
    res = render(Scene(objects=obj.scene_objects(angle)), cam, shadows=False)
    m = res.mask
    assert m.sum() > 3000
    pos = res.position[m]
    brdf = ramp(pos, res.uv[m].astype(np.float64), res.face_index[m])
    assert isinstance(brdf, CookTorrance)
    truth = ramp.alpha_at(_to_object(pos, angle))
    # uv is float32 in the buffers: ~1e-6 relative
    assert np.abs(np.ravel(brdf.alpha) - truth).max() < 1e-4
    assert np.ptp(truth) > 0.2  # the camera sees most of the ramp (0.35 end to end)


def test_multi_material_regions_follow_the_object():
    obj = make_multi_material(base="sphere", height_mm=80.0)
    mat = obj.parts[0].material
    assert isinstance(mat, MaterialMap) and len(mat.materials) == len(MULTI_MATERIALS) == 4
    cam = default_camera(160, 120, fov_deg=14.0, target_mm=(0, 0, 40))
    for angle in (0.0, 120.0):
        res = render(Scene(objects=obj.scene_objects(angle)), cam, shadows=False)
        m = res.mask
        ids = mat.resolve_ids(res.position[m], res.uv[m], res.face_index[m].astype(np.int64))
        truth = region_ids(_to_object(res.position[m], angle), 80.0)
        # per-face ids vs the point's own region: they differ only on faces straddling a border
        assert np.mean(ids == truth) > 0.97
        assert len(np.unique(ids)) >= 3


def test_bunny_sits_on_the_platter(shared_data):
    mesh = bunny_mesh(120.0, data_dir=shared_data)
    assert len(mesh.faces) == 69451
    lo, hi = mesh.bounds
    assert lo[2] == pytest.approx(0.0, abs=1e-9) and hi[2] - lo[2] == pytest.approx(120.0)
    assert np.allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-9)
    # the ears point up: the top of the scan (its +y) is now +z, proper rotation (no mirror)
    src = _load_mesh(str(shared_data / "meshes" / "bun_zipper.ply"))  # cached: the same scan
    assert np.argmax(mesh.vertices[:, 2]) == np.argmax(src.vertices[:, 1])
    A = np.linalg.lstsq(np.c_[src.vertices, np.ones(len(src.vertices))], mesh.vertices, rcond=None)[0]
    assert np.linalg.det(A[:3]) > 0  # a rotation and scale, not a reflection
    up = A[:3].T @ [0, 1, 0]  # row-vector fit: the linear map is A[:3].T
    assert np.allclose(up / np.linalg.norm(up), [0, 0, 1])
    small = bunny_mesh(60.0, full=False, data_dir=shared_data)
    assert len(small.faces) == 16301


def test_bunny_falls_back_to_a_procedural_mesh(tmp_path):
    with pytest.warns(RuntimeWarning, match="procedural stand-in"):
        mesh = bunny_mesh(100.0, data_dir=tmp_path)
    assert mesh.is_watertight and mesh.bounds[0][2] == pytest.approx(0.0)
    assert mesh.bounds[1][2] == pytest.approx(100.0)


def test_make_object_names():
    assert set(OBJECTS) == {"sphere", "hemisphere", "multi", "bunny", "bumpy"}
    with pytest.raises(ValueError, match="object must be one of"):
        make_object("teapot")
    sphere = make_object("sphere")
    assert sphere.height_mm == 80.0 and len(sphere.markers_mm) == 2


def test_hemisphere_highlight_sharpens_from_left_to_right():
    """Zickler et al. 2005, Fig. 5: mirror-symmetric lights put the highlight on the left and on
    the right half of the dome; only the roughness differs there, so the smoother right side
    shows a brighter, smaller highlight (GGX peak ~ 1 / alpha^2: alpha ~0.31 vs ~0.14)."""
    from sims.world import SimWorld, light_position
    cam = default_camera(200, 150, fov_deg=12.0, target_mm=(0, 0, 20))
    world = SimWorld("hemisphere", camera=cam, platter=False)
    peaks, areas = [], []
    for az in (-60.0, 60.0):
        state = {"light_position_mm": tuple(light_position(az, 30.0))}
        # the specular reflection alone: parallel minus crossed analyser (lamp polarized at 0 deg)
        spec = (world.radiance({**state, "polarizer_angle_deg": 0.0})
                - world.radiance({**state, "polarizer_angle_deg": 90.0})).mean(axis=2)
        peak = np.unravel_index(np.argmax(spec), spec.shape)
        y_obj = world.ground_truth(state).buffers.position[peak][1]
        assert np.sign(y_obj) == np.sign(az)  # the highlight is on the lamp's side
        peaks.append(spec.max())
        areas.append(int((spec > 0.5 * spec.max()).sum()))
    assert peaks[1] > 3 * peaks[0] and areas[1] < areas[0] / 2
