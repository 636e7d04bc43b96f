"""The session report: one self-contained HTML file (every picture an embedded PNG).

:func:`write_html_report` draws what :func:`capture.pipeline.run.process_session` did from the store
(the plan, the frames' capture times, the stored reconstructions and their ``report.npz``
pictures) and the run's :class:`capture.pipeline.run.ProcessReport` (calibration stages, timings,
truth comparisons). Each section says in plain words what its pictures show, for a reader who has
never heard of the papers. Without ground truth the truth columns are left out. An imported
session (:mod:`capture.pipeline.imported`) gets the same report with what was imported in place
of the plan, and the normals' error maps against the set's ground truth.

The Exports section lists the pages ``gonio export`` wrote (:func:`link_export` adds a row in
place; the rows live in the report as JSON and survive a rewrite). The page pieces
(:func:`html_table`, :func:`comparison_figure` ...) also draw the export's own page
(:mod:`capture.export.page`).
"""
from __future__ import annotations

import base64
import html
import io
import json
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..outputs import write_atomically
from ..store import ResultRecord, Store
from .passive_sample import SAMPLE_FIGURES
from .pictures import SLICE_THETA_I_DEG
from .plan_table import plan_rows

__all__ = ["write_html_report", "METHOD_NOTES", "summary_note", "ExportLink", "export_links", "link_export",
           "check_session_report", "comparison_figure", "html_table", "img_tag", "png_uri", "tonemap", "CSS"]

#: what each method is, in one paragraph a newcomer can read
METHOD_NOTES = {
    "lambertian": "The reference: every surface point gets one colour (an albedo) and is assumed "
                  "perfectly matte, as a plain photograph would suggest. Any real reflectance method "
                  "must predict the held-out lights better than this.",
    "lensch": "Lensch et al. 2003: the object is made of a few basic materials (found by clustering "
              "the measurements); every point's reflectance is a non-negative mix of them, and each "
              "point's surface normal is refined so that bumps the mesh lacks reappear.",
    "sharing": "Zickler et al. 2005 (reflectance sharing): neighbouring points lend each other their "
               "measurements, so a smooth interpolation over position and angle predicts each point's "
               "reflectance from very few images; diffuse and specular parts come apart by polarization. "
               "The method needs exact surface normals: where the matte (diffuse) part shows that a "
               "point's normal differs from the mesh's, the normal is first refitted from it (photometric "
               "stereo), so bumps the mesh lacks do not move the predicted highlights.",
    "passive": "Romeiro et al. 2008 (passive reflectometry): one image of a curved surface of one material, "
               "lit only by the room, whose light is known from a mirror-ball photograph, gives that material's "
               "reflectance function. The lab photographs a sphere of the sample material for it; a session "
               "without that photograph uses its image of the object, whose several materials the one "
               "function can only average.",
}


def png_uri(fig) -> str:
    import matplotlib.pyplot as plt
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def img_tag(uri: str, alt: str) -> str:
    return f'<img src="{uri}" alt="{html.escape(alt)}">'


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        if not np.isfinite(v):
            return "–"
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items())
    return html.escape(str(v))


def html_table(rows: list[dict[str, Any]], columns: list[str] | None = None) -> str:
    if not rows:
        return "<p><em>none</em></p>"
    cols = columns or list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(r.get(c, ''))}</td>" for c in cols) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def tonemap(img: np.ndarray, scale: float) -> np.ndarray:
    """Linear radiance -> display RGB: exposure ``scale``, sRGB-like gamma; NaN -> white."""
    out = np.clip(np.nan_to_num(img / scale, nan=1.0), 0, 1) ** (1 / 2.2)
    return out


# -- sections -----------------------------------------------------------------------------------
def _timeline(store: Store, session_id: int) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    frames = store.frames(session_id)
    if not frames:
        return ""
    steps = {s.index: s.spec for s in store.steps(session_id)}
    t0 = min(f.captured_at for f in frames)
    fig, ax = plt.subplots(figsize=(8, 2.6))
    kinds = sorted({steps[f.step]["kind"] for f in frames})
    for k, kind in enumerate(kinds):
        ts = [f.captured_at - t0 for f in frames if steps[f.step]["kind"] == kind]
        ax.plot(ts, [k] * len(ts), "|", ms=12, label=kind)
    ax.set_yticks(range(len(kinds)), kinds)
    ax.set_xlabel("time since the first frame (s)")
    ax.set_title("capture timeline: every frame, by kind of step")
    return img_tag(png_uri(fig), "capture timeline")


def comparison_figure(panels: list[tuple[str, np.ndarray]], error: tuple[str, np.ndarray, np.ndarray],
                      alt: str, *, dots: bool = False) -> str:
    """Radiance images (H, W, 3) side by side at one exposure, then ``error = (title, a, b)``:
    ``|a - b| / mean |b|`` per pixel. Every panel is cropped to the pixels where both ``a`` and
    ``b`` are known (not NaN), and exposed at ``b``'s 99.5th percentile there. ``dots``: a panel
    known at scattered pixels only (a method fitted to a random subset) is drawn as dots on grey,
    so its pixels are seen, not lost among the white of the unknown ones."""
    import matplotlib.pyplot as plt
    title, a, b = error
    on = ~np.isnan(a).any(axis=2) & ~np.isnan(b).any(axis=2)
    scale = float(np.percentile(b[on], 99.5)) if on.any() else 1.0
    mean = float(np.mean(np.linalg.norm(b[on], axis=1))) if on.any() else 1.0
    err = np.linalg.norm(np.nan_to_num(a - b), axis=2) / max(mean, 1e-12)
    err[~on] = np.nan
    ys, xs = np.nonzero(on)
    y0, x0 = (max(ys.min() - 4, 0), max(xs.min() - 4, 0)) if len(ys) else (0, 0)
    crop = (slice(y0, ys.max() + 5), slice(x0, xs.max() + 5)) if len(ys) else (slice(None), slice(None))
    fig, axes = plt.subplots(1, len(panels) + 1, figsize=(3.4 * (len(panels) + 1), 3.6))

    def scatter(ax, img, values, **kw):
        ax.imshow(np.full(img[crop].shape[:2], 0.5), cmap="gray", vmin=0, vmax=1)
        known = ~np.isnan(img).any(axis=2) if img.ndim == 3 else ~np.isnan(img)
        py, px = np.nonzero(known)
        return ax.scatter(px - x0, py - y0, c=values[known], s=2, linewidths=0, **kw)

    for ax, (name, img) in zip(axes, panels):
        if dots and np.isnan(img).any():
            scatter(ax, img, tonemap(img, scale))
        else:
            ax.imshow(tonemap(img, scale)[crop])
        ax.set_title(name, fontsize=9)
    if dots:
        im = scatter(axes[-1], err, err, cmap="magma", vmin=0, vmax=1)
    else:
        im = axes[-1].imshow(err[crop], cmap="magma", vmin=0, vmax=1)
    axes[-1].set_title(title, fontsize=9)
    fig.colorbar(im, ax=axes[-1], fraction=0.046)
    for ax in axes:
        ax.axis("off")
    return img_tag(png_uri(fig), alt)


def _held_out_figure(pics: dict[str, np.ndarray], suffix: str = "", *, dots: bool = False) -> str:
    cap, pred = pics["heldout_captured" + suffix], pics["heldout_predicted" + suffix]
    return comparison_figure([("captured under a held-out light", cap), ("predicted by the model", pred)],
                             ("|error| / mean radiance", pred, cap), "held-out capture, prediction and error",
                             dots=dots)


def _held_out_part(pics: dict[str, np.ndarray]) -> str:
    """The held-out figures: a captured session's first held-out view, or an imported set's
    photographs under its most frontal and most oblique held-out lights (``heldout_lights``)."""
    if "heldout_lights" not in pics:
        return ("<p>Left: a capture under a light the model never saw; middle: the model's "
                "prediction for the same light; right: their difference (dark is good).</p>" + _held_out_figure(pics))
    parts = []
    for suffix, (k, deg) in zip(("", "_2"), pics["heldout_lights"]):
        fitted = int(np.isfinite(pics["heldout_predicted" + suffix]).all(axis=2).sum())
        parts.append(f"<p>Left: the photograph under held-out light {int(k) + 1} ({deg:.0f}° from the "
                     "view axis), which no fit saw; middle: the model's prediction, drawn only at the "
                     f"{fitted} pixels it fitted that this light reaches (grey: not fitted); right: their "
                     "difference (dark is good).</p>" + _held_out_figure(pics, suffix, dots=True))
    return "".join(parts)


def _slices_figure(pics: dict[str, np.ndarray], theta_i: float) -> str:
    import matplotlib.pyplot as plt
    fits = sorted(k for k in pics if k.startswith("slice_fit_"))
    if not fits:
        return ""
    theta = pics["slice_theta_o_deg"]
    fig, axes = plt.subplots(1, len(fits), figsize=(3.2 * len(fits), 3), squeeze=False)
    for ax, key in zip(axes[0], fits):
        g = key.removeprefix("slice_fit_")
        for c, col in enumerate("rgb"):
            ax.semilogy(theta, np.maximum(pics[key][:, c], 1e-4), col + "-", lw=1.5)
            if f"slice_true_{g}" in pics:
                ax.semilogy(theta, np.maximum(pics[f"slice_true_{g}"][:, c], 1e-4), col + "--", lw=1)
        ax.axvline(theta_i, color="gray", lw=0.5)
        ax.set_title(f"material {g}" if g != "all" else "all points")
        ax.set_xlabel("viewing angle θo (°)")
    axes[0][0].set_ylabel("BRDF f_r (1/sr)")
    fig.suptitle(f"reflectance in the plane of incidence, light at θi = {theta_i:g}° "
                 "(solid: recovered, dashed: true)", fontsize=9)
    return img_tag(png_uri(fig), "BRDF slices")


def _normals_figure(pics: dict[str, np.ndarray]) -> str:
    """The fitted normals as colour, and how far the fitted (and true) normals lean from the
    mesh's: the relief the mesh lacks, recovered from the shading."""
    import matplotlib.pyplot as plt
    mesh = pics["normals_mesh"]
    on = ~np.isnan(mesh).any(axis=2)
    ys, xs = np.nonzero(on)
    crop = (slice(max(ys.min() - 2, 0), ys.max() + 3), slice(max(xs.min() - 2, 0), xs.max() + 3))

    def lean(key):
        cos = np.clip(np.sum(pics[key] * mesh, axis=2), -1, 1)
        return np.where(on, np.degrees(np.arccos(cos)), np.nan)[crop]

    panels = [("fitted normals (colour: x, y, z)", np.nan_to_num((pics["normals_fitted"] + 1) / 2, nan=1.0)
               .clip(0, 1)[crop], None)]
    panels.append(("fitted: lean from the mesh (deg)", lean("normals_fitted"), "viridis"))
    if "normals_true" in pics:
        panels.append(("truth: lean from the mesh (deg)", lean("normals_true"), "viridis"))
    top = max(float(np.nanpercentile(p[1], 99)) for p in panels[1:])
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.6), squeeze=False)
    for ax, (title, img, cmap) in zip(axes[0], panels):
        im = ax.imshow(img, cmap=cmap, vmin=0 if cmap else None, vmax=top if cmap else None)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
        if cmap:
            fig.colorbar(im, ax=ax, fraction=0.046)
    return img_tag(png_uri(fig), "normal maps")


def _lights_figure(rows: list[dict[str, Any]]) -> str:
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(9, 3))
    labels = [f"{r['azimuth_deg']:g}/{r['elevation_deg']:g}" for r in rows]
    x = np.arange(len(rows))
    axes[0].bar(x, [r["distance_error_pct"] for r in rows])
    axes[0].axhline(0.5, color="r", lw=0.8)
    axes[0].axhline(-0.5, color="r", lw=0.8)
    axes[0].set_ylabel("distance error (%)")
    axes[1].bar(x, [r["direction_error_deg"] for r in rows])
    axes[1].axhline(0.25, color="r", lw=0.8)
    axes[1].set_ylabel("direction error (°)")
    for a in axes:
        a.set_xticks(x, labels, rotation=60, fontsize=7)
        a.set_xlabel("light azimuth/elevation (°)")
    fig.suptitle("calibrated lamp positions against the truth (red: the calibration's targets)", fontsize=9)
    return img_tag(png_uri(fig), "light calibration errors")


def _environment_figure(store: Store, session_id: int) -> str:
    import matplotlib.pyplot as plt
    probe = [r for r in store.results(session_id, "calibration") if r.kind == "environment_map"]
    if not probe or "environment.npz" not in probe[-1].artifacts:
        return ""
    with np.load(io.BytesIO(store.read_object(probe[-1].artifacts["environment.npz"]))) as z:
        env, weight = z["env"], z["weight"]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    img = tonemap(env, float(np.percentile(env, 99)) or 1.0) * np.clip(weight, 0, 1)[..., None]
    ax.imshow(img, extent=(0, 360, -90, 90))  # column 0: azimuth 0 (+x, towards the camera)
    ax.set_xlabel("azimuth (°, lab frame)")
    ax.set_ylabel("elevation (°)")
    ax.set_title("the room's light from the mirror-ball photograph (black: not seen)")
    return img_tag(png_uri(fig), "environment map")


def _calibration_section(rep, truth, store: Store, session_id: int, intro: str) -> str:
    parts = ["<h2>2. Calibration</h2>", f"<p>{intro}</p>",
             html_table([{"stage": c["stage"], "status": c["status"], "figures": c.get("figures", {}),
                      "note": c.get("reason", "")} for c in rep.calibration])]
    ct = rep.calibration_truth
    if ct:
        parts.append("<h3>Against the simulation's ground truth</h3>"
                     "<p>Targets of the calibration: light position within 0.5 % of its distance and "
                     "0.25° in direction, focal length within 0.2 %.</p>")
        parts.append(html_table([{"focal length error (%)": ct["focal_error_pct"],
                              "principal point error (px)": ct["principal_point_error_px"],
                              "camera centre error (mm)": ct["camera_centre_error_mm"],
                              "lamp intensity error (%)": ct.get("intensity_error_pct", "relative units"),
                              "lights from": ct["light_source"]}]))
        parts.append(html_table(ct.get("lights", []), ["azimuth_deg", "elevation_deg", "error_mm",
                                                    "distance_error_pct", "direction_error_deg"]))
        if ct.get("lights"):
            parts.append(_lights_figure(ct["lights"]))
    env = _environment_figure(store, session_id)
    if env:
        parts.append("<p>The room's light as the mirror ball saw it, unwrapped to a map of directions: "
                     "passive reflectometry explains the object's appearance by this light alone.</p>" + env)
    return "\n".join(parts)


def _method_section(i: int, outcome, stored: ResultRecord | None, pics: dict[str, np.ndarray] | None) -> str:
    name = outcome.method
    parts = [f"<h3>{i}. {html.escape(name)}</h3>", f"<p>{html.escape(METHOD_NOTES.get(name, ''))}</p>"]
    if outcome.outside_assumption:
        parts.append(f"<p class='outside'><b>Outside its assumption</b>: {html.escape(outcome.outside_assumption)}.</p>")
    if outcome.status in ("skipped", "failed"):
        parts.append(f"<p class='{outcome.status}'><b>{outcome.status}</b>: {html.escape(outcome.reason)}</p>")
        return "\n".join(parts)
    figures = outcome.figures if stored is None else stored.result.get("figures", outcome.figures)
    rows = [{"measure": k, "value": v} for k, v in figures.items()
            if k not in ("table_ii_rms", "poorly_observed", "unconstrained", *SAMPLE_FIGURES)]
    if "image_of" in figures:
        parts.append(_sample_sphere_part(figures, pics or {}))
    if "held_out_rel_rms" in figures:
        parts.append("<p><b>held_out_rel_rms</b>: relative RMS difference between the model's prediction and "
                     "the captures under lights it never saw (<b>_trimmed</b>: without the 1 % worst samples, "
                     "which carry most of a glossy object's pooled error); <b>truth_rel_rms</b>: the same against "
                     "the true reflectance (simulation only).</p>")
    parts.append(html_table(rows))
    if figures.get("table_ii_rms"):
        parts.append("<p>Lensch Table II: the RMS fitting error after each stage (single average BRDF, "
                     "per cluster, projection, PFA, normal fitting) — it should fall from left to right.</p>"
                     + html_table([figures["table_ii_rms"]]))
    if "poorly_observed" in figures:
        parts.append(_adequacy_table(figures))
    warnings = outcome.warnings if stored is None else stored.result.get("warnings", outcome.warnings)
    if warnings:
        parts.append("<ul class='warn'>" + "".join(f"<li>{html.escape(w)}</li>" for w in warnings) + "</ul>")
    if pics:
        if "heldout_captured" in pics:
            parts.append(_held_out_part(pics))
        s = _slices_figure(pics, SLICE_THETA_I_DEG)
        if s:
            parts.append("<p>How much light the surface reflects towards each viewing angle when lit from "
                         f"{SLICE_THETA_I_DEG:g}° (the peak near +{SLICE_THETA_I_DEG:g}° is the highlight).</p>" + s)
        if "normals_fitted" in pics:
            parts.append("<p>The surface orientation the method recovered from the shading (as colour), and how "
                         "far it leans from the smooth mesh it was given: bumps and engravings the mesh lacks "
                         "show up here (beside the truth, in a simulation).</p>" + _normals_figure(pics))
    return "\n".join(parts)


_SAMPLE_LABELS = {
    "image_of": "the image is of", "sphere_pixels": "pixels used",
    "eq1_error": "BRDF error against the truth (Romeiro Eq. 1, per sample)",
    "eq1_error_lambertian": "the same for the best matte (Lambertian) BRDF",
    "eq1_error_reduction": "the same for the true BRDF reduced to the method's 2-D table (the best it can do)",
    "eq1_error_pooled": "BRDF error against the truth (Eq. 1 pooled: RMS difference / RMS value)",
    "render_rel_rms": "recovered BRDF rendered under the room's light vs the photograph (rel. RMS)",
    "floor_render_rel_rms": "the floor: the true BRDF rendered under the room's light as measured vs the photograph "
                            "(what the probe map, the sensor and the geometry leave)",
    "truth_render_rel_rms": "recovered vs true BRDF rendered under the room's light (rel. RMS)",
    "held_out_env_rel_rms": "recovered vs true BRDF rendered under another room's light (rel. RMS)"}


def _sample_sphere_part(figures: dict[str, Any], pics: dict[str, np.ndarray]) -> str:
    """Passive reflectometry on the sample sphere: its figures against the truth and the sphere
    rendered with the recovered and the true BRDF (:mod:`capture.pipeline.passive_sample`)."""
    rows = [{"measure": _SAMPLE_LABELS[k], "value": figures[k]} for k in SAMPLE_FIGURES if k in figures]
    parts = ["<p><b>On the sample sphere.</b> The method ran on its photograph of the homogeneous sample "
             "sphere, within its assumption (one material, a known curved shape), so its result is that "
             "material's reflectance and is scored against it, not on the object's held-out lights. The "
             "BRDF error compares the recovered reflectance function with the true one over every pair of "
             "directions (0 is perfect; a matte guess shows what ignoring the highlight costs). The floor is "
             "the true reflectance rendered under the room's light as the mirror ball measured it: where it is "
             "far from the photograph, that measured light cannot explain the sphere even with the true "
             "material, and the figures against the truth measure the light probe rather than the "
             "method.</p>" + html_table(rows)]
    if "sample_captured" in pics:
        cap, rec = pics["sample_captured"], pics["sample_recovered"]
        panels = [("photographed under the room's light", cap), ("recovered BRDF, rendered", rec)]
        if "sample_truth" in pics:
            panels.append(("true BRDF, rendered", pics["sample_truth"]))
            err = ("|recovered − true| / mean radiance", rec, pics["sample_truth"])
        else:
            err = ("|recovered − photograph| / mean radiance", rec, cap)
        parts.append("<p>The sample sphere under the room's light: the photograph, the recovered "
                     "reflectance rendered on the sphere, and (simulation) the true one.</p>"
                     + comparison_figure(panels, err, "sample sphere: photograph, recovered and true"))
    if "sample_heldout_truth" in pics:
        want, got = pics["sample_heldout_truth"], pics["sample_heldout_recovered"]
        parts.append("<p>The same sphere rendered under another room's light, which the method never saw: "
                     "true and recovered reflectance.</p>"
                     + comparison_figure([("true BRDF, another room", want), ("recovered BRDF, another room", got)],
                                         ("|recovered − true| / mean radiance", got, want),
                                         "sample sphere under a held-out environment"))
    return "\n".join(parts)


def _adequacy_table(figures: dict[str, Any]) -> str:
    """Passive reflectometry's adequacy report (Romeiro et al. Sect. 3.1) as a table: the regions of
    the BRDF's (theta_h, theta_d) domain and the share of their nodes the room lit too little to
    constrain (there the recovered BRDF is the prior's extrapolation)."""
    rows = [{"range of the BRDF": k, "share of poorly lit nodes": f"{v:.0%}"}
            for k, v in figures["poorly_observed"].items()]
    rows += [{"range of the BRDF": f"theta_d {b['theta_d_deg'][0]}–{b['theta_d_deg'][1]}°, theta_h "
                                   f"{b['theta_h_deg']}°",
              "share of poorly lit nodes": f"{b['poorly_lit_share']:.0%} of the band"}
             for b in figures.get("unconstrained", [])]
    return ("<p><b>What the room's light could not constrain.</b> One image under the room's light sees "
            "each surface orientation from one direction, so parts of the reflectance function are lit "
            "too little to be measured (less than a tenth of the light a uniform sky would give, or "
            "never seen); there the recovered function is the prior's guess, learned from other "
            "materials. θh: angle between the normal and the halfway vector (0: mirror direction); "
            "θd: angle between the light and the halfway vector (0: retro-reflection, 90: grazing).</p>"
            + html_table(rows))


def summary_note(m, figures: dict[str, Any]) -> str:
    """A method's note in the summary: outside its assumption, or scored on the sample sphere."""
    if m.outside_assumption:
        return f"outside its assumption: {m.outside_assumption}"
    if "image_of" not in figures:
        return ""
    note = f"on {figures['image_of']}, not the object (no held-out lights)"
    if "eq1_error" in figures:
        note += (f": BRDF error (Eq. 1) {figures['eq1_error']:.3g}, a matte BRDF's "
                 f"{figures['eq1_error_lambertian']:.3g}")
    return note


def _summary(rep, figures, with_truth: bool, imported: bool = False) -> str:
    """The methods table (held-out score, its ratio to the floor, the error against the truth;
    for an imported set the normals' error against its ground truth) and the floor, or why there
    is none."""
    def ratio(m) -> Any:
        return "–" if m.floor_ratio is None else f"{m.floor_ratio:.2f}×"

    rows = [{"method": m.method, "status": m.status,
             "held-out rel. RMS": figures(m).get("held_out_rel_rms", float("nan")),
             **({"× floor": ratio(m)} if rep.floor is not None else {}),
             **({"vs truth rel. RMS": figures(m).get("truth_rel_rms", float("nan"))} if with_truth else {}),
             **({"normal error (°)": figures(m).get("normal_error_deg", "–")} if imported else {}),
             "note": summary_note(m, figures(m))}
            for m in rep.methods]
    if rep.floor is not None:
        note = (f"<p><b>The floor</b>: the simulation's true reflectance, scored exactly as the methods are "
                f"on the same held-out captures, is {rep.floor.held_out_rel_rms:.3g} off them "
                f"({rep.floor.held_out_rel_rms_trimmed:.3g} without the 1 % worst samples): what sensor noise, "
                "calibration and resampling leave. No model can be expected to score lower; <b>× floor</b> is each "
                "method's held-out error over it (1 would be as good as the truth).</p>")
    elif with_truth:   # results stored before the floor existed, or no held-out light captured
        note = ("<p><b>No floor</b>: the true model was not scored on held-out captures in this run (none "
                "captured, or results stored before the floor was; <code>gonio process --force</code> "
                "recomputes them).</p>")
    elif imported:
        note = ("<p><b>No floor</b>: the true reflectance of an imported object is unknown (only its normals "
                "may be given), so the held-out errors stand alone: each method must beat the Lambertian "
                "reference.</p>")
    else:
        note = ("<p><b>No floor</b>: the true reflectance of this object is unknown (the floor, the true model "
                "scored on the held-out captures, exists only for sessions captured in the simulated lab), so "
                "the held-out errors stand alone.</p>")
    return html_table(rows) + note


def _plan_section(store: Store, info, prog) -> str:
    """The plan as a table of its kinds of step, the stored plan itself folded away."""
    rows = [{"kind": r.kind, "steps": r.steps, "turntable (°)": r.turntable, "lamp (°)": r.lights,
             "polarizer (°)": r.polarizer, "exposures": r.exposures,
             "frames": r.frames_stored if r.frames_stored == r.frames_planned
             else f"{r.frames_stored} of {r.frames_planned}",
             "MB": round(r.bytes_stored / 1e6, 2)}
            for r in plan_rows([s.step for s in store.steps(info.id)], store.frames(info.id))]
    return ("<h2>1. The plan and the capture</h2>"
            f"<p>{prog.steps_done} of {prog.steps_total} steps, {prog.frames_stored} frames "
            f"({prog.bytes_stored / 1e6:.1f} MB). One row per kind of step: the turntable angles, lamp "
            "positions (azimuth × elevation about the turntable axis) and polarizer angles it visits, in "
            "degrees (<i>a–b by s (n)</i>: n angles from a to b in steps of s); <i>held out</i> steps are "
            "captured like the rest but never fitted: they score the models.</p>"
            + html_table(rows)
            + "<details><summary>the plan as stored (JSON)</summary>"
            f"<pre>{html.escape(json.dumps(info.plan, indent=1))}</pre></details>"
            + _timeline(store, info.id))


# -- exports: `gonio export` links its page here ------------------------------------------------
_EXPORTS = re.compile(r"<!-- gonio:exports -->.*?<!-- /gonio:exports -->", re.S)
_EXPORTS_JSON = re.compile(r'<script type="application/json" id="gonio-exports" data-session="([^"]*)">(.*?)</script>',
                           re.S)


@dataclass(frozen=True)
class ExportLink:
    """One ``gonio export`` as the session report lists it: ``page`` the export's own page
    (``DIR/report.html``) relative to the report's folder, the method and formats, and the
    export's stated error against the method at the held-out samples (None: not computed)."""

    page: str
    method: str
    formats: tuple[str, ...]
    export_vs_method: float | None
    written: str


def export_links(report: str | Path) -> list[ExportLink]:
    """The exports a written session report lists ([] when it does not exist or lists none)."""
    try:
        m = _EXPORTS_JSON.search(Path(report).read_text())
    except FileNotFoundError:
        return []
    if m is None:
        return []
    try:
        rows = json.loads(m.group(2))   # JSON reads "<\/" (written below) as "</"
        return [ExportLink(r["page"], r["method"], tuple(r["formats"]), r["export_vs_method"], r["written"])
                for r in rows]
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{report}: its list of exports is damaged ({exc}); re-write the report with "
                         "gonio process") from None


def _exports_section(session: str, links: list[ExportLink]) -> str:
    data = json.dumps([asdict(x) for x in links]).replace("</", "<\\/")
    if links:
        body = ("<p>Each export's own page links its files, states how far the exported model is from the "
                "method's and shows a renderer's image of it beside gonio's prediction.</p>"
                + "<table><tr><th>export</th><th>method</th><th>formats</th><th>export vs method (rel. RMS, "
                  "held out)</th><th>written</th></tr>"
                + "".join(f'<tr><td><a href="{html.escape(x.page)}">{html.escape(x.page)}</a></td>'
                          f"<td>{html.escape(x.method)}</td><td>{html.escape(', '.join(x.formats))}</td>"
                          f"<td>{_fmt(x.export_vs_method if x.export_vs_method is not None else '–')}</td>"
                          f"<td>{html.escape(x.written)}</td></tr>" for x in links) + "</table>")
    else:
        body = ("<p>None yet: <code>gonio export SESSION --method M --out DIR</code> writes the recovered "
                "appearance in formats other software reads and links its page here.</p>")
    return (f'<!-- gonio:exports --><h2>6. Exports</h2>{body}'
            f'<script type="application/json" id="gonio-exports" data-session="{html.escape(session)}">{data}'
            '</script><!-- /gonio:exports -->')


def check_session_report(report: str | Path, session: str) -> None:
    """Raise ``FileNotFoundError`` when ``report`` does not exist, ``ValueError`` when it is not
    ``session``'s report with an Exports section (or that section is damaged)."""
    report = Path(report)
    text = report.read_text()
    m = _EXPORTS_JSON.search(text)
    if not _EXPORTS.search(text) or m is None:
        raise ValueError(f"{report} is not a gonio session report with an Exports section (written by "
                         "gonio process; re-run it to update an older report)")
    if html.unescape(m.group(1)) != session:
        raise ValueError(f"{report} is the report of session {html.unescape(m.group(1))!r}, not {session!r}")
    export_links(report)


def link_export(report: str | Path, session: str, link: ExportLink) -> Path:
    """Add ``link`` (replacing one to the same page) to the Exports section of ``session``'s
    written report ``report``, in place and atomically. Raises as :func:`check_session_report`."""
    check_session_report(report, session)
    links = [x for x in export_links(report) if x.page != link.page] + [link]
    section = _exports_section(session, links)
    return write_atomically(report, _EXPORTS.sub(lambda _: section, Path(report).read_text(), count=1))


CSS = """body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:2px 8px;font-size:90%}
th{background:#eee}img{max-width:100%}.skipped{color:#866}.failed{color:#b00}.warn{color:#a60}
.outside{background:#fff3d6;border-left:4px solid #e0a000;padding:4px 8px}"""


_CAPTURED_INTRO = ("gonio measured how this object reflects light: a turntable turned it, a lamp on an arm lit "
                  "it from many directions, a camera photographed it through a rotating polarizer at several "
                  "exposures, and the rig calibrated itself from its own captures. Reconstruction methods then "
                  "recovered the object's reflectance; each is judged by predicting captures under lights it "
                  "was never shown.")
_IMPORTED_INTRO = ("This session was not captured by gonio: it is a multi-light image set recorded elsewhere "
                   "(photographs of one object under many distant lights, with the lights, a mask and, where "
                   "given, the true surface normals) and imported as it was. gonio recovered the object's "
                   "surface orientation and reflectance from the images; each method is judged by predicting "
                   "the images under lights it was never shown, and the normals against the set's ground truth.")
_CAPTURED_CALIBRATION = ("Before anything can be measured, the rig measures itself from its own calibration "
                         "captures: the camera's lens (from a printed board), where the turntable's axis is, where "
                         "the lamp was for every capture (from its reflections in mirror balls), the lamp's "
                         "brightness (from an 18 % gray card) and the room's light (from a mirror ball).")
_IMPORTED_CALIBRATION = ("An imported set brings what calibration would measure (the light directions and "
                         "intensities, an orthographic camera), so the rig's calibration stages are skipped; each "
                         "is listed with the reason.")


def _imported_section(facts) -> str:
    """What was imported: provenance, images, lights (training and held out), the mask."""
    prov = facts.provenance
    rows = [{"object": prov.get("object"), "format": prov.get("format"), "source": prov.get("source"),
             "images": facts.images, "image size (px)": "{} × {}".format(*facts.image_size_px),
             "bit depth": prov.get("bit_depth"), "training lights": int((~facts.held_out).sum()),
             "held-out lights": int(facts.held_out.sum()), "mask pixels": facts.mask_pixels,
             "ground-truth normals": "yes (scoring only)" if facts.normal_errors else "no",
             "files with SHA-256 recorded": facts.files_hashed}]
    return ("<h2>1. What was imported</h2>"
            f"<p>{html.escape(str(prov.get('citation', '')))}</p>" + html_table(rows)
            + "<p>Every file's bytes are stored in the session as they were, with their SHA-256. Light "
              "directions are in the camera frame (x right, y down, z away from the camera); every "
              f"{prov.get('held_out_every', '–')}th light is held out: never fitted, it scores the models.</p>"
            + _lights_figure_imported(facts.light_directions, facts.held_out))


def _lights_figure_imported(directions: np.ndarray, held_out: np.ndarray) -> str:
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(3.8, 3.8))
    ax.add_patch(plt.Circle((0, 0), 1, fill=False, color="gray", lw=0.5))
    for sel, mark, label in ((~held_out, "o", "training"), (held_out, "x", "held out")):
        ax.plot(directions[sel, 0], directions[sel, 1], mark, ms=4, label=label)
    ax.set_xlim(-1.05, 1.05)
    ax.set_ylim(1.05, -1.05)          # y down, as in the images
    ax.set_aspect("equal")
    ax.set_xlabel("x (right)")
    ax.set_ylabel("y (down)")
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title("light directions seen from the camera", fontsize=9)
    return img_tag(png_uri(fig), "light directions")


def _normal_errors_figure(maps: dict[str, np.ndarray], fitted: np.ndarray) -> str:
    """Angular error maps (deg) side by side on one colour scale, cropped to the scored pixels.
    A map scored at few pixels (a method fitted to a random subset) is drawn as dots over the
    object's silhouette; a dense one also states its mean at the ``fitted`` pixels, the subset's."""
    import matplotlib.pyplot as plt
    on = np.any([np.isfinite(m) for m in maps.values()], axis=0)
    ys, xs = np.nonzero(on)
    y0, x0 = ys.min(), xs.min()
    crop = (slice(y0, ys.max() + 1), slice(x0, xs.max() + 1))
    top = max(float(np.nanpercentile(m, 99)) for m in maps.values())
    fig, axes = plt.subplots(1, len(maps), figsize=(3.6 * len(maps), 3.6), squeeze=False)
    for ax, (name, m) in zip(axes[0], maps.items()):
        scored = np.isfinite(m)
        title = f"{name}: mean {np.nanmean(m):.2f}°"
        if scored.sum() < 0.5 * on.sum():
            ax.imshow(np.where(on, 0.85, 1.0)[crop], cmap="gray", vmin=0, vmax=1)
            py, px = np.nonzero(scored)
            im = ax.scatter(px - x0, py - y0, c=m[scored], s=3, cmap="viridis", vmin=0, vmax=top, linewidths=0)
            title += f"\nat its {scored.sum()} pixels"
        else:
            im = ax.imshow(m[crop], cmap="viridis", vmin=0, vmax=top)
            if (fitted & scored).sum() < scored.sum():
                title += f"\n({np.nanmean(m[fitted]):.2f}° at the {fitted.sum()} fitted pixels)"
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.colorbar(im, ax=axes[0].tolist(), fraction=0.03, label="angle to the true normal (°)")
    return img_tag(png_uri(fig), "normal error maps")


def _normals_section(facts) -> str:
    if not facts.normal_errors:
        return ("<h2>4. Normals</h2><p>The set has no ground-truth normals, so the recovered normals "
                "are not scored.</p>")
    return ("<h2>4. Normals against the ground truth</h2><p>How far each recovered surface normal is "
            "from the set's true one (degrees; the truth is used only here, never in a fit). Least "
            "squares: Lambertian photometric stereo on the training lights; robust: the same without each "
            "pixel's darkest and brightest lights and those the fit shades or far exceeds (shadows, "
            "highlights); the methods' own normals at the pixels they fitted "
            f"({html.escape(facts.texels_note)}).</p>" + _normal_errors_figure(facts.normal_errors, facts.fitted))


def write_html_report(store: Store, session: str, rep, *, truth=None, path: str | Path,
                      imported=None) -> Path:
    """Write the session's report (HTML with embedded PNGs) to ``path`` and return it.

    ``imported``: for a session imported from another lab's image set, its
    :class:`capture.pipeline.imported.ImportedFacts` (what was imported and the normals' error
    maps), which replace the plan and the capture."""
    import matplotlib
    matplotlib.use("Agg")
    info = store.session(session)
    stored = {r.kind: r for r in store.results(info.id, "reconstruction")}
    intro = _IMPORTED_INTRO if imported is not None else _CAPTURED_INTRO + (
        " This session comes from the simulated lab, so every figure is also compared with the ground truth."
        if truth is not None else "")
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>gonio: {html.escape(session)}</title>"
             f"<style>{CSS}</style></head><body>",
             f"<h1>gonio report: {html.escape(session)}</h1>", f"<p>{intro}</p>"]

    def figures(m) -> dict:
        r = stored.get(m.method)
        return m.figures if r is None else r.result.get("figures", m.figures)

    parts.append("<h2>Summary</h2>" + _summary(rep, figures, truth is not None, imported is not None))
    if imported is None:
        parts.append(_plan_section(store, info, store.progress(info.id)))
    else:
        parts.append(_imported_section(imported))
    parts.append(_calibration_section(rep, truth, store, info.id,
                                      _IMPORTED_CALIBRATION if imported is not None else _CAPTURED_CALIBRATION))
    parts.append("<h2>3. Reconstruction inputs</h2><p>Every measurement is resampled onto points of the "
                 "object's surface (\"lumitexels\"): per point, the directions to the lamp and the camera "
                 "and how much light came back. Held-out lights are kept aside for scoring.</p>"
                 + html_table([rep.inputs]))
    if imported is not None:
        parts.append(_normals_section(imported))
    n = 5 if imported is not None else 4
    parts.append(f"<h2>{n}. Methods</h2>")
    for i, m in enumerate(rep.methods, 1):
        pics = None
        r = stored.get(m.method)
        if r is not None and "report.npz" in r.artifacts:
            with np.load(io.BytesIO(store.read_object(r.artifacts["report.npz"]))) as z:
                pics = {k: z[k] for k in z.files}
        parts.append(_method_section(i, m, r, pics))
    parts.append(f"<h2>{n + 1}. Timings</h2><p>Seconds per stage of this run (a method stored before "
                 "and not re-run takes none).</p>"
                 + html_table([{"stage": k, "seconds": v} for k, v in rep.timings.items()]))
    path = Path(path)
    if imported is None:   # gonio export writes captured sessions' models only
        parts.append(_exports_section(session, export_links(path)))   # kept when the report is written again
    parts.append("</body></html>")
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_atomically(path, "\n".join(parts))   # whole or not at all (a full disk)
