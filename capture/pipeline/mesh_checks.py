"""The object's mesh (``gonio process --mesh FILE``): read it, refuse what cannot be right, and
check its units and placement against the session's calibration.

A mesh is in the object frame, which is the lab frame at turntable reading 0, in millimetres
(``docs/architecture.md``). What goes wrong in practice: a file that is no mesh (a PNG, text,
random bytes, an empty ``.glb``, no extension), face indices past the vertices, NaN or infinite
vertices, faces wound inward, a mesh in metres (1000 x too small) or placed far from the
turntable, where the calibrated camera never saw it. Each is a :class:`MeshError` that names the
file and says what looks wrong, before any reconstruction work.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from .process import ProcessError

__all__ = ["MeshError", "load_mesh", "check_mesh_placement", "MESH_SUFFIXES"]

#: extensions trimesh reads meshes from (its loader picks the parser by extension)
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf", ".dae", ".3mf")
#: smallest believable object, as a fraction of the camera's distance from the lab origin
MIN_SIZE_OF_DISTANCE = 0.01
#: a mesh whose centre lies further from the turntable axis than this fraction of the camera's
#: distance (and than its own size) is not on the turntable
MAX_OFFSET_OF_DISTANCE = 0.5


class MeshError(ProcessError):
    """The mesh file is unreadable or its geometry cannot be the object's; names the file."""


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """The mesh in ``path`` (object frame, mm), checked: triangles, indices, finite vertices,
    non-zero area, outward winding when closed.

    Raises
    ------
    MeshError
        Names the file and the problem.
    """
    path = Path(path)
    where = f"--mesh {path}"
    if not path.is_file():
        raise MeshError(f"{where}: " + ("is a folder, not a mesh file" if path.is_dir() else "does not exist"))
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise MeshError(f"{where}: {'no file extension' if not path.suffix else f'{path.suffix!r} is not a mesh format'}; "
                        f"trimesh picks its reader by extension: {', '.join(MESH_SUFFIXES)}")
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh's parsers raise anything on bad bytes
        raise MeshError(f"{where}: not a readable {path.suffix} mesh ({type(exc).__name__}: "
                        f"{str(exc)[:200] or 'no detail'})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError(f"{where}: holds no triangles")
    vertices = np.asarray(loaded.vertices, dtype=float)
    faces = np.asarray(loaded.faces)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{where}: face indices run from {faces.min()} to {faces.max()} but there are "
                        f"{len(vertices)} vertices")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshError(f"{where}: {int(bad.sum())} of {len(vertices)} vertices are NaN or infinite "
                        f"(first: vertex {int(np.flatnonzero(bad)[0])})")
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=True)
    if mesh.area <= 0 or len(mesh.faces) == 0:
        raise MeshError(f"{where}: every triangle has zero area")
    if mesh.is_watertight and mesh.volume < 0:
        raise MeshError(f"{where}: the faces are wound inward (normals point into the object; "
                        f"volume {mesh.volume:.3g} mm^3); flip them (trimesh.repair.fix_inversion)")
    return mesh


def check_mesh_placement(mesh: trimesh.Trimesh, camera, source: str = "the mesh") -> None:
    """Check the mesh against the calibrated camera (``reconstruct.camera.CameraModel``, lab
    frame, mm): its size must be believable at the camera's distance (metres instead of mm is
    1000 x too small), its centre near the turntable axis, and it must project into the image.

    Raises
    ------
    MeshError
        Says what looks wrong and by how much.
    """
    distance = float(np.linalg.norm(camera.center))
    lo, hi = mesh.bounds
    size = float(np.max(hi - lo))
    centre = (lo + hi) / 2
    if size < MIN_SIZE_OF_DISTANCE * distance:
        raise MeshError(f"{source} is {size:.3g} mm across while the calibrated camera is {distance:.0f} mm "
                        f"from the turntable: is it in metres? (the mesh must be in mm; x1000 gives "
                        f"{size * 1000:.3g} mm)")
    if size > 2 * distance:
        raise MeshError(f"{source} is {size:.3g} mm across, more than twice the camera's distance "
                        f"({distance:.0f} mm): wrong units?")
    offset = float(np.linalg.norm(centre[:2]))
    if offset > max(MAX_OFFSET_OF_DISTANCE * distance, size):
        raise MeshError(f"{source}'s centre is {offset:.0f} mm from the turntable axis (x {centre[0]:.0f}, "
                        f"y {centre[1]:.0f} mm) with the object {size:.0f} mm across: it must be placed "
                        "in the object frame (the lab frame at turntable reading 0, origin on the axis)")
    corners = trimesh.bounds.corners(mesh.bounds)
    px = camera.project(corners)
    inside = ((px[:, 0] >= 0) & (px[:, 0] < camera.width) & (px[:, 1] >= 0) & (px[:, 1] < camera.height)
              & (camera.depth(corners) > 0))
    centre_px = camera.project(centre[None])[0]
    if not inside.any() and not (0 <= centre_px[0] < camera.width and 0 <= centre_px[1] < camera.height):
        raise MeshError(f"{source} projects outside the calibrated camera's image (its centre at pixel "
                        f"({centre_px[0]:.0f}, {centre_px[1]:.0f}) of {camera.width} x {camera.height}): "
                        "check its placement and units")
