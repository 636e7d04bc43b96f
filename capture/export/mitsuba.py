"""Mitsuba 3 scene files: the object (PLY + EXR textures + BSDF) and one XML per captured pose
with the calibrated camera and that capture's point light.

Frames and units: everything in the object frame (the lab frame at turntable reading 0), mm;
for a capture at turntable angle ``phi`` the camera and the light are taken into the object
frame with the inverse of the object's pose, so the object file is shared by every view.

The BSDF is the exported one (:mod:`capture.export.ggx`) in Mitsuba's own plugins:
``normalmap`` around ``blendbsdf`` (weight 0.5) of ``diffuse`` (reflectance ``2 rho_d``) and
``roughconductor`` (``material = "none"``: Fresnel 1; GGX ``alpha``; ``specular_reflectance
2 ks``): half of each doubled is their sum, ``rho_d / pi + ks D G1 G1 / (4 cos cos)``, exactly
the exported formula (Mitsuba's microfacet masking is Smith's separable G1 G1).

Camera: Mitsuba's ``perspective`` sensor is a pinhole with square pixels: the calibrated
``fx`` sets its horizontal field of view, the principal point its offset; lens distortion and
``fy != fx`` are not rendered (:func:`pinhole_project` projects exactly as it renders, so a
comparison can go through the same geometry).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

__all__ = ["MitsubaView", "write_ply", "object_xml", "view_xml", "pinhole_project", "render"]


@dataclass(frozen=True)
class MitsubaView:
    """One capture to render: the camera and the light in the object frame.

    Attributes
    ----------
    name : str                 file stem (e.g. ``step-0012``)
    camera_to_object : (4, 4)  OpenCV camera (x right, y down, z forward) -> object frame, mm
    K : (3, 3)                 calibrated intrinsics (fx, cx, cy used)
    size : (int, int)          image (width, height), pixels
    light_mm : (3,)            point light position, object frame, mm
    intensity : (3,)           its radiant intensity per channel (the calibration's units)
    held_out : bool            a held-out light (never fitted)
    """

    name: str
    camera_to_object: np.ndarray
    K: np.ndarray
    size: tuple[int, int]
    light_mm: np.ndarray
    intensity: np.ndarray
    held_out: bool = False


def write_ply(path: str | Path, vertices: np.ndarray, normals: np.ndarray, uv: np.ndarray,
              faces: np.ndarray) -> None:
    """Binary little-endian PLY with ``x y z nx ny nz u v`` per vertex (float32) and triangles."""
    V, F = len(vertices), len(faces)
    vert = np.zeros(V, dtype=[(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz", "u", "v")])
    for k, col in zip(("x", "y", "z"), vertices.T):
        vert[k] = col
    for k, col in zip(("nx", "ny", "nz"), normals.T):
        vert[k] = col
    vert["u"], vert["v"] = uv[:, 0], uv[:, 1]
    face = np.zeros(F, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, faces
    header = (f"ply\nformat binary_little_endian 1.0\ncomment gonio export: object frame, mm\n"
              f"element vertex {V}\n" + "".join(f"property float {k}\n" for k in vert.dtype.names)
              + f"element face {F}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())


def _texture(name: str, filename: str) -> str:
    return (f'<texture type="bitmap" name="{name}"><string name="filename" value={quoteattr(filename)}/>'
            '<boolean name="raw" value="true"/><string name="filter_type" value="bilinear"/>'
            '<string name="wrap_mode" value="clamp"/></texture>')


def object_xml(ply: str, textures: dict[str, str]) -> str:
    """The object's scene fragment: the PLY and its BSDF from the texture files ``textures``
    (keys ``diffuse2``, ``ks2``, ``alpha``, ``normal``; paths relative to the XML)."""
    return f"""<scene version="3.0.0">
    <!-- gonio export: f_r = rho_d/pi + ks D G1 G1 / (4 cos_i cos_o), GGX; object frame, mm -->
    <shape type="ply">
        <string name="filename" value={quoteattr(ply)}/>
        <boolean name="face_normals" value="false"/>
        <bsdf type="normalmap">
            {_texture("normalmap", textures["normal"])}
            <bsdf type="blendbsdf">
                <float name="weight" value="0.5"/>
                <bsdf type="diffuse">{_texture("reflectance", textures["diffuse2"])}</bsdf>
                <bsdf type="roughconductor">
                    <string name="material" value="none"/>
                    <string name="distribution" value="ggx"/>
                    {_texture("alpha", textures["alpha"])}
                    {_texture("specular_reflectance", textures["ks2"])}
                </bsdf>
            </bsdf>
        </bsdf>
    </shape>
</scene>
"""


def _mitsuba_camera(view: MitsubaView) -> tuple[float, float, float]:
    """Horizontal field of view (deg) and Mitsuba's principal-point offsets: fractions of the
    film's width / height by which the image moves left / up (measured: a positive offset moves
    the picture towards -x, -y in pixels), hence the minus signs."""
    W, H = view.size
    fx, cx, cy = view.K[0, 0], view.K[0, 2], view.K[1, 2]
    return float(np.degrees(2 * np.arctan(W / (2 * fx)))), float((W / 2 - cx) / W), float((H / 2 - cy) / H)


def pinhole_project(view: MitsubaView, points_obj: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) (pixel centres at +0.5) at which :func:`view_xml`'s camera
    images object-frame points (N, 3): the calibrated pinhole with ``fy = fx``, no distortion."""
    T = np.linalg.inv(view.camera_to_object)
    pc = points_obj @ T[:3, :3].T + T[:3, 3]
    fx, cx, cy = view.K[0, 0], view.K[0, 2], view.K[1, 2]
    return np.stack([fx * pc[:, 0] / pc[:, 2] + cx, fx * pc[:, 1] / pc[:, 2] + cy], axis=1)


def view_xml(view: MitsubaView, object_file: str, *, spp: int = 16) -> str:
    """A complete scene: ``object_file`` included, the view's camera and point light, Mitsuba's
    ``direct`` integrator (no inter-reflection, as gonio's renderer) and a float RGB film."""
    fov, px, py = _mitsuba_camera(view)
    # Mitsuba's camera looks along +z with +x left and +y up: OpenCV's with x and y negated
    M = view.camera_to_object @ np.diag([-1.0, -1.0, 1.0, 1.0])
    matrix = " ".join(f"{v:.12g}" for v in M.ravel())
    W, H = view.size
    lx, ly, lz = (f"{v:.9g}" for v in view.light_mm)
    r, g, b = (f"{v:.9g}" for v in view.intensity)
    return f"""<scene version="3.0.0">
    <!-- gonio export, {"held-out" if view.held_out else "training"} capture {view.name}: object frame, mm.
         A larger film (-D width=... -D height=..., same aspect) is the same camera supersampled -->
    <default name="width" value="{W}"/>
    <default name="height" value="{H}"/>
    <default name="spp" value="{spp}"/>
    <integrator type="direct"><integer name="emitter_samples" value="1"/><integer name="bsdf_samples" value="0"/></integrator>
    <sensor type="perspective">
        <string name="fov_axis" value="x"/>
        <float name="fov" value="{fov:.12g}"/>
        <float name="principal_point_offset_x" value="{px:.12g}"/>
        <float name="principal_point_offset_y" value="{py:.12g}"/>
        <float name="near_clip" value="1"/>
        <float name="far_clip" value="100000"/>
        <transform name="to_world"><matrix value="{matrix}"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="$width"/><integer name="height" value="$height"/>
            <string name="pixel_format" value="rgb"/><rfilter type="box"/>
        </film>
    </sensor>
    <emitter type="point">
        <point name="position" x="{lx}" y="{ly}" z="{lz}"/>
        <rgb name="intensity" value="{r}, {g}, {b}"/>
    </emitter>
    <include filename={quoteattr(object_file)}/>
</scene>
"""


def render(xml: str | Path, *, spp: int | None = None, supersample: int = 1,
           variant: str = "scalar_rgb") -> np.ndarray:
    """Render a :func:`view_xml` scene file with Mitsuba 3 (``variant``, CPU) -> linear RGB
    (H s, W s, 3) float32, ``s = supersample`` (the same camera on an s times finer film)."""
    import mitsuba as mi
    if mi.variant() != variant:
        mi.set_variant(variant)
    params = {}
    if supersample != 1:
        scene = mi.load_file(str(xml))
        W, H = scene.sensors()[0].film().size()
        params = {"width": str(W * supersample), "height": str(H * supersample)}
    if spp:
        params["spp"] = str(spp)
    scene = mi.load_file(str(xml), **params)
    return np.asarray(mi.render(scene), np.float32)[..., :3]
