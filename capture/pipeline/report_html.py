"""The session report: one self-contained HTML file (every picture an embedded PNG).

:func:`write_html_report` draws what :func:`capture.pipeline.run.process_session` did from the store
(the plan, the frames' capture times, the stored reconstructions and their ``report.npz``
pictures) and the run's :class:`capture.pipeline.run.ProcessReport` (calibration stages, timings,
truth comparisons). Each section says in plain words what its pictures show, for a reader who has
never heard of the papers. Without ground truth the truth columns are left out.
"""
from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from ..outputs import write_atomically
from ..store import ResultRecord, Store
from .pictures import SLICE_THETA_I_DEG
from .plan_table import plan_rows

__all__ = ["write_html_report", "METHOD_NOTES"]

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
    "passive": "Romeiro et al. 2008 (passive reflectometry): one image of the object lit only by the room, "
               "whose light is known from a mirror-ball photograph, gives one reflectance function for the "
               "whole object (it assumes a single material).",
}


def _png(fig) -> str:
    import matplotlib.pyplot as plt
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _img(uri: str, alt: str) -> str:
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


def _table(rows: list[dict[str, Any]], columns: list[str] | None = None) -> str:
    if not rows:
        return "<p><em>none</em></p>"
    cols = columns or list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(r.get(c, ''))}</td>" for c in cols) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _tonemap(img: np.ndarray, scale: float) -> np.ndarray:
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
    return _img(_png(fig), "capture timeline")


def _held_out_figure(pics: dict[str, np.ndarray]) -> str:
    import matplotlib.pyplot as plt
    cap, pred = pics["heldout_captured"], pics["heldout_predicted"]
    on = ~np.isnan(pred).any(axis=2)          # pixels of surface points the model predicts
    scale = float(np.percentile(cap[on], 99.5)) if on.any() else 1.0
    err = np.linalg.norm(np.nan_to_num(pred - cap), axis=2) / max(float(np.mean(np.linalg.norm(cap[on], axis=1)))
                                                                  if on.any() else 1.0, 1e-12)
    err[~on] = np.nan
    ys, xs = np.nonzero(on)
    crop = (slice(max(ys.min() - 4, 0), ys.max() + 5), slice(max(xs.min() - 4, 0), xs.max() + 5)) if len(ys) else \
        (slice(None), slice(None))
    fig, axes = plt.subplots(1, 3, figsize=(10, 3.6))
    axes[0].imshow(_tonemap(cap, scale)[crop])
    axes[0].set_title("captured under a held-out light")
    axes[1].imshow(_tonemap(pred, scale)[crop])
    axes[1].set_title("predicted by the model")
    im = axes[2].imshow(err[crop], cmap="magma", vmin=0, vmax=1)
    axes[2].set_title("|error| / mean radiance")
    fig.colorbar(im, ax=axes[2], fraction=0.046)
    for a in axes:
        a.axis("off")
    return _img(_png(fig), "held-out capture, prediction and error")


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
    return _img(_png(fig), "BRDF slices")


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
    return _img(_png(fig), "normal maps")


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
    return _img(_png(fig), "light calibration errors")


def _environment_figure(store: Store, session_id: int) -> str:
    import matplotlib.pyplot as plt
    probe = [r for r in store.results(session_id, "calibration") if r.kind == "environment_map"]
    if not probe or "environment.npz" not in probe[-1].artifacts:
        return ""
    with np.load(io.BytesIO(store.read_object(probe[-1].artifacts["environment.npz"]))) as z:
        env, weight = z["env"], z["weight"]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    img = _tonemap(env, float(np.percentile(env, 99)) or 1.0) * np.clip(weight, 0, 1)[..., None]
    ax.imshow(img, extent=(0, 360, -90, 90))  # column 0: azimuth 0 (+x, towards the camera)
    ax.set_xlabel("azimuth (°, lab frame)")
    ax.set_ylabel("elevation (°)")
    ax.set_title("the room's light from the mirror-ball photograph (black: not seen)")
    return _img(_png(fig), "environment map")


def _calibration_section(rep, truth, store: Store, session_id: int) -> str:
    parts = ["<h2>2. Calibration</h2>",
             "<p>Before anything can be measured, the rig measures itself from its own calibration "
             "captures: the camera's lens (from a printed board), where the turntable's axis is, where "
             "the lamp was for every capture (from its reflections in mirror balls), the lamp's "
             "brightness (from an 18 % gray card) and the room's light (from a mirror ball).</p>",
             _table([{"stage": c["stage"], "status": c["status"], "figures": c.get("figures", {}),
                      "note": c.get("reason", "")} for c in rep.calibration])]
    ct = rep.calibration_truth
    if ct:
        parts.append("<h3>Against the simulation's ground truth</h3>"
                     "<p>Targets of the calibration: light position within 0.5 % of its distance and "
                     "0.25° in direction, focal length within 0.2 %.</p>")
        parts.append(_table([{"focal length error (%)": ct["focal_error_pct"],
                              "principal point error (px)": ct["principal_point_error_px"],
                              "camera centre error (mm)": ct["camera_centre_error_mm"],
                              "lamp intensity error (%)": ct.get("intensity_error_pct", "relative units"),
                              "lights from": ct["light_source"]}]))
        parts.append(_table(ct.get("lights", []), ["azimuth_deg", "elevation_deg", "error_mm",
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
    rows = [{"measure": k, "value": v} for k, v in figures.items() if k != "table_ii_rms"]
    parts.append("<p><b>held_out_rel_rms</b>: relative RMS difference between the model's prediction and "
                 "the captures under lights it never saw (<b>_trimmed</b>: without the 1 % worst samples, which "
                 "carry most of a glossy object's pooled error); <b>truth_rel_rms</b>: the same against the "
                 "true reflectance (simulation only).</p>" + _table(rows))
    if figures.get("table_ii_rms"):
        parts.append("<p>Lensch Table II: the RMS fitting error after each stage (single average BRDF, "
                     "per cluster, projection, PFA, normal fitting) — it should fall from left to right.</p>"
                     + _table([figures["table_ii_rms"]]))
    warnings = outcome.warnings if stored is None else stored.result.get("warnings", outcome.warnings)
    if warnings:
        parts.append("<ul class='warn'>" + "".join(f"<li>{html.escape(w)}</li>" for w in warnings) + "</ul>")
    if pics:
        if "heldout_captured" in pics:
            parts.append("<p>Left: a capture under a light the model never saw; middle: the model's "
                         "prediction for the same light; right: their difference (dark is good).</p>"
                         + _held_out_figure(pics))
        s = _slices_figure(pics, SLICE_THETA_I_DEG)
        if s:
            parts.append("<p>How much light the surface reflects towards each viewing angle when lit from "
                         f"{SLICE_THETA_I_DEG:g}° (the peak near +{SLICE_THETA_I_DEG:g}° is the highlight).</p>" + s)
        if "normals_fitted" in pics:
            parts.append("<p>The surface orientation the method recovered from the shading (as colour), and how "
                         "far it leans from the smooth mesh it was given: bumps and engravings the mesh lacks "
                         "show up here (beside the truth, in a simulation).</p>" + _normals_figure(pics))
    return "\n".join(parts)


def _summary(rep, figures, with_truth: bool) -> str:
    """The methods table (held-out score, its ratio to the floor, the error against the truth)
    and the floor, or why there is none."""
    def ratio(m) -> Any:
        return "–" if m.floor_ratio is None else f"{m.floor_ratio:.2f}×"

    rows = [{"method": m.method, "status": m.status,
             "held-out rel. RMS": figures(m).get("held_out_rel_rms", float("nan")),
             **({"× floor": ratio(m)} if rep.floor is not None else {}),
             **({"vs truth rel. RMS": figures(m).get("truth_rel_rms", float("nan"))} if with_truth else {}),
             "note": f"outside its assumption: {m.outside_assumption}" if m.outside_assumption else ""}
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
    else:
        note = ("<p><b>No floor</b>: the true reflectance of this object is unknown (the floor, the true model "
                "scored on the held-out captures, exists only for sessions captured in the simulated lab), so "
                "the held-out errors stand alone.</p>")
    return _table(rows) + note


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
            + _table(rows)
            + "<details><summary>the plan as stored (JSON)</summary>"
            f"<pre>{html.escape(json.dumps(info.plan, indent=1))}</pre></details>"
            + _timeline(store, info.id))


_CSS = """body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:2px 8px;font-size:90%}
th{background:#eee}img{max-width:100%}.skipped{color:#866}.failed{color:#b00}.warn{color:#a60}
.outside{background:#fff3d6;border-left:4px solid #e0a000;padding:4px 8px}"""


def write_html_report(store: Store, session: str, rep, *, truth=None, path: str | Path) -> Path:
    """Write the session's report (HTML with embedded PNGs) to ``path`` and return it."""
    import matplotlib
    matplotlib.use("Agg")
    info = store.session(session)
    stored = {r.kind: r for r in store.results(info.id, "reconstruction")}
    prog = store.progress(info.id)
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>gonio: {html.escape(session)}</title>"
             f"<style>{_CSS}</style></head><body>",
             f"<h1>gonio report: {html.escape(session)}</h1>",
             "<p>gonio measured how this object reflects light: a turntable turned it, a lamp on an arm lit "
             "it from many directions, a camera photographed it through a rotating polarizer at several "
             "exposures, and the rig calibrated itself from its own captures. Reconstruction methods then "
             "recovered the object's reflectance; each is judged by predicting captures under lights it "
             "was never shown." + (" This session comes from the simulated lab, so every figure is also "
                                   "compared with the ground truth." if truth is not None else "") + "</p>"]
    def figures(m) -> dict:
        r = stored.get(m.method)
        return m.figures if r is None else r.result.get("figures", m.figures)

    parts.append("<h2>Summary</h2>" + _summary(rep, figures, truth is not None))
    parts.append(_plan_section(store, info, prog))
    parts.append(_calibration_section(rep, truth, store, info.id))
    parts.append("<h2>3. Reconstruction inputs</h2><p>Every measurement is resampled onto points of the "
                 "object's surface (\"lumitexels\"): per point, the directions to the lamp and the camera "
                 "and how much light came back. Held-out lights are kept aside for scoring.</p>"
                 + _table([rep.inputs]))
    parts.append("<h2>4. Methods</h2>")
    for i, m in enumerate(rep.methods, 1):
        pics = None
        r = stored.get(m.method)
        if r is not None and "report.npz" in r.artifacts:
            with np.load(io.BytesIO(store.read_object(r.artifacts["report.npz"]))) as z:
                pics = {k: z[k] for k in z.files}
        parts.append(_method_section(i, m, r, pics))
    parts.append("<h2>5. Timings</h2>" + _table([{"stage": k, "seconds": v} for k, v in rep.timings.items()]))
    parts.append("</body></html>")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_atomically(path, "\n".join(parts))   # whole or not at all (a full disk)
