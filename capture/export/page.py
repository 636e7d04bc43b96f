"""The export's own page, ``DIR/report.html``: what ``gonio export`` wrote, how far each format is
from the method's model, and a renderer's image of it beside gonio's prediction.

Every file is linked relative to ``DIR`` (the page travels with the folder); pictures are
embedded PNGs. The render is Mitsuba 3's image of the first held-out capture's scene
(``mitsuba/heldout-000.xml``: the calibrated camera, the held-out light), beside gonio's own
prediction and the capture at the held-out samples (drawn where the pinhole images them), and
``|render - prediction| / mean prediction``. Mitsuba is a test extra, not a dependency of gonio:
without it the page says how to install it and still links every file.
"""
from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np

from reconstruct.metrics import relative_rms

from ..pipeline.pictures import splat
from ..pipeline.report_html import CSS, comparison_figure, html_table
from .appearance import Appearance
from .check import render_held_out

__all__ = ["PAGE", "write_export_page", "RENDER_SPP", "RENDER_SUPERSAMPLE"]

#: the page's name in the export folder
PAGE = "report.html"
#: Mitsuba's samples per pixel and film supersampling for the page's render (as the check's)
RENDER_SPP, RENDER_SUPERSAMPLE = 4, 3

#: what each stated figure of model.json's ``approximation`` means
_APPROXIMATION = {
    "export_vs_method_held_out_rel_rms": "the exported model (read through its textures) against the method's "
                                         "own prediction",
    "gltf_vs_method_held_out_rel_rms": "glTF's metallic-roughness material against the method's prediction",
    "export_held_out_rel_rms": "the exported model against the captures",
    "gltf_held_out_rel_rms": "glTF's material against the captures",
    "method_held_out_rel_rms": "the method itself against the captures (what the export approximates)",
}


def _files_table(files: dict[str, list[str]], described: dict[str, Any]) -> str:
    """Every file linked (relative to the export folder) with what it holds; a folder's own
    description (``mitsuba/``) once, on its first file."""
    rows, told = [], set()
    for fmt, names in files.items():
        for name in names:
            key = name if name in described else name.split("/")[0] + "/"
            what = described.get(key, {}) if key not in told else {}
            told.add(key)
            rows.append(f'<tr><td>{html.escape(fmt)}</td><td><a href="{html.escape(name)}">{html.escape(name)}</a>'
                        f"</td><td>{html.escape(what.get('what', what.get('format', '')))}</td></tr>")
    return ('<table><tr><th>format</th><th>file</th><th>what</th></tr>' + "".join(rows)
            + '<tr><td></td><td><a href="model.json">model.json</a></td><td>every file, its units, the '
              "exact BRDF formula and these figures</td></tr></table>")


def _approximation_table(approx: dict[str, Any]) -> str:
    rows = [{"compared": what, "relative RMS": approx[k], "figure in model.json": k}
            for k, what in _APPROXIMATION.items() if k in approx]
    per_material = approx.get("brdf_fit_rel_rms_per_material")
    return (f"<p>At the {approx.get('held_out_samples', 0)} held-out samples (lights the method never saw), "
            "relative RMS of reflectance:</p>" + html_table(rows)
            + ("" if per_material is None else
               f"<p>The exported BRDF's fit to the method's prediction at the training samples, per material: "
               f"{', '.join(f'{v:.3g}' for v in per_material)}.</p>"))


def _render_section(out: Path, app: Appearance, files: dict[str, list[str]]) -> str:
    """Mitsuba's render of the first held-out capture beside gonio's prediction and the capture,
    or why there is none."""
    held = np.flatnonzero(app.view_held_out)
    if "mitsuba" not in files:
        return ("<p>No render: the Mitsuba scenes were not exported (add <code>--format mitsuba</code>).</p>")
    if not len(held):
        return "<p>No render: the session has no held-out capture to compare with.</p>"
    try:   # Mitsuba is imported by the render: a test extra, not a dependency
        r = render_held_out(out / "mitsuba" / "heldout-000.xml", app, int(held[0]), spp=RENDER_SPP,
                            supersample=RENDER_SUPERSAMPLE)
    except ImportError as exc:
        return ("<p class='skipped'><b>No render</b>: Mitsuba 3 is not installed here "
                f"({html.escape(str(exc))}). It is not needed to export; to see the render, install it "
                "(<code>pip install mitsuba</code>) and export again, or render the linked scene yourself: "
                "<code>mitsuba -m scalar_rgb mitsuba/heldout-000.xml</code>.</p>")
    H, W = r.image.shape[:2]
    predicted, captured = (splat(r.pixels, v, (H, W)) for v in (r.predicted, r.captured))
    figure = comparison_figure([("Mitsuba 3 renders the export", r.image), ("gonio predicts", predicted),
                                ("captured", captured)], ("|render - prediction| / mean", r.image, predicted),
                               "Mitsuba's render of the export, gonio's prediction, the capture and their difference")
    rows = [{"compared at this capture's held-out samples": "Mitsuba's render vs gonio's prediction",
             "relative RMS": relative_rms(r.rendered, r.predicted)},
            {"compared at this capture's held-out samples": "Mitsuba's render vs the capture",
             "relative RMS": relative_rms(r.rendered, r.captured)},
            {"compared at this capture's held-out samples": "gonio's prediction vs the capture",
             "relative RMS": relative_rms(r.predicted, r.captured)}]
    return (f"<p>Mitsuba 3 (software gonio did not write) renders <a href='mitsuba/heldout-000.xml'>"
            f"mitsuba/heldout-000.xml</a>: the calibrated camera and a light the method never saw "
            f"({RENDER_SPP} samples per pixel on a {RENDER_SUPERSAMPLE}x finer film, averaged down). Beside it "
            f"gonio's own prediction and the capture at the {len(r.rendered)} held-out samples the render "
            "covers, drawn where the same pinhole images them; right: the render's difference from the "
            "prediction (dark is good).</p>" + figure + html_table(rows))


def write_export_page(out: Path, session: str, method: str, files: dict[str, list[str]],
                      model: dict[str, Any], app: Appearance) -> Path:
    """Write ``out/report.html`` for the export in ``out`` (``files`` per format, relative to
    ``out``; ``model`` as written to ``model.json``) and return its path."""
    import matplotlib
    matplotlib.use("Agg")
    approx = model.get("approximation")
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>gonio export: {html.escape(session)} "
             f"{html.escape(method)}</title><style>{CSS}</style></head><body>",
             f"<h1>gonio export: {html.escape(method)} of {html.escape(session)}</h1>",
             f"<p>Result {model.get('result_id')} ({html.escape(str(model.get('code_version', '')))}), as one BRDF "
             f"every format carries: <code>{html.escape(model['brdf']['formula'])}</code>; "
             f"{html.escape(model['brdf']['rho_d_convention'])}; {html.escape(model['brdf']['units'])}. "
             f"Frame: {html.escape(model['frame'])}.</p>",
             "<h2>Files</h2>" + _files_table(files, model.get("files", {})),
             "<h2>How far the export is from the method</h2>"
             + (_approximation_table(approx) if approx else "<p>Not computed: only a tabulated BRDF was "
                                                               "exported (MERL holds the method's table itself).</p>"),
             "<h2>A renderer's image of the export</h2>" + _render_section(out, app, files),
             "</body></html>"]
    path = out / PAGE
    path.write_text("\n".join(parts))
    return path
