"""Ray casting against triangle meshes (Embree through embreex) and analytic surfaces.

One place for every ray query of the project: camera rays of the renderer, shadow and visibility
tests of lumitexel assembly, reflection rays of mirror surfaces.

Frames and units: everything here is in the world (turntable) frame, millimetres, unless a
name says ``local``. Every surface carries ``transform``, a 4x4 object -> world affine matrix
(rigid motion, optionally with scale). Rays are taken into the object frame with the inverse
transform *without* renormalising the direction, so the ray parameter ``t`` is the same in both
frames: a hit lies at ``origin + t * direction`` in the world (``t`` is a distance in mm when
``direction`` is a unit vector).

Meshes are intersected by Embree (float32, single precision). Their vertices are re-centred on
the bounding-box centre before the conversion to float32 so that precision scales with the
object, not with its distance from the world origin; hit positions are recomputed in float64
from the barycentric coordinates. Shadow rays that start on a surface must still be offset:
:func:`occluded` does it when given the surface normals (scale-aware epsilon along the
geometric normal, on the side the ray leaves).
"""
from __future__ import annotations

import copy
import threading
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import trimesh

from .frames import linear_rows

try:  # Embree: ~100-3500x faster than trimesh's pure-Python intersector and bounded in memory
    from embreex import rtcore_scene as _rtcs
    from embreex.mesh_construction import TriangleMesh as _EmbreeTriangles
    HAVE_EMBREE = True
except ImportError:  # pragma: no cover - exercised only on machines without the embreex wheel
    HAVE_EMBREE = False

#: Relative size of the origin offset of secondary rays (times the scene scale, mm).
OFFSET_EPS = 1e-5
#: Rays per call of the pure-Python fallback (it needs ~0.4 MB per ray).
_FALLBACK_CHUNK = 2000
#: Serialises the lazy builds (BVH, per-pose tables) when a frame is rendered on threads.
_BUILD_LOCK = threading.Lock()


class SlowRaycastWarning(RuntimeWarning):
    """Embree (embreex) is not installed: meshes are intersected by trimesh's pure-Python path."""


# ----------------------------------------------------------------------------------------------
# hits
# ----------------------------------------------------------------------------------------------
@dataclass(eq=False)
class Hits:
    """First intersections of N rays with a set of surfaces (world frame, mm).

    Attributes
    ----------
    t : ndarray of shape (N,), float64
        Ray parameter of the hit (mm for unit directions); ``inf`` where nothing was hit.
    position : ndarray of shape (N, 3), float64
        Hit point, world frame, mm; NaN where nothing was hit.
    normal : ndarray of shape (N, 3), float64
        Unit shading normal, world frame: interpolated vertex normals for smooth meshes, the
        analytic normal for spheres/planes. Outward (as stored), not flipped towards the ray.
        Zero where nothing was hit.
    geometric_normal : ndarray of shape (N, 3), float64
        Unit normal of the hit face (mesh) or analytic normal, world frame, outward. Zero on misses.
    uv : ndarray of shape (N, 2), float64
        Surface parameterisation: the mesh's texture coordinates interpolated (NaN when the mesh
        has none); for analytic surfaces see their classes. NaN on misses.
    face_index : ndarray of shape (N,), int64
        Triangle hit (meshes); -1 for analytic surfaces and misses.
    surface_index : ndarray of shape (N,), int64
        Index into the ``surfaces`` sequence; -1 on misses.
    mask : ndarray of shape (N,), bool
        True where a surface was hit.
    """

    t: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    geometric_normal: np.ndarray
    uv: np.ndarray
    face_index: np.ndarray
    surface_index: np.ndarray
    mask: np.ndarray

    def __len__(self) -> int:
        return len(self.t)


# ----------------------------------------------------------------------------------------------
# surfaces
# ----------------------------------------------------------------------------------------------
def _check_transform(transform) -> np.ndarray:
    T = np.eye(4) if transform is None else np.asarray(transform, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"transform must be a 4x4 object->world matrix, got shape {T.shape}")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(f"transform must be affine (last row 0 0 0 1), got last row {T[3]}")
    if abs(np.linalg.det(T[:3, :3])) < 1e-12:
        raise ValueError("transform is singular (its 3x3 part has zero determinant)")
    return T


class Surface:
    """Base of the intersectable surfaces.

    Subclasses implement, in their object frame, ``_intersect`` (ray parameter and a primitive
    index with two surface parameters) and ``_attributes`` (position, normals, uv), or
    ``_hit_world`` directly in the world frame (meshes: per-pose face tables).
    """

    transform: np.ndarray

    def __init__(self, transform=None):
        self._set_transform(transform)

    def _set_transform(self, transform) -> None:
        self.transform = _check_transform(transform)
        self._identity = bool(np.array_equal(self.transform, np.eye(4)))
        self._inv = np.linalg.inv(self.transform)
        self._normal_matrix = self._inv[:3, :3].T  # inverse-transpose takes normals to the world

    def with_transform(self, transform) -> "Surface":
        """The same surface placed with another 4x4 object -> world ``transform`` (shares caches:
        a mesh's acceleration structure is built once and reused for every pose)."""
        other = copy.copy(self)
        other._set_transform(transform)
        return other

    @property
    def bounding_radius(self) -> float:
        """Radius of a world-frame sphere about the world origin containing the surface (mm);
        ``inf`` for unbounded surfaces. Used for the scale of ray offsets."""
        raise NotImplementedError

    # object frame ------------------------------------------------------------------------------
    def _intersect(self, o, d, t_max):  # pragma: no cover - abstract
        """Local rays (N, 3) -> (t (N,) with inf on misses, prim (N,) int, b1 (N,), b2 (N,))."""
        raise NotImplementedError

    def _attributes(self, o, d, t, prim, b1, b2):  # pragma: no cover - abstract
        """-> (position, geometric normal, shading normal, uv) in the object frame (unnormalised
        normals allowed)."""
        raise NotImplementedError

    def _occluded(self, o, d, t_max):
        """Any hit of local rays with 0 < t < t_max -> (N,) bool."""
        return np.isfinite(self._intersect(o, d, t_max)[0])

    # world frame ------------------------------------------------------------------------------
    def _to_local(self, origins, dirs):
        if self._identity:
            return origins, dirs
        A, b = self._inv[:3, :3], self._inv[:3, 3]
        if len(origins) and origins.strides[0] == 0:  # one shared origin: transform it once
            o = np.broadcast_to(A @ origins[0] + b, origins.shape)
        else:
            o = linear_rows(A, origins) + b
        return o, linear_rows(A, dirs)

    def _to_world(self, p, ng, ns):
        """Object-frame points and (unnormalised) normals -> world points and unit normals."""
        if self._identity:
            return p, _unit(ng), _unit(ns)
        return (linear_rows(self.transform[:3, :3], p) + self.transform[:3, 3],
                _unit(linear_rows(self._normal_matrix, ng)), _unit(linear_rows(self._normal_matrix, ns)))

    def _hit_world(self, o, d, t, prim, b1, b2):
        """World rays (M, 3) and their hits -> float64 ``t`` (M,), position, unit geometric and
        shading normals (M, 3), uv (M, 2), all in the world frame. (Closed-form surfaces
        already have a float64 ``t``.)"""
        p, ng, ns, uv = self._attributes(*self._to_local(o, d), t, prim, b1, b2)
        return (t, *self._to_world(p, ng, ns), uv)

    def intersect(self, origins, dirs, t_max=None):
        """Ray parameters of the first hits of world rays (N, 3): ``t`` (N,) with ``inf`` on
        misses and hits beyond ``t_max`` (N,) or scalar."""
        o, d = self._to_local(*_check_rays(origins, dirs))
        t_max = np.broadcast_to(np.inf if t_max is None else t_max, (len(o),))
        return self._intersect(o, d, t_max)[0]


class Mesh(Surface):
    """A triangle mesh (``trimesh.Trimesh``) placed in the world by ``transform``.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Vertices in the object frame (mm after ``transform``).
    transform : ndarray of shape (4, 4), optional
        Object -> world affine matrix.
    smooth : bool
        Shading normal = vertex normals interpolated with the barycentric coordinates (default);
        False: the face normal.

    Notes
    -----
    ``uv`` of a hit is the mesh's texture coordinate (``mesh.visual.uv``) interpolated, or NaN.
    The mesh's arrays are copied at construction (trimesh re-hashes its arrays on every access);
    build a new ``Mesh`` after editing the trimesh.
    """

    def __init__(self, mesh: trimesh.Trimesh, transform=None, *, smooth: bool = True):
        if not isinstance(mesh, trimesh.Trimesh):
            raise TypeError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
        if len(mesh.faces) == 0:
            raise ValueError("mesh has no faces")
        super().__init__(transform)
        self.mesh = mesh
        self.smooth = smooth
        uv = getattr(mesh.visual, "uv", None)
        # plain arrays shared by with_transform copies (the Embree scene is added on first use)
        self._geom = {
            "vertices": np.array(mesh.vertices, dtype=np.float64),
            "faces": np.array(mesh.faces, dtype=np.int64),
            "face_normals": np.array(mesh.face_normals, dtype=np.float64),
            "vertex_normals": np.array(mesh.vertex_normals, dtype=np.float64),
            "uv": None if uv is None or len(uv) != len(mesh.vertices) else np.array(uv, float),
            "corners": trimesh.bounds.corners(mesh.bounds),
        }

    @property
    def bounding_radius(self) -> float:
        corners = self._geom["corners"] @ self.transform[:3, :3].T + self.transform[:3, 3]
        return float(np.linalg.norm(corners, axis=1).max())

    def _embree(self):
        """The Embree scene of the object-frame mesh (built once, shared by all poses) and the
        centre its float32 vertices are relative to."""
        g = self._geom
        with _BUILD_LOCK:
            if "scene" not in g:
                centre = g["corners"].mean(axis=0)
                scene = _rtcs.EmbreeScene()
                _EmbreeTriangles(scene=scene,
                                 vertices=(g["vertices"] - centre).astype(np.float32),
                                 indices=g["faces"].astype(np.int32))
                g["scene"] = (scene, centre)
        return g["scene"]

    def _embree_rays(self, o, d, t_max):
        """float32 origins (relative to the mesh centre), directions and far limits."""
        scene, centre = self._embree()
        if len(o) and o.strides[0] == 0:  # a shared origin (camera rays): subtract once
            o32 = np.ascontiguousarray(np.broadcast_to((o[0] - centre).astype(np.float32),
                                                       o.shape))
        else:
            o32 = (o - centre).astype(np.float32)
        # inf -> float32 max (Embree's "no limit")
        dists = np.minimum(t_max, np.finfo(np.float32).max).astype(np.float32)
        return scene, o32, d.astype(np.float32), dists

    def _intersect(self, o, d, t_max):
        if not HAVE_EMBREE:
            return self._intersect_fallback(o, d, t_max)
        scene, o32, d32, dists = self._embree_rays(o, d, t_max)
        out = scene.run(o32, d32, dists=dists, output=1)
        prim = out["primID"]
        t = np.where(prim >= 0, out["tfar"], np.float32(np.inf))
        # u, v stay float32: _hit_world recomputes the barycentrics in float64
        return t, prim.astype(np.int64), out["u"], out["v"]

    def _occluded(self, o, d, t_max):
        if not HAVE_EMBREE:
            return super()._occluded(o, d, t_max)
        scene, o32, d32, dists = self._embree_rays(o, d, t_max)
        return scene.run(o32, d32, dists=dists, query="OCCLUDED") >= 0

    def _intersect_fallback(self, o, d, t_max):
        _warn_slow()
        n = len(o)
        t = np.full(n, np.inf)
        prim = np.full(n, -1, dtype=np.int64)
        b1 = np.zeros(n)
        b2 = np.zeros(n)
        rt = trimesh.ray.ray_triangle.RayMeshIntersector(self.mesh)
        for s in range(0, n, _FALLBACK_CHUNK):
            sl = slice(s, s + _FALLBACK_CHUNK)
            loc, iray, itri = rt.intersects_location(o[sl], d[sl], multiple_hits=False)
            iray = iray + s
            tt = np.einsum("ij,ij->i", loc - o[iray], d[iray]) / np.einsum("ij,ij->i", d[iray],
                                                                          d[iray])
            ok = tt < t_max[iray]
            iray, itri, tt, loc = iray[ok], itri[ok], tt[ok], loc[ok]
            bary = trimesh.triangles.points_to_barycentric(self.mesh.triangles[itri], loc)
            t[iray], prim[iray], b1[iray], b2[iray] = tt, itri, bary[:, 1], bary[:, 2]
        return t, prim, b1, b2

    def _set_transform(self, transform) -> None:
        super()._set_transform(transform)
        self._world = None  # per-pose face tables (see _world_tables)

    def _world_tables(self) -> dict:
        """Per-face world-frame data for this pose: first vertex, unit face normal, the three
        corners' unit normals, and the dual edge vectors g1, g2 with barycentrics
        b1 = (p - v0) . g1, b2 = (p - v0) . g2 (O(F), computed once per pose)."""
        with _BUILD_LOCK:
            if self._world is None:
                self._world = self._compute_world_tables()
        return self._world

    def _compute_world_tables(self) -> dict:
        g = self._geom
        A, b = self.transform[:3, :3], self.transform[:3, 3]
        tri = (linear_rows(A, g["vertices"]) + b)[g["faces"]]
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        d11, d12, d22 = (np.einsum("ij,ij->i", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
        den = d11 * d22 - d12 * d12
        inv = np.divide(1.0, den, out=np.zeros_like(den), where=np.abs(den) > 0)
        return {
            "v0": tri[:, 0], "normal": _unit(linear_rows(self._normal_matrix, g["face_normals"])),
            "g1": (d22[:, None] * e1 - d12[:, None] * e2) * inv[:, None],
            "g2": (d11[:, None] * e2 - d12[:, None] * e1) * inv[:, None],
            "ok": inv != 0,  # degenerate faces keep Embree's barycentrics
            # per face, its three corners' unit normals (F, 3, 3): one gather per hit
            "corner_normals": _unit(linear_rows(self._normal_matrix,
                                                g["vertex_normals"]))[g["faces"]],
        }

    def _hit_world(self, o, d, t, prim, b1, b2):
        wt = self._world_tables()
        v0, ng = wt["v0"][prim], wt["normal"][prim]
        # Embree's t and barycentrics are float32: redo the ray-plane hit and the barycentrics
        # in float64 so positions lie on the ray and on the face to ~1e-12 relative
        dn = np.einsum("ij,ij->i", d, ng)
        ok = np.abs(dn) > 1e-12 * np.sqrt(np.einsum("ij,ij->i", d, d))
        t = np.where(ok, np.einsum("ij,ij->i", v0 - o, ng) / np.where(ok, dn, 1.0), t)
        p = o + t[:, None] * d
        q = p - v0
        ok &= wt["ok"][prim]
        b1 = np.where(ok, np.einsum("ij,ij->i", q, wt["g1"][prim]), b1)
        b2 = np.where(ok, np.einsum("ij,ij->i", q, wt["g2"][prim]), b2)
        w = np.stack([1.0 - b1 - b2, b1, b2], axis=1)
        ns = _unit(np.einsum("nk,nkj->nj", w, wt["corner_normals"][prim])) if self.smooth else ng
        uv = self._geom["uv"]
        uv = np.einsum("nk,nkj->nj", w, uv[self._geom["faces"][prim]]) if uv is not None else \
            np.full((len(prim), 2), np.nan)
        return t, p, ng, ns, uv


def _quadric_roots(o, d, center, radius):
    """Both roots (t0 <= t1) of |o + t d - c|^2 = r^2 (NaN where the ray misses); stable form."""
    oc = o - center
    a = np.einsum("ij,ij->i", d, d)
    b = np.einsum("ij,ij->i", d, oc)
    c = np.einsum("ij,ij->i", oc, oc) - radius ** 2
    disc = b * b - a * c
    sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
    q = -(b + np.copysign(sq, b))
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = q / a, c / q
    return np.minimum(ta, tb), np.maximum(ta, tb)


def _first_valid(candidates, t_max):
    """The smallest t in ``candidates`` (each (N,), NaN/inf invalid) with 0 < t < t_max."""
    t = np.full(len(t_max), np.inf)
    for c in candidates:
        ok = (c > 0) & (c < t_max) & (c < t)
        t = np.where(ok, c, t)
    return t


def _sphere_uv(p_rel):
    """Lat-long uv of points relative to the centre: u = azimuth/2pi from +x towards +y, v =
    polar angle/pi from +z."""
    r = np.linalg.norm(p_rel, axis=1)
    u = np.mod(np.arctan2(p_rel[:, 1], p_rel[:, 0]) / (2 * np.pi), 1.0)
    v = np.arccos(np.clip(p_rel[:, 2] / np.where(r > 0, r, 1), -1, 1)) / np.pi
    return np.stack([u, v], axis=1)


class Sphere(Surface):
    """Sphere of ``radius`` (mm) about ``center`` (object frame; world frame when no transform).

    ``uv``: u = azimuth / 2pi about the object +z axis (from +x towards +y), v = polar angle / pi
    from +z. Normals point outwards.
    """

    def __init__(self, radius: float, center=(0.0, 0.0, 0.0), transform=None):
        if not np.isfinite(radius) or radius <= 0:
            raise ValueError(f"radius must be a positive number of mm, got {radius!r}")
        center = np.asarray(center, dtype=np.float64)
        if center.shape != (3,):
            raise ValueError(f"center must be a 3-vector in mm, got shape {center.shape}")
        super().__init__(transform)
        self.radius = float(radius)
        self.center = center

    @property
    def bounding_radius(self) -> float:
        c = self.transform[:3, :3] @ self.center + self.transform[:3, 3]
        return float(np.linalg.norm(c) + self.radius * np.abs(self.transform[:3, :3]).sum(0).max())

    def _intersect(self, o, d, t_max):
        t0, t1 = _quadric_roots(o, d, self.center, self.radius)
        t = _first_valid((t0, t1), t_max)
        z = np.zeros(len(t))
        return t, np.full(len(t), -1, dtype=np.int64), z, z

    def _attributes(self, o, d, t, prim, b1, b2):
        rel = o + t[:, None] * d - self.center
        rel *= self.radius / np.linalg.norm(rel, axis=1, keepdims=True)  # project onto the sphere
        return self.center + rel, rel, rel, _sphere_uv(rel)


class Hemisphere(Sphere):
    """The half of a sphere with object-frame ``z >= center_z`` (a dome open at its base), e.g. a
    test object with a parameter varying across it. ``uv`` as :class:`Sphere` (v <= 0.5).
    Normals point outwards; the inside is visible through the opening."""

    def _intersect(self, o, d, t_max):
        t0, t1 = _quadric_roots(o, d, self.center, self.radius)
        cands = []
        for tc in (t0, t1):
            z = o[:, 2] + tc * d[:, 2] - self.center[2]
            cands.append(np.where(z >= 0, tc, np.nan))
        t = _first_valid(cands, t_max)
        z = np.zeros(len(t))
        return t, np.full(len(t), -1, dtype=np.int64), z, z


class Plane(Surface):
    """The object-frame plane z = 0, normal +z, optionally limited to a ``size`` = (width, height)
    mm rectangle centred on the origin (x along width, y along height).

    ``uv``: for a finite plane (x / width + 1/2, y / height + 1/2) in [0, 1]; for an infinite
    plane the object-frame (x, y) in mm.
    """

    def __init__(self, size=None, transform=None):
        if size is not None:
            size = tuple(float(s) for s in np.ravel(size))
            if len(size) != 2 or min(size) <= 0:
                raise ValueError(f"size must be (width, height) in mm, both > 0, got {size}")
        super().__init__(transform)
        self.size = size

    @classmethod
    def from_point_normal(cls, point, normal, size=None, *, x_axis=None) -> "Plane":
        """A plane through ``point`` (mm, world) with unit ``normal`` (world); ``x_axis`` picks the
        in-plane direction of u (default: any tangent)."""
        n = np.asarray(normal, float)
        if n.shape != (3,) or np.linalg.norm(n) == 0:
            raise ValueError(f"normal must be a non-zero 3-vector, got {normal!r}")
        n = n / np.linalg.norm(n)
        x = np.cross([0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0], n) \
            if x_axis is None else np.asarray(x_axis, float)
        x = x - (x @ n) * n
        if np.linalg.norm(x) < 1e-9:
            raise ValueError("x_axis must not be parallel to the normal")
        x /= np.linalg.norm(x)
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(n, x), n, point
        return cls(size, T)

    @property
    def bounding_radius(self) -> float:
        if self.size is None:
            return np.inf
        corners = np.array([[sx * self.size[0] / 2, sy * self.size[1] / 2, 0.0]
                            for sx in (-1, 1) for sy in (-1, 1)])
        return float(np.linalg.norm(corners @ self.transform[:3, :3].T + self.transform[:3, 3],
                                    axis=1).max())

    def _intersect(self, o, d, t_max):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[:, 2] / d[:, 2]
        if self.size is not None:
            x = o[:, 0] + t * d[:, 0]
            y = o[:, 1] + t * d[:, 1]
            t = np.where((np.abs(x) <= self.size[0] / 2) & (np.abs(y) <= self.size[1] / 2), t,
                         np.nan)
        t = _first_valid((t,), t_max)
        z = np.zeros(len(t))
        return t, np.full(len(t), -1, dtype=np.int64), z, z

    def _hit_world(self, o, d, t, prim, b1, b2):
        # constant normal: no per-hit transform of normals
        p = o + t[:, None] * d
        n = np.broadcast_to(_unit(self._normal_matrix[:, 2:].T)[0], p.shape)
        xy = linear_rows(self._inv[:3, :3], p)[:, :2] + self._inv[:2, 3]
        uv = xy / np.asarray(self.size) + 0.5 if self.size is not None else xy
        return t, p, n, n, uv


# ----------------------------------------------------------------------------------------------
# queries
# ----------------------------------------------------------------------------------------------
_warned = False


def _warn_slow() -> None:
    global _warned
    if not _warned:
        warnings.warn("embreex is not installed: meshes are ray-cast by trimesh's pure-Python "
                      "intersector (100-3500x slower, ~0.4 MB per ray). `pip install embreex`.",
                      SlowRaycastWarning, stacklevel=3)
        _warned = True


def _check_rays(origins, dirs):
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"dirs must have shape (N, 3), got {d.shape}")
    if o.shape == (3,):
        o = np.broadcast_to(o, d.shape)
    if o.shape != d.shape:
        raise ValueError(f"origins must have shape (3,) or {d.shape} like dirs, got {o.shape}")
    if not np.all(np.isfinite(d)) or not np.all(np.isfinite(o)):
        raise ValueError("origins and dirs must be finite")
    return o, d


def _check_surfaces(surfaces) -> list[Surface]:
    if isinstance(surfaces, Surface):
        return [surfaces]
    surfaces = list(surfaces)
    for i, s in enumerate(surfaces):
        if not isinstance(s, Surface):
            raise TypeError(f"surfaces[{i}] must be a raycast.Surface (Mesh, Sphere, Hemisphere, "
                            f"Plane), got {type(s).__name__}")
    return surfaces


def first_hits(surfaces: Sequence[Surface] | Surface, origins, dirs, t_max=None) -> Hits:
    """Nearest intersection of each ray with any of ``surfaces``.

    Parameters
    ----------
    surfaces : sequence of Surface
        Placed surfaces (world frame); ``Hits.surface_index`` indexes this sequence.
    origins : ndarray of shape (N, 3) or (3,)
        Ray origins, world frame, mm.
    dirs : ndarray of shape (N, 3)
        Ray directions, world frame; unit vectors make ``t`` a distance in mm.
    t_max : float or ndarray of shape (N,), optional
        Ignore hits farther than this ray parameter.

    Returns
    -------
    Hits
    """
    surfaces = _check_surfaces(surfaces)
    o, d = _check_rays(origins, dirs)
    return _first_hits(surfaces, o, d, t_max)


def _first_hits(surfaces: list[Surface], o, d, t_max=None) -> Hits:
    """:func:`first_hits` on checked float64 arrays."""
    n = len(d)
    best = np.full(n, np.inf) if t_max is None else np.broadcast_to(
        np.asarray(t_max, float), (n,)).copy()
    owner = np.full(n, -1, dtype=np.int64)
    found = []
    for k, s in enumerate(surfaces):
        t, prim, b1, b2 = s._intersect(*s._to_local(o, d), best)
        closer = t < best
        best[closer] = t[closer]
        owner[closer] = k
        found.append((prim, b1, b2))

    mask = owner >= 0
    hits = Hits(t=best if t_max is None else np.where(mask, best, np.inf),
                position=np.full((n, 3), np.nan), normal=np.zeros((n, 3)),
                geometric_normal=np.zeros((n, 3)), uv=np.full((n, 2), np.nan),
                face_index=np.full(n, -1, dtype=np.int64), surface_index=owner, mask=mask)
    for k, s in enumerate(surfaces):
        idx = np.flatnonzero(owner == k)
        if len(idx) == 0:
            continue
        prim, b1, b2 = (a[idx] for a in found[k])
        # float64 t from the exact hit point (Embree's tfar is float32)
        hits.t[idx], hits.position[idx], ngw, nsw, hits.uv[idx] = s._hit_world(
            o[idx], d[idx], best[idx], prim, b1, b2)
        hits.geometric_normal[idx] = ngw
        hits.normal[idx] = nsw
        hits.face_index[idx] = prim
    return hits


def _unit(v):
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def scene_scale(surfaces: Sequence[Surface], points=None) -> float:
    """A length (mm) setting the float32 precision of the scene: the largest bounded surface
    radius about the world origin and the largest coordinate of ``points``."""
    radii = [s.bounding_radius for s in _check_surfaces(surfaces)]
    radii = [r for r in radii if np.isfinite(r)]
    if points is not None and len(points):
        radii.append(float(np.abs(points).max()))
    return max(radii, default=1.0)


def offset_origins(points, normals, dirs, scale: float) -> np.ndarray:
    """Shift surface points (N, 3) by ``OFFSET_EPS * scale`` mm along ±``normals`` (N, 3), to the
    side ``dirs`` (N, 3) leave, so a ray starting there does not hit its own surface."""
    side = np.sign(np.einsum("ij,ij->i", normals, dirs))
    side[side == 0] = 1.0
    return points + (OFFSET_EPS * scale) * side[:, None] * normals


def occluded(surfaces: Sequence[Surface] | Surface, origins, dirs, max_t=None, *,
             normals=None) -> np.ndarray:
    """Whether anything blocks each ray before ``max_t`` (a shadow / visibility test).

    Parameters
    ----------
    surfaces : sequence of Surface
        Blockers, world frame.
    origins : ndarray of shape (N, 3) or (3,)
        Ray origins, world frame, mm; usually points on a surface.
    dirs : ndarray of shape (N, 3)
        Directions, world frame (unit vectors: ``max_t`` is in mm).
    max_t : float or ndarray of shape (N,), optional
        Distance to the light / target; hits at or beyond it do not count. Default: infinity.
    normals : ndarray of shape (N, 3), optional
        Geometric normals at ``origins``: the origins are then offset along them by a scale-aware
        epsilon (see :func:`offset_origins`) and ``max_t`` shortened by the same amount, which
        avoids self-shadowing acne from Embree's float32 arithmetic.

    Returns
    -------
    ndarray of shape (N,), bool
    """
    surfaces = _check_surfaces(surfaces)
    o, d = _check_rays(origins, dirs)
    n = len(d)
    tm = np.full(n, np.inf) if max_t is None else np.broadcast_to(np.asarray(max_t, float),
                                                                   (n,)).copy()
    if normals is not None:
        nrm = np.asarray(normals, float)
        if nrm.shape != d.shape:
            raise ValueError(f"normals must have shape {d.shape}, got {nrm.shape}")
        eps = OFFSET_EPS * scene_scale(surfaces, o)
        o = offset_origins(o, nrm, d, eps / OFFSET_EPS)
        tm = tm - 2 * eps / np.linalg.norm(d, axis=1)
    return _occluded(surfaces, o, d, tm)


def _occluded(surfaces: list[Surface], o, d, tm) -> np.ndarray:
    """:func:`occluded` on checked arrays (origins already offset), ``tm`` (N,)."""
    blocked = np.zeros(len(d), dtype=bool)
    for s in surfaces:
        # rays already blocked get zero length (their answer no longer matters, and a zero-length
        # ray costs Embree next to nothing): cheaper than gathering the others and scattering back
        blocked |= s._occluded(*s._to_local(o, d), np.where(blocked, 0.0, tm))
        if blocked.all():
            break
    return blocked


def reflect(d, n) -> np.ndarray:
    """Mirror directions (N, 3) of incoming ray directions ``d`` about unit normals ``n``."""
    return d - 2.0 * np.einsum("ij,ij->i", d, n)[:, None] * n
