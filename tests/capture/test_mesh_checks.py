"""``--mesh`` files a user really passes (issue 19 #8): each bad one is refused naming the file
and the problem, before any work; units and placement are checked against the calibrated camera."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from capture.pipeline.mesh_checks import MeshError, check_mesh_placement, load_mesh
from reconstruct.camera import CameraModel

CAMERA = CameraModel.look_at((0.0, -700.0, 250.0), (0.0, 0.0, 40.0), width=320, height=240, fov_deg=30.0)
BOX = trimesh.creation.box((60.0, 60.0, 80.0))          # an object on the turntable, mm


def _ply(vertices, faces) -> str:
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    return head + "".join(" ".join(map(str, v)) + "\n" for v in vertices) + "".join(
        f"3 {a} {b} {c}\n" for a, b, c in faces)


TRI = [[0, 0, 0], [10, 0, 0], [0, 10, 0]]
BAD_FILES = {
    "photo.png": b"\x89PNG\r\n\x1a\n" + bytes(200),
    "notes.obj": b"this is not a mesh at all\n",
    "noise.ply": np.random.default_rng(1).bytes(4096),
    "empty.glb": b"",
    "mesh": _ply(TRI, [[0, 1, 2]]).encode(),
    "index.ply": _ply(TRI, [[0, 1, 99]]).encode(),
    "nan.ply": _ply([[0, 0, 0], [10, "nan", 0], [0, 10, "inf"]], [[0, 1, 2]]).encode(),
    "flat.ply": _ply([[0, 0, 0], [10, 0, 0], [20, 0, 0]], [[0, 1, 2]]).encode(),
}
WORDS = {"photo.png": "'.png' is not a mesh format", "notes.obj": "holds no triangles",
         "noise.ply": "not a readable .ply mesh", "empty.glb": "not a readable .glb mesh|holds no triangles",
         "mesh": "no file extension", "index.ply": "face indices run from 0 to 99 but there are 3 vertices",
         "nan.ply": "2 of 3 vertices are NaN or infinite", "flat.ply": "zero area"}


@pytest.mark.parametrize("name", list(BAD_FILES))
def test_a_bad_mesh_file_is_refused_naming_the_file(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(BAD_FILES[name])
    with pytest.raises(MeshError, match=WORDS[name]) as err:
        load_mesh(path)
    assert str(path) in str(err.value)


def test_missing_folder_and_inward_faces_are_named(tmp_path):
    with pytest.raises(MeshError, match="does not exist"):
        load_mesh(tmp_path / "none.ply")
    with pytest.raises(MeshError, match="is a folder"):
        load_mesh(tmp_path)
    inverted = BOX.copy()
    inverted.invert()
    inverted.export(tmp_path / "inverted.ply")
    with pytest.raises(MeshError, match="wound inward"):
        load_mesh(tmp_path / "inverted.ply")


def test_a_good_mesh_reads_and_passes_the_placement_check(tmp_path):
    box = BOX.copy()
    box.apply_translation([0.0, 0.0, 40.0])
    box.export(tmp_path / "box.ply")
    mesh = load_mesh(tmp_path / "box.ply")
    assert np.allclose(mesh.bounds, box.bounds) and mesh.volume > 0
    check_mesh_placement(mesh, CAMERA)


@pytest.mark.parametrize("change, words", [
    (lambda m: m.apply_scale(0.001), r"0.08 mm across .* in metres\? .* x1000 gives 80 mm"),
    (lambda m: m.apply_translation([1000.0, 0.0, 0.0]), "centre is 1000 mm from the turntable axis"),
    (lambda m: m.apply_scale(100.0), "more than twice the camera's distance"),
    (lambda m: m.apply_translation([0.0, 0.0, 600.0]), "projects outside the calibrated camera's image"),
])
def test_units_and_placement_are_checked_against_the_calibrated_camera(change, words):
    mesh = BOX.copy()
    mesh.apply_translation([0.0, 0.0, 40.0])
    change(mesh)
    with pytest.raises(MeshError, match=words):
        check_mesh_placement(mesh, CAMERA)
