"""Ground-truth objects for the simulated turntable, with their (spatially varying) BRDFs.

Object frame = the turntable frame at turntable angle 0: origin on the rotation axis at the
platter surface, +z up the axis, millimetres. Objects sit on the platter (lowest point at
z = 0, centred on the axis). At turntable angle ``a`` the object frame is rotated by
``Rz(a)`` (counter-clockwise seen from above, right-handed about +z): see
:func:`turntable_pose`.

Materials are pose-independent: they are looked up through the surface's own ``uv`` (analytic
spheres) or its ``face_index`` (meshes), never through world positions, so the reflectance
painted on the object turns with it.
"""
from __future__ import annotations

import functools
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from reconstruct.brdf import BRDF, CookTorrance, Lafortune, Lambertian, OrenNayar
from reconstruct.raycast import Hemisphere, Mesh, Sphere, Surface
from reconstruct.render import MaterialMap, SceneObject

#: Names accepted by :func:`make_object` (and ``gonio sim render --object``).
OBJECTS = ("sphere", "hemisphere", "multi", "bunny", "bumpy")
#: Default ceramic-like glaze of the single-material objects.
GLAZE = CookTorrance(kd=(0.60, 0.52, 0.45), f0=0.04, alpha=0.15)


def shared_data_dir() -> Path | None:
    """The folder of real data shipped beside the repository: ``$GONIO_DATA`` if set, else
    ``<repo>/../shared/data``; None when it does not exist."""
    env = os.environ.get("GONIO_DATA")
    path = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"
    return path if path.is_dir() else None


def turntable_pose(angle_deg: float) -> np.ndarray:
    """Object -> world 4x4 matrix at turntable ``angle_deg``: a rotation about world +z."""
    if not np.isfinite(angle_deg):
        raise ValueError(f"turntable angle must be a finite number of degrees, got {angle_deg!r}")
    a = np.radians(angle_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


@dataclass
class Part:
    """One surface of an object (placed in the object frame by ``surface.transform``)."""

    surface: Surface
    material: object
    name: str


@dataclass
class GroundTruthObject:
    """An object on the turntable: surfaces with ground-truth materials, plus facts for tests.

    Attributes
    ----------
    name : str
    parts : list of Part
        Surfaces in the object frame and their materials (BRDF, MaterialMap or callable).
    markers_mm : ndarray of shape (K, 3)
        Object-frame centres of small dark marker dots painted on the surface (features whose
        image position tests can predict); may be empty.
    height_mm : float
        Height of the object above the platter (for framing the camera).
    radius_mm : float
        Largest distance of the object from the turntable axis.
    """

    name: str
    parts: list[Part]
    markers_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    height_mm: float = 0.0
    radius_mm: float = 0.0

    def scene_objects(self, angle_deg: float = 0.0) -> list[SceneObject]:
        """The parts placed at turntable ``angle_deg`` (world frame), for a render Scene."""
        T = turntable_pose(angle_deg)
        return [SceneObject(p.surface.with_transform(T @ p.surface.transform), p.material,
                            f"{self.name}:{p.name}") for p in self.parts]

    def markers_world(self, angle_deg: float) -> np.ndarray:
        """Marker centres at turntable ``angle_deg`` in the world frame, (K, 3) mm."""
        T = turntable_pose(angle_deg)
        return self.markers_mm @ T[:3, :3].T + T[:3, 3]


# ----------------------------------------------------------------------------------------------
# sphere
# ----------------------------------------------------------------------------------------------
def _sphere_dirs(uv: np.ndarray) -> np.ndarray:
    """Object-frame unit directions of raycast.Sphere uv (u = azimuth / 2 pi, v = polar / pi)."""
    phi, theta = 2 * np.pi * uv[:, 0], np.pi * uv[:, 1]
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)


def make_sphere(radius_mm: float = 40.0, material: BRDF = GLAZE, *,
                marker_dirs=((1.0, 0.0, 0.0), (0.0, 0.7, 0.7)), marker_radius_mm: float = 2.5,
                marker_albedo: float = 0.02) -> GroundTruthObject:
    """A sphere resting on the platter (centre at z = radius) with one BRDF and small dark
    Lambertian marker dots at the given object-frame directions from its centre."""
    if not radius_mm > 0:
        raise ValueError(f"radius_mm must be > 0, got {radius_mm!r}")
    dirs = np.asarray(marker_dirs, dtype=np.float64).reshape(-1, 3)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) if len(dirs) else dirs
    center = np.array([0.0, 0.0, radius_mm])
    cos_dot = np.cos(marker_radius_mm / radius_mm)
    dot = Lambertian(marker_albedo)

    def ids(position, uv, face_index):
        if len(dirs) == 0:
            return np.zeros(len(uv), dtype=np.int64)
        d = _sphere_dirs(uv)  # one matrix-vector product per marker (no multithreaded GEMM)
        return (np.max([d @ m for m in dirs], axis=0) > cos_dot).astype(np.int64)

    part = Part(Sphere(radius_mm, center), MaterialMap([material, dot], ids), "sphere")
    return GroundTruthObject("sphere", [part], markers_mm=center + radius_mm * dirs,
                             height_mm=2 * radius_mm, radius_mm=radius_mm)


# ----------------------------------------------------------------------------------------------
# hemisphere with linearly varying roughness (Zickler et al. 2005, Fig. 5)
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RoughnessRamp:
    """Cook-Torrance material whose roughness ``alpha`` varies linearly with object-frame y over
    a hemisphere of ``radius_mm``: ``alpha = alpha_left`` at y = -r to ``alpha_right`` at y = +r,
    i.e. left to right as the default camera (on the +x side) sees it at turntable angle 0 (the
    reflectance-sharing paper's synthetic test, Fig. 5: the highlight sharpens from left to
    right across the surface)."""

    radius_mm: float = 40.0
    alpha_left: float = 0.40
    alpha_right: float = 0.05
    kd: tuple = (0.35, 0.25, 0.20)
    f0: float = 0.04

    def __post_init__(self) -> None:
        if not (self.alpha_left > 0 and self.alpha_right > 0):
            raise ValueError(f"alpha_left and alpha_right must be > 0, got {self.alpha_left!r}, {self.alpha_right!r}")

    def alpha_at(self, points_obj: np.ndarray) -> np.ndarray:
        """Ground-truth roughness at object-frame points (N, 3) mm -> (N,)."""
        y = np.clip(np.asarray(points_obj, float).reshape(-1, 3)[:, 1] / self.radius_mm, -1, 1)
        return self.alpha_left + (self.alpha_right - self.alpha_left) * (y + 1) / 2

    def brdf_at(self, points_obj: np.ndarray) -> CookTorrance:
        """The ground-truth BRDF at object-frame points (per-sample parameters)."""
        return CookTorrance(kd=self.kd, f0=self.f0, alpha=self.alpha_at(points_obj))

    def __call__(self, position, uv, face_index) -> CookTorrance:
        return self.brdf_at(self.radius_mm * _sphere_dirs(np.asarray(uv, float)))


def make_hemisphere(ramp: RoughnessRamp | None = None) -> GroundTruthObject:
    """A dome (open at the base, resting on the platter, axis = the turntable axis) with a
    Cook-Torrance BRDF of linearly varying roughness (:class:`RoughnessRamp`)."""
    ramp = RoughnessRamp() if ramp is None else ramp
    part = Part(Hemisphere(ramp.radius_mm), ramp, "dome")
    return GroundTruthObject("hemisphere", [part], height_mm=ramp.radius_mm, radius_mm=ramp.radius_mm)


# ----------------------------------------------------------------------------------------------
# meshes: bunny and the multi-material object
# ----------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=4)
def _load_mesh(path: str) -> trimesh.Trimesh:
    mesh = trimesh.load(path, force="mesh", process=True)
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path} holds no triangle mesh")
    return mesh


def _procedural_blob() -> trimesh.Trimesh:
    """A lumpy closed mesh (icosphere displaced by low-order harmonics), ~1 unit tall, y up."""
    m = trimesh.creation.icosphere(subdivisions=5)
    v = m.vertices
    r = 1.0 + 0.18 * v[:, 0] * v[:, 1] + 0.12 * np.sin(3 * v[:, 2]) + 0.1 * v[:, 1] ** 3
    return trimesh.Trimesh(v * r[:, None] * [0.6, 0.5, 0.45], m.faces, process=True)


def bunny_mesh(height_mm: float = 120.0, *, full: bool = True,
               data_dir: str | Path | None = None) -> trimesh.Trimesh:
    """The Stanford bunny in the object frame: z up (the scan's +y), ``height_mm`` tall, resting
    on z = 0, bounding box centred on the axis. ``full``: the 69k-face ``bun_zipper.ply`` (else
    the reduced 16k-face ``trimesh_bunny.ply``). Without the data folder a procedural blob stands
    in, with a warning saying so."""
    if not height_mm > 0:
        raise ValueError(f"height_mm must be > 0, got {height_mm!r}")
    base = Path(data_dir) if data_dir is not None else shared_data_dir()
    name = "bun_zipper.ply" if full else "trimesh_bunny.ply"
    path = None if base is None else base / "meshes" / name
    if path is not None and path.is_file():
        src = _load_mesh(str(path))
    else:
        warnings.warn(f"bunny mesh {name} not found (looked in {path or '$GONIO_DATA / ../shared/data'}); "
                      "using a procedural stand-in mesh", RuntimeWarning, stacklevel=2)
        src = _procedural_blob()
    v = src.vertices[:, [0, 2, 1]] * [1.0, -1.0, 1.0]  # scan y-up -> z-up, keeping handedness
    lo, hi = v.min(axis=0), v.max(axis=0)
    s = height_mm / (hi[2] - lo[2])
    v = (v - [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]) * s
    return trimesh.Trimesh(v, src.faces, process=False)


def _mesh_object(name, mesh, material) -> GroundTruthObject:
    r = float(np.linalg.norm(mesh.vertices[:, :2], axis=1).max())
    return GroundTruthObject(name, [Part(Mesh(mesh), material, name)],
                             height_mm=float(mesh.vertices[:, 2].max()), radius_mm=r)


def make_bunny(material=GLAZE, *, height_mm: float = 120.0, full: bool = True,
               data_dir: str | Path | None = None) -> GroundTruthObject:
    """The bunny with one material (default: a glazed-ceramic Cook-Torrance)."""
    return _mesh_object("bunny", bunny_mesh(height_mm, full=full, data_dir=data_dir), material)


#: The materials of :func:`make_multi_material`, in id order.
MULTI_MATERIALS: tuple[BRDF, ...] = (
    CookTorrance(kd=(0.55, 0.08, 0.06), f0=0.04, alpha=0.12),               # red plastic
    OrenNayar(albedo=(0.15, 0.25, 0.55), sigma=0.35),                          # blue matte paint
    CookTorrance(kd=0.02, f0=(0.90, 0.70, 0.30), alpha=0.25),                 # brushed gold
    Lafortune.phong(rho_d=(0.12, 0.40, 0.15), rho_s=0.4, exponent=30.0),     # green glossy
)


def region_ids(points_obj: np.ndarray, height_mm: float) -> np.ndarray:
    """Ground-truth material id of object-frame points (N, 3): four regions, upper/lower half
    (split at 45 % of the height) x the sign of x -> (N,) in 0..3."""
    p = np.asarray(points_obj, float).reshape(-1, 3)
    return (2 * (p[:, 2] > 0.45 * height_mm) + (p[:, 0] > 0)).astype(np.int64)


def make_multi_material(base: str = "bunny", *, height_mm: float = 120.0,
                        data_dir: str | Path | None = None) -> GroundTruthObject:
    """An object painted with the four :data:`MULTI_MATERIALS` by region (:func:`region_ids` of
    each face's centroid): the bunny (``base="bunny"``) or a sphere mesh (``"sphere"``)."""
    if base == "bunny":
        mesh = bunny_mesh(height_mm, data_dir=data_dir)
    elif base == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=5, radius=height_mm / 2)
        mesh.apply_translation([0, 0, height_mm / 2])
    else:
        raise ValueError(f"base must be 'bunny' or 'sphere', got {base!r}")
    ids = region_ids(mesh.triangles_center, height_mm)
    return _mesh_object("multi", mesh, MaterialMap(list(MULTI_MATERIALS), ids))


def make_object(name: str, **kwargs) -> GroundTruthObject:
    """One of :data:`OBJECTS` by name, with its default parameters (``kwargs`` passed on)."""
    makers = {"sphere": make_sphere, "hemisphere": make_hemisphere,
              "multi": make_multi_material, "bunny": make_bunny, "bumpy": make_bumpy}
    if name not in makers:
        raise ValueError(f"object must be one of {OBJECTS}, got {name!r}")
    return makers[name](**kwargs)


# ----------------------------------------------------------------------------------------------
# bumpy multi-material object (Lensch et al. 2003: detail in the surface, not in the mesh)
# ----------------------------------------------------------------------------------------------
#: The materials of :func:`make_bumpy`, in id order (single-lobe Lafortune, as the paper fits).
BUMPY_MATERIALS: tuple[Lafortune, ...] = (
    Lafortune.phong(rho_d=(0.55, 0.12, 0.08), rho_s=0.5, exponent=25.0),     # red glossy
    Lafortune.phong(rho_d=(0.10, 0.20, 0.50), rho_s=0.8, exponent=70.0),     # blue shiny
    Lafortune(rho_d=(0.30, 0.25, 0.10), cx=[[-1.02, -0.99, -0.93]], cz=[[0.95, 0.93, 0.88]],
              n=[[12.0, 12.0, 12.0]]),                                        # gold-ish, off-specular
)


@dataclass
class BumpyObject(GroundTruthObject):
    """A sphere with raised bumps and an engraved groove, painted with :data:`BUMPY_MATERIALS`.

    ``parts`` render the displaced high-resolution mesh; ``fitter_mesh`` is the smooth sphere a
    reconstruction is handed (the detail is in the images, not in this mesh).
    :meth:`normal_at` / :meth:`material_at` give the ground truth at object-frame points (looked up
    by their direction from the sphere's centre, so points on either mesh work).
    """

    fitter_mesh: trimesh.Trimesh | None = None
    center_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sphere_radius_mm: float = 0.0
    bump_centers: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bump_height_mm: float = 0.0
    bump_sigma_rad: float = 0.1
    groove_depth_mm: float = 0.0
    groove_width_rad: float = 0.05
    materials: tuple = ()

    def _dirs(self, points) -> np.ndarray:
        d = np.asarray(points, float).reshape(-1, 3) - self.center_mm
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def height(self, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Displacement h (N,) mm along the unit ``dirs`` (N, 3) and its gradient on the sphere
        (N, 3) (tangent, mm per radian): Gaussian bumps in the angle from each bump centre, minus a
        Gaussian groove around the circle of latitude z = 0.35 (an engraved ring)."""
        h = np.zeros(len(dirs))
        grad = np.zeros((len(dirs), 3))
        for c in self.bump_centers:  # a few dozen bumps, vectorised over points
            cosang = np.clip(dirs @ c, -1, 1)
            ang = np.arccos(cosang)
            g = self.bump_height_mm * np.exp(-0.5 * (ang / self.bump_sigma_rad) ** 2)
            h += g
            # d ang / d dir along the tangent towards c: -(c - cos d) / sin
            sin = np.maximum(np.sqrt(1 - cosang ** 2), 1e-9)
            tangent_to_c = (c - cosang[:, None] * dirs) / sin[:, None]
            grad += (g * ang / self.bump_sigma_rad ** 2)[:, None] * tangent_to_c
        lat = np.arcsin(np.clip(dirs[:, 2], -1, 1)) - np.arcsin(0.35)
        gg = -self.groove_depth_mm * np.exp(-0.5 * (lat / self.groove_width_rad) ** 2)
        h += gg
        up = np.array([0.0, 0.0, 1.0]) - dirs[:, 2:3] * dirs  # d lat direction (unnormalised)
        up /= np.maximum(np.linalg.norm(up, axis=1, keepdims=True), 1e-9)
        grad += (-gg * lat / self.groove_width_rad ** 2)[:, None] * up
        return h, grad

    def normal_at(self, points) -> np.ndarray:
        """True unit normals (N, 3) of the displaced surface at the directions of ``points``."""
        d = self._dirs(points)
        h, grad = self.height(d)
        r = self.sphere_radius_mm + h
        n = d - grad / r[:, None]  # normal of r(d) = R + h(d): d - grad_s h / r
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def material_at(self, points) -> np.ndarray:
        """Material id (N,) at ``points``: three bands in azimuth about the axis."""
        d = self._dirs(points)
        az = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
        return (az // (2 * np.pi / 3)).astype(np.int64) % 3


def make_bumpy(radius_mm: float = 40.0, *, n_bumps: int = 40, bump_height_mm: float = 0.8,
               bump_sigma_mm: float = 3.5, groove_depth_mm: float = 0.6, groove_width_mm: float = 1.5,
               subdivisions: int = 6, fitter_subdivisions: int = 4, seed: int = 0) -> BumpyObject:
    """A sphere on the platter with fine relief the fitter's mesh lacks (Lensch 2003, Sec. 9).

    The rendered surface is an icosphere of ``subdivisions`` (default 6: 82k faces, ~0.7 mm edges)
    displaced by ``n_bumps`` Gaussian bumps (height ``bump_height_mm``, width ``bump_sigma_mm``) and
    an engraved ring; ``fitter_mesh`` is the undisplaced icosphere of ``fitter_subdivisions``.
    Three materials in azimuth bands (:meth:`BumpyObject.material_at`).
    """
    if not radius_mm > 0:
        raise ValueError(f"radius_mm must be > 0, got {radius_mm!r}")
    rng = np.random.default_rng(seed)
    centers = rng.normal(size=(n_bumps, 3))
    centers /= np.linalg.norm(centers, axis=1, keepdims=True)
    center = np.array([0.0, 0.0, radius_mm + bump_height_mm])
    obj = BumpyObject(name="bumpy", parts=[], height_mm=2 * (radius_mm + bump_height_mm),
                      radius_mm=radius_mm + bump_height_mm, center_mm=center,
                      sphere_radius_mm=radius_mm, bump_centers=centers,
                      bump_height_mm=bump_height_mm, bump_sigma_rad=bump_sigma_mm / radius_mm,
                      groove_depth_mm=groove_depth_mm, groove_width_rad=groove_width_mm / radius_mm,
                      materials=BUMPY_MATERIALS)
    fine = trimesh.creation.icosphere(subdivisions=subdivisions)
    h, _ = obj.height(fine.vertices)
    detailed = trimesh.Trimesh(fine.vertices * (radius_mm + h)[:, None] + center, fine.faces, process=False)
    smooth = trimesh.creation.icosphere(subdivisions=fitter_subdivisions, radius=radius_mm)
    obj.fitter_mesh = trimesh.Trimesh(smooth.vertices + center, smooth.faces, process=False)
    ids = obj.material_at(detailed.triangles_center)
    obj.parts = [Part(Mesh(detailed), MaterialMap(list(BUMPY_MATERIALS), ids), "bumpy")]
    return obj
