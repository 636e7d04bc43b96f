"""The mesh's UV atlas and per-texel values baked into it.

UV convention (glTF's, also Mitsuba 3's for PLY): ``(u, v)`` in [0, 1], ``(0, 0)`` the top-left
corner of the image, ``v`` down the rows; atlas pixel ``(row, col)`` has its centre at
``u = (col + 0.5) / W``, ``v = (row + 0.5) / H``.

Tangent space (the MikkTSpace convention glTF and Blender use): per vertex a unit tangent ``T``
along increasing ``u`` and a sign ``w`` with the bitangent ``B = w (N x T)`` along *decreasing*
``v`` (up the image: the normal map's green channel points up, OpenGL style). A normal map texel
holds ``(x, y, z)`` with ``n = normalize(x T + y B + z N)`` from the interpolated, un-normalised
vertex vectors (what a MikkTSpace-compatible shader does); the bake inverts exactly that. The
tangents are written into the glTF file, so a viewer uses these, not its own.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

__all__ = ["Atlas", "make_atlas", "BakedTexels", "bake", "MAX_ATLAS"]

#: the largest atlas side (pixels)
MAX_ATLAS = 4096


@dataclass(frozen=True)
class Atlas:
    """A mesh with one UV per vertex (seams split), object frame, mm.

    Attributes
    ----------
    vertices : (V, 3) float    positions
    normals : (V, 3)           unit vertex normals
    faces : (F, 3) int
    uv : (V, 2)                texture coordinates (see the module docstring)
    tangents : (V, 4)          unit tangent xyz and the bitangent sign w (+1 or -1)
    size : (int, int)          atlas (height, width) in pixels
    """

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    tangents: np.ndarray
    size: tuple[int, int]


def make_atlas(mesh: trimesh.Trimesh, texel_mm: float) -> Atlas:
    """A UV atlas of ``mesh`` with about two atlas pixels per ``texel_mm`` (the spacing of the
    reconstruction's texels): xatlas's charts, packed with 2-pixel padding; the mesh's own UVs
    when it has them (trimesh ``visual.uv``).

    Raises
    ------
    ValueError
        Empty mesh, non-positive ``texel_mm``, or an atlas larger than :data:`MAX_ATLAS`.
    """
    if len(mesh.faces) == 0:
        raise ValueError("mesh: no faces to lay out")
    if not texel_mm > 0:
        raise ValueError(f"texel_mm must be > 0, got {texel_mm}")
    own = getattr(mesh.visual, "uv", None)
    if own is not None and len(own) == len(mesh.vertices):
        vertices, faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
        uv = np.asarray(own, float) * [1.0, -1.0] + [0.0, 1.0]   # trimesh's v is up (OBJ)
        side = int(np.clip(2 * np.sqrt(mesh.area) / texel_mm, 64, MAX_ATLAS))
        h = w = side
        normals = np.asarray(mesh.vertex_normals, float)
    else:
        import xatlas
        atlas = xatlas.Atlas()
        atlas.add_mesh(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32))
        pack = xatlas.PackOptions()
        pack.texels_per_unit = 2.0 / texel_mm
        pack.padding = 2
        pack.bilinear = True
        atlas.generate(pack_options=pack)
        vmap, idx, uv = atlas[0] if hasattr(atlas, "__getitem__") else atlas.get_mesh(0)
        h, w = atlas.height, atlas.width
        if max(h, w) > MAX_ATLAS:
            raise ValueError(f"atlas would be {w} x {h} pixels (> {MAX_ATLAS}): texels of {texel_mm:.3g} mm "
                             f"on a mesh of {mesh.area:.3g} mm^2")
        vertices = np.asarray(mesh.vertices, float)[vmap]
        normals = np.asarray(mesh.vertex_normals, float)[vmap]
        faces = np.asarray(idx, np.int64)
        uv = np.asarray(uv, float)
    return Atlas(vertices, normals, faces, uv, _tangents(vertices, normals, faces, uv), (int(h), int(w)))


def _tangents(p: np.ndarray, n: np.ndarray, f: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Per-vertex tangents (V, 4): the faces' dP/du and dP/dv, area-weighted at their vertices,
    T Gram-Schmidt against N, ``w`` the sign making ``w (N x T)`` point along -dP/dv."""
    e1, e2 = p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]
    d1, d2 = uv[f[:, 1]] - uv[f[:, 0]], uv[f[:, 2]] - uv[f[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    r = np.where(np.abs(det) > 1e-20, 1.0 / np.where(det == 0, 1.0, det), 0.0)[:, None]
    # weighted by |det|: dP/du's face contributions scale with the face's UV area
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * r * np.abs(det)[:, None]
    dpdv = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * r * np.abs(det)[:, None]
    tu, tv = np.zeros_like(p), np.zeros_like(p)
    for k in range(3):
        np.add.at(tu, f[:, k], dpdu)
        np.add.at(tv, f[:, k], dpdv)
    t = tu - np.sum(tu * n, axis=1, keepdims=True) * n
    norm = np.linalg.norm(t, axis=1, keepdims=True)
    fallback = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    t = np.where(norm > 1e-12, t / np.maximum(norm, 1e-300), fallback / np.linalg.norm(fallback, axis=1, keepdims=True))
    w = np.where(np.sum(np.cross(n, t) * -tv, axis=1) < 0, -1.0, 1.0)
    return np.concatenate([t, w[:, None]], axis=1)


@dataclass(frozen=True)
class BakedTexels:
    """Which texel of the reconstruction each atlas pixel shows.

    Attributes
    ----------
    texel : (H, W) int     nearest reconstruction texel (every pixel, padding included)
    covered : (H, W) bool  the pixel's centre lies on the mesh (inside a chart)
    distance_mm : (H, W)   distance from the pixel's surface point to that texel (inf off charts)
    position, normal, tangent, bitangent : (H, W, 3)
        The pixel's surface point, interpolated vertex normal, tangent and ``w (N x T)``
        (un-normalised, as a shader interpolates them; zeros off charts)
    """

    texel: np.ndarray
    covered: np.ndarray
    distance_mm: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    bitangent: np.ndarray

    def tangent_space(self, normals: np.ndarray, *, signed: bool = True) -> np.ndarray:
        """Object-frame unit normals (H, W, 3) -> the normal map's unit (x, y, z), the exact
        inverse of ``normalize(x T + y B + z N)``; (0, 0, 1) off charts.

        ``signed=False`` bakes against ``B = N x T`` without the sign ``w``: Mitsuba's
        ``normalmap`` builds its frame that way, so on the charts xatlas mirrored (w = -1) its
        map's y is the glTF map's negated."""
        bit = self.bitangent if signed else np.cross(self.normal, self.tangent)
        basis = np.stack([self.tangent, bit, self.normal], axis=-1)   # columns T, B, N
        out = np.zeros(normals.shape)
        out[..., 2] = 1.0
        c = self.covered & (np.abs(np.linalg.det(np.where(self.covered[..., None, None], basis, np.eye(3)))) > 1e-9)
        x = np.linalg.solve(basis[c], normals[c][..., None])[..., 0]
        out[c] = x / np.linalg.norm(x, axis=1, keepdims=True)
        return out


def bake(atlas: Atlas, positions: np.ndarray) -> BakedTexels:
    """Assign every atlas pixel the nearest of the reconstruction's texels (``positions`` (T, 3),
    object frame, mm): pixels on a chart by their surface point, the padding around charts from
    the nearest chart pixel (so bilinear lookups at chart edges stay on the chart's values)."""
    from matplotlib.tri import Triangulation
    H, W = atlas.size
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    u, v = (cols.ravel() + 0.5) / W, (rows.ravel() + 0.5) / H
    tri = Triangulation(atlas.uv[:, 0], atlas.uv[:, 1], atlas.faces)
    face = tri.get_trifinder()(u, v)
    inside = face >= 0
    f = atlas.faces[face[inside]]
    a, b, c = (atlas.uv[f[:, k]] for k in range(3))
    q = np.stack([u[inside], v[inside]], axis=1)
    den = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    l0 = ((b[:, 1] - c[:, 1]) * (q[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (q[:, 1] - c[:, 1])) / den
    l1 = ((c[:, 1] - a[:, 1]) * (q[:, 0] - c[:, 0]) + (a[:, 0] - c[:, 0]) * (q[:, 1] - c[:, 1])) / den
    bary = np.stack([l0, l1, 1 - l0 - l1], axis=1)

    def interp(attr):
        out = np.zeros((H * W, attr.shape[1]))
        out[inside] = np.einsum("nk,nkc->nc", bary, attr[f])
        return out.reshape(H, W, -1)

    pos, nrm, tan = interp(atlas.vertices), interp(atlas.normals), interp(atlas.tangents)
    bit = tan[..., 3:4] * np.cross(nrm, tan[..., :3])
    covered = inside.reshape(H, W)
    dist, nearest = cKDTree(np.asarray(positions, float)).query(pos[covered])
    texel = np.zeros((H, W), np.int64)
    texel[covered] = nearest
    # padding: the value of the nearest chart pixel
    _, (ri, ci) = ndimage.distance_transform_edt(~covered, return_indices=True)
    texel = texel[ri, ci]
    distance = np.full((H, W), np.inf)
    distance[covered] = dist
    return BakedTexels(texel, covered, distance, pos, nrm, tan[..., :3], bit)
