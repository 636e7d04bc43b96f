"""glTF 2.0 binary (``.glb``): the mesh, its normal map and a metallic-roughness +
``KHR_materials_specular`` material approximating the exported BRDF per texel.

glTF's BRDF (the specification's Appendix B with KHR_materials_specular, metallic 0) is

    f_r = (1 - F) * baseColor / pi + F * D(h; alpha) * V(wi, wo),   alpha = roughness^2,
    F = F0 + (1 - F0) (1 - |v.h|)^5,   F0 = min(0.04 * specularColor, 1) * specular,

D the GGX distribution and V the height-correlated Smith visibility ``G / (4 |n.l| |n.v|)``.
From :mod:`capture.export.ggx`'s ``rho_d``, ``ks``, ``alpha``: roughness = sqrt(alpha),
F0 = min(ks, 1), baseColor = min(rho_d / (1 - F0), 1) — the lobe's scale becomes Fresnel's
value at normal incidence and the diffuse term is raised by what ``(1 - F)`` takes from it. What
that costs is measured (:func:`gltf_reflectance` against the method's own predictions) and stated
in ``model.json``. Units: metres (the mesh's mm / 1000); colour textures sRGB-encoded 8-bit PNG as
glTF requires, normal and metallic-roughness textures linear.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from reconstruct.brdf import microfacet_distribution

from .atlas import Atlas
from .ggx import GgxMaps

__all__ = ["GltfMaterial", "gltf_material", "gltf_reflectance", "write_glb", "srgb_encode"]

#: F0 of glTF's default dielectric (ior 1.5): the unit of specularColor
_F0_IOR15 = 0.04


@dataclass(frozen=True)
class GltfMaterial:
    """Per-texel glTF parameters (any leading shape): base_color (..., 3) linear in [0, 1],
    roughness (...) in [0, 1], f0 (..., 3) in [0, 1] (metallic 0, specular 1)."""

    base_color: np.ndarray
    roughness: np.ndarray
    f0: np.ndarray

    def take(self, index: np.ndarray) -> "GltfMaterial":
        """The parameters at ``index`` (rows)."""
        return GltfMaterial(self.base_color[index], self.roughness[index], self.f0[index])


def gltf_material(maps: GgxMaps) -> GltfMaterial:
    """The glTF parameters standing for the exported BRDF (see the module docstring)."""
    f0 = np.clip(maps.ks, 0.0, 1.0)
    base = np.clip(maps.rho_d / np.maximum(1.0 - f0, 1e-6), 0.0, 1.0)
    return GltfMaterial(base, np.clip(np.sqrt(maps.alpha), 0.0, 1.0), f0)


def gltf_reflectance(m: GltfMaterial, n: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """``f_r cos theta_i`` (S, 3) of glTF's BRDF for per-sample parameters ``m`` (S rows) and
    unit normals / directions (S, 3) in one frame."""
    h = wi + wo
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    nl, nv = np.einsum("ij,ij->i", n, wi), np.einsum("ij,ij->i", n, wo)
    nh, vh = np.einsum("ij,ij->i", n, h), np.abs(np.einsum("ij,ij->i", wo, h))
    front = (nl > 1e-6) & (nv > 1e-6)
    nl_, nv_ = np.where(front, nl, 1.0), np.where(front, nv, 1.0)
    a2 = (m.roughness ** 2) ** 2
    vis = 0.5 / (nl_ * np.sqrt(nv_ ** 2 * (1 - a2) + a2) + nv_ * np.sqrt(nl_ ** 2 * (1 - a2) + a2))
    d = microfacet_distribution(np.clip(nh, 1e-9, 1.0), m.roughness ** 2, "ggx")
    fr = m.f0 + (1 - m.f0) * ((1 - vh) ** 5)[:, None]
    f = (1 - fr) * m.base_color / np.pi + fr * (d * vis)[:, None]
    return np.where(front[:, None], f * nl_[:, None], 0.0)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1)."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def _png8(rgb: np.ndarray) -> bytes:
    code = np.rint(np.clip(rgb, 0, 1) * 255).astype(np.uint8)[..., ::-1]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(code))
    if not ok:
        raise OSError("OpenCV could not encode a PNG")
    return buf.tobytes()


def write_glb(path, atlas: Atlas, material: GltfMaterial, normal_map: np.ndarray, *, name: str) -> None:
    """Write ``atlas`` (mm) with per-pixel ``material`` maps ((H, W, ...) arrays) and the
    tangent-space ``normal_map`` (H, W, 3) unit vectors as one glTF 2.0 binary."""
    import pygltflib as g

    pos = (atlas.vertices / 1000.0).astype(np.float32)
    arrays = [pos, atlas.normals.astype(np.float32), atlas.tangents.astype(np.float32),
              atlas.uv.astype(np.float32), atlas.faces.astype(np.uint32).ravel()]
    mr = np.zeros(material.roughness.shape + (3,))
    mr[..., 1] = material.roughness              # G: roughness, B: metallic (0)
    s = max(float(material.f0.max()) / _F0_IOR15, 1e-6)   # specularColorFactor: F0 / 0.04 at most
    images = [_png8(srgb_encode(material.base_color)), _png8(mr), _png8((normal_map + 1) / 2),
              _png8(srgb_encode(material.f0 / (_F0_IOR15 * s)))]
    blob, views = bytearray(), []
    for i, data in enumerate([a.tobytes() for a in arrays] + images):
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data),
                                  target=(g.ELEMENT_ARRAY_BUFFER if i == 4 else g.ARRAY_BUFFER) if i < 5 else None))
        blob += data
        blob += b"\0" * (-len(blob) % 4)
    acc = [g.Accessor(bufferView=0, componentType=g.FLOAT, count=len(pos), type=g.VEC3,
                      min=pos.min(axis=0).tolist(), max=pos.max(axis=0).tolist()),
           g.Accessor(bufferView=1, componentType=g.FLOAT, count=len(pos), type=g.VEC3),
           g.Accessor(bufferView=2, componentType=g.FLOAT, count=len(pos), type=g.VEC4),
           g.Accessor(bufferView=3, componentType=g.FLOAT, count=len(pos), type=g.VEC2),
           g.Accessor(bufferView=4, componentType=g.UNSIGNED_INT, count=int(arrays[4].size), type=g.SCALAR)]
    tex = [g.TextureInfo(index=k) for k in range(4)]
    mat = g.Material(
        name=f"{name} (gonio export)",
        pbrMetallicRoughness=g.PbrMetallicRoughness(baseColorTexture=tex[0], metallicRoughnessTexture=tex[1],
                                                    metallicFactor=1.0, roughnessFactor=1.0),
        normalTexture=g.NormalMaterialTexture(index=2),
        extensions={"KHR_materials_specular": {"specularFactor": 1.0, "specularColorFactor": [s, s, s],
                                               "specularColorTexture": {"index": 3}}})
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="gonio export"),
        extensionsUsed=["KHR_materials_specular"],
        scene=0, scenes=[g.Scene(nodes=[0])], nodes=[g.Node(mesh=0, name=name)],
        meshes=[g.Mesh(name=name, primitives=[g.Primitive(
            attributes=g.Attributes(POSITION=0, NORMAL=1, TANGENT=2, TEXCOORD_0=3), indices=4, material=0)])],
        materials=[mat], accessors=acc, bufferViews=views,
        buffers=[g.Buffer(byteLength=len(blob))],
        samplers=[g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR, wrapS=g.CLAMP_TO_EDGE, wrapT=g.CLAMP_TO_EDGE)],
        textures=[g.Texture(source=k, sampler=0) for k in range(4)],
        images=[g.Image(bufferView=5 + k, mimeType="image/png") for k in range(4)])
    gltf.set_binary_blob(bytes(blob))
    gltf.save_binary(str(path))
