"""``gonio export``: one method's stored reconstruction -> files other software reads.

:func:`export_session` reads the method's ``appearance.npz`` (:mod:`capture.export.appearance`)
and the object's mesh, and writes into a new folder (``DIR``; nothing is written unless every
requested format succeeds: the files go to a hidden sibling folder renamed to ``DIR`` at the end):

- ``maps``: ``textures/*.exr`` (32-bit float) and ``textures/*.png`` (16-bit) in the mesh's UV
  atlas (``mesh.ply`` with the UVs and tangents): diffuse albedo, GGX lobe scale and roughness,
  the tangent-space normal map, the material of each texel (and, where a material has several,
  the method's clusters) and the confidence maps;
- ``gltf``: ``model.glb`` (:mod:`capture.export.gltf`);
- ``mitsuba``: ``mitsuba/`` (:mod:`capture.export.mitsuba`), one scene per captured pose;
- ``merl``: ``brdf.binary``, the tabulated BRDF in MERL's format (passive reflectometry's).

``model.json`` names every file, its units and the exact formula, and states the export's own
approximation error against the method's model and the captures.
"""
from __future__ import annotations

import io
import json
import os
import shutil
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import trimesh

from scipy.spatial import cKDTree

from reconstruct.brdf import Bivariate, TabulatedIsotropic
from reconstruct.frames import tangent_frames, to_local
from reconstruct.merl import write_merl
from reconstruct.metrics import relative_rms

from ..outputs import session_file
from ..pipeline.report_html import ExportLink, check_session_report, link_export
from ..lab_resolver import resolve_lab
from ..store import ResultRecord, SessionNotFound, Store
from .formats import FORMATS
from .appearance import EXPORTED_METHODS, HOMOGENEOUS_METHODS, Appearance
from .atlas import Atlas, BakedTexels, bake, make_atlas
from .ggx import FORMULA, GgxMaps, ggx_reflectance
from .gltf import gltf_material, gltf_reflectance, write_glb
from .images import write_exr, write_png16
from .mitsuba import MitsubaView, object_xml, view_xml, write_ply
from .page import PAGE, write_export_page

__all__ = ["FORMATS", "ExportError", "ExportReport", "export_session"]

class ExportError(ValueError):
    """A request ``gonio export`` cannot carry out (the message says what and how to fix it)."""


@dataclass
class ExportReport:
    """What :func:`export_session` wrote: the folder, the files per format (relative paths),
    the figures ``model.json`` states, the export's page (``out/report.html``) and the session
    report that now links it (None: none was found)."""

    out: Path
    files: dict[str, list[str]] = field(default_factory=dict)
    model: dict[str, Any] = field(default_factory=dict)
    page: Path | None = None
    linked_from: Path | None = None


def _stored(store: Store, session: str, method: str) -> tuple[ResultRecord, Appearance]:
    try:
        info = store.session(session)
    except SessionNotFound:
        raise ExportError(f"no session {session!r} in {store.root} (see gonio session list)") from None
    runs = [r for r in store.results(info.id, "reconstruction") if r.kind == method]
    if not runs:
        done = sorted({r.kind for r in store.results(info.id, "reconstruction")})
        raise ExportError(f"method {method!r} was not run on session {session!r} (stored: "
                          f"{', '.join(done) or 'none'}); run: gonio process {session} --methods {method}")
    run = runs[-1]
    if "appearance.npz" not in run.artifacts:
        raise ExportError(f"{method} result {run['id']} of session {session!r} was stored without the export "
                          f"data (before gonio export existed); re-run: gonio process {session} --methods "
                          f"{method} --force")
    return run, Appearance.from_npz(store.read_object(run.artifacts["appearance.npz"]))


def export_session(store: Store, session: str, *, method: str, formats: Sequence[str], out: str | Path,
                   mesh: trimesh.Trimesh | None = None, report: str | Path | None = None) -> ExportReport:
    """Write ``method``'s stored reconstruction of ``session`` in ``formats`` into the new folder
    ``out``, with its page ``out/report.html`` (:mod:`capture.export.page`), and link that page
    from the session's report.

    Parameters
    ----------
    mesh : trimesh.Trimesh, optional
        The object's mesh (object frame, mm: the one ``gonio process`` used); a session
        recorded in the built-in simulated lab brings its own.
    report : path, optional
        The session report (``gonio process``'s HTML) to link the export from; default
        ``<session>-report.html`` (``gonio process``'s) or ``report.html`` (``gonio demo``'s)
        beside the store, when it is this session's report.

    Raises
    ------
    ExportError
        Unknown method or format, ``out`` exists, the method was not run (or not stored with
        the export data), no mesh, MERL asked of a method without a tabulated BRDF, or a
        ``report`` that is not this session's report. Nothing is written.
    """
    if method not in EXPORTED_METHODS:
        raise ExportError(f"--method {method!r}: one of {', '.join(EXPORTED_METHODS)}")
    formats = list(dict.fromkeys(formats))
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise ExportError(f"--format {', '.join(bad) or '(none)'}: choose from {', '.join(FORMATS)}")
    out = Path(out)
    if out.exists():
        raise ExportError(f"--out {out} exists; name a new folder (gonio export never overwrites)")
    if "merl" in formats and method not in HOMOGENEOUS_METHODS:
        raise ExportError(f"--format merl: {method} recovers a spatially varying parametric BRDF, not a "
                          f"tabulated one; MERL files come from {', '.join(HOMOGENEOUS_METHODS)}")
    run, app = _stored(store, session, method)
    report = _session_report(store, session, report)
    if mesh is None:   # a session recorded in the built-in simulated lab has its own
        mesh = resolve_lab(store, session).mesh
    if mesh is None:
        raise ExportError(f"session {session!r} has no mesh gonio knows: pass --mesh FILE (the mesh "
                          "gonio process was given)")
    bivariate = None
    if "merl" in formats:
        model = np.load(io.BytesIO(store.read_object(run.artifacts["model.npz"])))
        bivariate = np.asarray(model["bivariate"], float)

    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    tmp.mkdir(parents=True)
    try:
        rep = _write(tmp, session, method, formats, run, app, mesh, bivariate)
        write_export_page(tmp, session, method, rep.files, rep.model, app)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    rep.out, rep.page = out, out / PAGE
    if report is not None:
        rep.linked_from = link_export(report, session, ExportLink(
            os.path.relpath(rep.page.resolve(), report.resolve().parent), method, tuple(formats),
            rep.model.get("approximation", {}).get("export_vs_method_held_out_rel_rms"),
            datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")))
    return rep


def _session_report(store: Store, session: str, report: str | Path | None) -> Path | None:
    """The session report to link the export from: ``report`` (checked now, before anything is
    written), else the first of ``gonio process``'s ``<session>-report.html`` and ``gonio demo``'s
    ``report.html`` beside the store that is this session's report, else None."""
    if report is None:
        folder = Path(store.root).resolve().parent
        for candidate in (session_file(folder, session, store.session(session).id, "-report.html"),
                          folder / "report.html"):
            try:
                check_session_report(candidate, session)
            except (OSError, ValueError):
                continue
            return candidate
        return None
    try:
        check_session_report(report, session)
    except FileNotFoundError:
        raise ExportError(f"--report {report}: no such file (the HTML report gonio process wrote)") from None
    except (ValueError, OSError) as exc:
        raise ExportError(f"--report {exc}") from None
    return Path(report)


def texel_spacing_mm(position: np.ndarray) -> float:
    """Median distance from a texel to its nearest neighbour (mm): the reconstruction's sampling."""
    d, _ = cKDTree(position).query(position, k=2)
    return float(np.median(d[:, 1]))


@dataclass(frozen=True)
class _Baked:
    """The exported model's maps in the atlas: per-pixel parameters, normal maps, texel index."""

    atlas: Atlas
    texels: BakedTexels
    maps: GgxMaps            # (H, W, ...) arrays
    normal_gltf: np.ndarray  # (H, W, 3) unit tangent-space normals, signed bitangent
    normal_mitsuba: np.ndarray


def _bake(app: Appearance, mesh: trimesh.Trimesh) -> _Baked:
    atlas = make_atlas(mesh, texel_spacing_mm(app.position))
    tx = bake(atlas, app.position)
    H, W = atlas.size
    m = app.maps.take(tx.texel.ravel())
    maps = GgxMaps(m.rho_d.reshape(H, W, 3), m.ks.reshape(H, W, 3), m.alpha.reshape(H, W))
    n = app.normal[tx.texel]
    return _Baked(atlas, tx, maps, tx.tangent_space(n), tx.tangent_space(n, signed=False))


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample (H, W, C) at uv (N, 2) as a renderer's bilinear lookup with clamped edges."""
    H, W = image.shape[:2]
    x = np.clip(uv[:, 0] * W - 0.5, 0, W - 1)
    y = np.clip(uv[:, 1] * H - 0.5, 0, H - 1)
    x0, y0 = np.minimum(x.astype(int), W - 2), np.minimum(y.astype(int), H - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    img = image.reshape(H, W, -1)
    return ((img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx) * (1 - fy)
            + (img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx) * fy)


def _through_textures(app: Appearance, b: _Baked, texels: np.ndarray):
    """The exported model as a renderer reads it at texel positions: (GgxMaps, object-frame
    normals) from bilinear lookups of the maps at the texels' UVs (closest point on the atlas mesh)."""
    am = trimesh.Trimesh(b.atlas.vertices, b.atlas.faces, process=False)
    pts, _, face = trimesh.proximity.closest_point(am, app.position[texels])
    bary = trimesh.triangles.points_to_barycentric(am.triangles[face], pts)
    f = b.atlas.faces[face]

    def interp(attr):
        return np.einsum("nk,nkc->nc", bary, attr[f])

    uv = interp(b.atlas.uv)
    maps = GgxMaps(_bilinear(b.maps.rho_d, uv), _bilinear(b.maps.ks, uv), _bilinear(b.maps.alpha, uv)[:, 0])
    N, T4 = interp(b.atlas.normals), interp(b.atlas.tangents)
    B = T4[:, 3:4] * np.cross(N, T4[:, :3])   # as written: interpolated w of one chart is +-1
    c = _bilinear(b.normal_gltf, uv)
    n = c[:, :1] * T4[:, :3] + c[:, 1:2] * B + c[:, 2:3] * N
    return maps, n / np.linalg.norm(n, axis=1, keepdims=True)


def _approximation(app: Appearance, b: _Baked, run: ResultRecord) -> dict[str, Any]:
    """The export's error at the held-out samples, through the textures as a renderer reads
    them: against the method's own predictions and against the captures."""
    if not len(app.held_texel):
        return {"held_out_samples": 0}
    uniq, inv = np.unique(app.held_texel, return_inverse=True)
    maps_u, n_u = _through_textures(app, b, uniq)
    frames = tangent_frames(app.mesh_normal[app.held_texel])
    n_local = to_local(n_u[inv], frames)
    ggx = ggx_reflectance(maps_u.take(inv), n_local, app.held_wi, app.held_wo)
    gl = gltf_reflectance(gltf_material(maps_u).take(inv), n_local, app.held_wi, app.held_wo)
    figures = run.result.get("figures", {})
    return {
        "held_out_samples": int(len(app.held_texel)),
        "brdf_fit_rel_rms_per_material": [round(float(v), 5) for v in app.fit_rel_rms],
        "export_vs_method_held_out_rel_rms": relative_rms(ggx, app.held_predicted),
        "gltf_vs_method_held_out_rel_rms": relative_rms(gl, app.held_predicted),
        "method_held_out_rel_rms": relative_rms(app.held_predicted, app.held_captured),
        "method_held_out_rel_rms_stored": figures.get("held_out_rel_rms"),
        "export_held_out_rel_rms": relative_rms(ggx, app.held_captured),
        "gltf_held_out_rel_rms": relative_rms(gl, app.held_captured),
    }


def _png_scale(a: np.ndarray) -> float:
    """A round scale putting ``a``'s maximum at or below PNG full code (1 when it fits)."""
    top = float(np.max(a)) if a.size else 0.0
    return 1.0 if top <= 1.0 else float(2.0 ** np.ceil(np.log2(top)))


def _write(out: Path, session: str, method: str, formats: list[str], run: ResultRecord, app: Appearance,
           mesh: trimesh.Trimesh, bivariate: np.ndarray | None) -> ExportReport:
    rep = ExportReport(out)
    spatial = any(f in formats for f in ("maps", "gltf", "mitsuba"))
    b = _bake(app, mesh) if spatial else None
    model: dict[str, Any] = {
        "session": session, "method": method, "result_id": run.id, "code_version": run.code_version,
        "materials": app.n_materials,
        "frame": "object frame (the lab frame at turntable reading 0), millimetres; glTF in metres",
        "brdf": {"name": "Lambertian + GGX lobe (gonio export)", "formula": FORMULA,
                 "rho_d_convention": "rho_d is the diffuse albedo: the Lambertian term is rho_d / pi",
                 "units": "f_r in 1/sr when the calibration is absolute (gray card), else relative"},
        "uv": "u right, v down the image ((0, 0) the top-left corner), as glTF",
        "tangent_space": "MikkTSpace convention: T along +u, B = w (N x T) along -v (up the image), "
                         "n = normalize(x T + y B + z N); tangents (xyz, w) stored per vertex in mesh.ply "
                         "and model.glb",
        "files": {},
    }
    if b is not None:
        model["atlas"] = {"width": b.atlas.size[1], "height": b.atlas.size[0],
                          "texel_spacing_mm": texel_spacing_mm(app.position)}
        model["approximation"] = _approximation(app, b, run)
    if "maps" in formats:
        rep.files["maps"] = _write_maps(out, app, b, model["files"])
    if "gltf" in formats:
        write_glb(out / "model.glb", b.atlas, gltf_material(b.maps), b.normal_gltf, name=f"{session} {method}")
        rep.files["gltf"] = ["model.glb"]
        model["files"]["model.glb"] = {"format": "glTF 2.0 binary", "material": (
            "metallic 0; roughness = sqrt(alpha); KHR_materials_specular F0 = min(ks, 1); "
            "baseColor = min(rho_d / (1 - F0), 1); its error: approximation.gltf_*")}
    if "mitsuba" in formats:
        rep.files["mitsuba"] = _write_mitsuba(out, app, b, model["files"])
    if "merl" in formats:
        write_merl(out / "brdf.binary", TabulatedIsotropic.from_brdf(Bivariate(bivariate)))
        rep.files["merl"] = ["brdf.binary"]
        model["files"]["brdf.binary"] = {
            "format": "MERL binary (Matusik et al. 2003): int32 (90, 90, 180), then float64 R, G, B planes "
                      "times (1/1500, 1.15/1500, 1.66/1500) = f_r in 1/sr; -1 = unmeasured",
            "what": f"{method}'s tabulated isotropic BRDF (one for the whole object) at MERL's nodes"}
    (out / "model.json").write_text(json.dumps(model, indent=1, default=float))
    rep.model = model
    return rep


def _write_maps(out: Path, app: Appearance, b: _Baked, files: dict) -> list[str]:
    tex = out / "textures"
    tex.mkdir()
    write_ply(out / "mesh.ply", b.atlas.vertices, b.atlas.normals, b.atlas.uv, b.atlas.faces)
    files["mesh.ply"] = {"what": "the mesh with its atlas UVs (u, v) and normals; object frame, mm"}
    t = b.texels
    samples = np.where(t.covered, app.samples[t.texel], 0).astype(float)
    no_hl = (t.covered & app.no_highlight[t.texel]).astype(float)
    maps = {
        "diffuse_albedo": (b.maps.rho_d, "rho_d, linear RGB (the Lambertian term is rho_d / pi)"),
        "specular_scale": (b.maps.ks, "ks, linear RGB: the GGX lobe's scale"),
        "specular_alpha": (b.maps.alpha, "alpha, GGX roughness (glTF roughness = sqrt(alpha))"),
        "normal_tangent": ((b.normal_gltf + 1) / 2, "tangent-space normal (x, y, z) stored as (n + 1) / 2, "
                                                    "MikkTSpace convention (see tangent_space)"),
        "material_label": (np.where(t.covered, app.label[t.texel], -1).astype(float) + 1,
                           f"material + 1 (0 = not on the mesh), {app.n_materials} materials; PNG: code = "
                           "material + 1"),
        **({"cluster_label": (np.where(t.covered, app.cluster[t.texel], -1).astype(float) + 1,
                              "the method's cluster + 1 (0 = not on the mesh): a material's variant clusters "
                              "apart (texels that saw their highlight through a normal the mesh lacks, fitted "
                              "with a broader lobe); PNG: code = cluster + 1")}
           if len(np.unique(app.cluster)) > len(np.unique(app.label)) else {}),
        "confidence_samples": (samples, "training samples of the texel shown (0 off the charts)"),
        "confidence_no_highlight": (no_hl, "1 where the texel never saw its highlight (no training "
                                           "sample's halfway vector within 10 deg of its normal)"),
        "confidence_distance_mm": (np.where(t.covered, t.distance_mm, 0.0),
                                   "distance from the pixel's surface point to the texel it shows, mm"),
    }
    written = ["mesh.ply"]
    for name, (a, what) in maps.items():
        write_exr(tex / f"{name}.exr", a)
        scale = 65535.0 if name in ("material_label", "cluster_label", "confidence_samples") else _png_scale(a)
        write_png16(tex / f"{name}.png", a, scale)
        files[f"textures/{name}.exr"] = {"what": what, "format": "OpenEXR, 32-bit float, linear"}
        files[f"textures/{name}.png"] = {"what": what, "format": "PNG, 16-bit, linear",
                                         "value": f"code / 65535 * {scale:g}"}
        written += [f"textures/{name}.exr", f"textures/{name}.png"]
    return written


def _write_mitsuba(out: Path, app: Appearance, b: _Baked, files: dict) -> list[str]:
    d = out / "mitsuba"
    (d / "textures").mkdir(parents=True)
    write_ply(d / "object.ply", b.atlas.vertices, b.atlas.normals, b.atlas.uv, b.atlas.faces)
    textures = {"diffuse2": (2 * b.maps.rho_d, "diffuse2.exr"), "ks2": (2 * b.maps.ks, "ks2.exr"),
                "alpha": (b.maps.alpha, "alpha.exr"), "normal": ((b.normal_mitsuba + 1) / 2, "normal.exr")}
    for a, name in textures.values():
        write_exr(d / "textures" / name, a)
    (d / "object.xml").write_text(object_xml("object.ply", {k: f"textures/{v[1]}" for k, v in textures.items()}))
    written = ["mitsuba/object.ply", "mitsuba/object.xml"] + [f"mitsuba/textures/{v[1]}" for v in textures.values()]
    W, H = (int(v) for v in app.image_size)
    n_train = int(np.sum(~app.view_held_out))
    for k, (M, light, held) in enumerate(zip(app.view_camera_to_object, app.view_light_mm, app.view_held_out)):
        name = f"heldout-{k - n_train:03d}" if held else f"view-{k:03d}"
        view = MitsubaView(name, M, app.K, (W, H), light, app.light_intensity, bool(held))
        (d / f"{name}.xml").write_text(view_xml(view, "object.xml"))
        written.append(f"mitsuba/{name}.xml")
    files["mitsuba/"] = {
        "what": "Mitsuba 3 scenes: mitsuba -m scalar_rgb mitsuba/heldout-000.xml; one XML per captured pose "
                "(view-NNN training, heldout-NNN held out: camera and light in the object frame), object.xml "
                "the shared object; textures diffuse2 = 2 rho_d, ks2 = 2 ks (blendbsdf 0.5 halves them), "
                "alpha, normal (Mitsuba's normalmap frame: B = N x T, unsigned)",
        "camera": "pinhole with the calibrated fx, cx, cy (fy = fx, lens distortion not rendered)"}
    return written
