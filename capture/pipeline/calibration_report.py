"""PNG report of a calibration run (matplotlib, Agg backend: no display needed).

:func:`write_report` draws one figure with a panel per result that the run produced —
reprojection error per view, corner coverage map, turntable per-view residuals, the environment
map, light positions on a polar plot beside the positioner's commanded positions, a
polarization separation example and an HDR example — plus the stage summary with timings.
Panels whose stage did not run say why.
"""
from __future__ import annotations

import io
import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # before pyplot: headless servers and CI have no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..outputs import write_atomically  # noqa: E402
from .calibrate import CalibrationReport  # noqa: E402

__all__ = ["write_report", "tonemap"]


def tonemap(img: np.ndarray, *, percentile: float = 99.0) -> np.ndarray:
    """Linear RGB (H, W, 3) -> displayable sRGB in [0, 1]: scaled so ``percentile`` of the
    luminance is white, then the sRGB transfer curve."""
    img = np.nan_to_num(np.asarray(img, np.float64), nan=0.0, posinf=0.0)
    top = np.percentile(img.mean(axis=-1) if img.ndim == 3 else img, percentile)
    x = np.clip(img / top if top > 0 else img, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _missing(ax, report: CalibrationReport, stage: str, title: str) -> None:
    s = report.stage(stage)
    ax.set_title(title)
    ax.axis("off")
    text = f"{stage}: {s.status}\n{s.reason}" if s.reason else f"{stage}: {s.status}"
    ax.text(0.5, 0.5, "\n".join(_wrap(text, 48)), ha="center", va="center", fontsize=8, wrap=True,
            transform=ax.transAxes)


def _wrap(text: str, width: int) -> list[str]:
    return [w for line in text.splitlines() for w in textwrap.wrap(line, width) or [""]]


def _reprojection(ax, report: CalibrationReport) -> None:
    p = report.plots.get("intrinsics")
    if p is None:
        return _missing(ax, report, "intrinsics", "Reprojection error per view")
    err = np.asarray(p["per_view_rms_px"])
    ax.bar(np.arange(len(err)), err, color="tab:blue")
    ax.axhline(float(np.sqrt(np.mean(err ** 2))), color="k", ls="--", lw=1, label="overall RMS")
    labels = [f.split("(")[-1].rstrip(")") for f in p["frames"]]  # "frame 12 (step 3)" -> "step 3"
    ax.set_xticks(np.arange(len(err)), labels, rotation=60, fontsize=6)
    ax.set_ylabel("RMS reprojection error (px)")
    ax.set_title("Intrinsics: reprojection error per view")
    ax.legend(fontsize=7)


def _coverage(ax, report: CalibrationReport) -> None:
    p = report.plots.get("intrinsics")
    if p is None:
        return _missing(ax, report, "intrinsics", "Corner coverage")
    w, h = p["image_size"]
    cov = np.asarray(p["coverage"])
    ax.imshow(cov, extent=(0, w, h, 0), cmap="viridis", interpolation="nearest", alpha=0.8)
    for pts in p["points"]:
        ax.plot(pts[:, 0], pts[:, 1], ".", ms=1.5, color="w")
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_title(f"Corner coverage ({100 * np.mean(cov > 0):.0f}% of cells)")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")


def _turntable(ax, report: CalibrationReport) -> None:
    p = report.plots.get("turntable")
    if p is None:
        return _missing(ax, report, "turntable", "Turntable axis residuals")
    readings = (np.asarray(p["readings_deg"], float) + 180) % 360 - 180  # a sweep through 0 stays whole
    order = np.argsort(readings)
    ax.plot(readings[order], np.asarray(p["per_view_rms_px"])[order], "o-", color="tab:green")
    ax.set_xlabel("turntable reading (deg, wrapped to ±180)")
    ax.set_ylabel("RMS residual (px)")
    fig = report.stage("turntable").figures
    ax.set_title(f"Turntable: axis {np.round(fig.get('axis', []), 3).tolist()}", fontsize=9)


def _lights(fig, slot, report: CalibrationReport) -> None:
    p = report.plots.get("lights")
    if p is None:
        ax = fig.add_subplot(slot)
        stage = "positioner" if report.stage("lights").status == "ok" else "lights"
        return _missing(ax, report, stage, "Light positions")
    ax = fig.add_subplot(slot, projection="polar")
    # radius = 90 - elevation: the zenith in the middle, the horizon at the rim
    ax.scatter(np.radians(p["commanded_az"]), 90 - np.asarray(p["commanded_el"]), marker="x", s=40,
               color="tab:red", label="commanded")
    ax.scatter(np.radians(p["measured_az"]), 90 - np.asarray(p["measured_el"]), marker="o", s=25,
               facecolors="none", edgecolors="tab:blue", label="measured (spheres)")
    ax.set_ylim(0, 90)
    ax.set_yticks([0, 30, 60, 90], ["90°", "60°", "30°", "0°"], fontsize=6)
    ax.set_title("Lights: azimuth / elevation", fontsize=9)
    ax.legend(fontsize=6, loc="lower left", bbox_to_anchor=(-0.15, -0.2))


def _image(ax, img, title: str) -> None:
    ax.imshow(tonemap(img))
    ax.set_title(title, fontsize=9)
    ax.axis("off")


def write_report(report: CalibrationReport, path: str | Path, *, dpi: int = 110) -> Path:
    """Draw the calibration report of ``report`` into a PNG at ``path`` (parents created).

    Returns
    -------
    Path
        The PNG written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = plt.figure(figsize=(18, 13))
    grid = fig.add_gridspec(3, 5, height_ratios=[1, 1, 0.9])
    _reprojection(fig.add_subplot(grid[0, 0:2]), report)
    _coverage(fig.add_subplot(grid[0, 2]), report)
    _turntable(fig.add_subplot(grid[0, 3]), report)
    probe = report.plots.get("probe")
    if probe is None:
        _missing(fig.add_subplot(grid[0, 4]), report, "mirror_probe", "Environment map")
    else:
        frame = report.stage("mirror_probe").figures.get("frame")
        _image(fig.add_subplot(grid[0, 4]), probe["env"], f"Environment map ({frame} frame, lat-long)")
    _lights(fig, grid[1, 0], report)
    pol = report.plots.get("polarization")
    if pol is None:
        for k, what in ((1, "diffuse"), (2, "specular")):
            _missing(fig.add_subplot(grid[1, k]), report, "polarization", f"Polarization: {what}")
    else:
        _image(fig.add_subplot(grid[1, 1]), pol["diffuse"],
               f"Diffuse ({pol['method']}, steps {pol['steps']})")
        _image(fig.add_subplot(grid[1, 2]), np.clip(pol["specular"], 0, None), "Specular")
    hdr = report.plots.get("hdr_example")
    if hdr is None:
        _missing(fig.add_subplot(grid[1, 3:5]), report, "hdr", "HDR example")
    else:
        exps = ", ".join(f"{t:g}" for t in hdr["exposures_s"])
        _image(fig.add_subplot(grid[1, 3:5]), hdr["image"], f"HDR step {hdr['step']} ({exps} s)")
    ax = fig.add_subplot(grid[2, :])
    ax.axis("off")
    rows = [[s.stage, s.status, f"{s.seconds:.1f}",
             "\n".join(_wrap(_figures_text(s.figures) if s.status == "ok" else s.reason, 170))]
            for s in report.stages]
    table = ax.table(cellText=rows, colLabels=["stage", "status", "s", "key figures / reason"],
                     loc="center", cellLoc="left", colWidths=[0.09, 0.06, 0.04, 0.81])
    table.auto_set_font_size(False)
    table.set_fontsize(7)
    table.scale(1, 1.5)
    fig.suptitle(f"gonio calibration report: session {report.session}", fontsize=13)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=dpi)
    plt.close(fig)
    return write_atomically(path, png.getvalue())   # whole or not at all (a full disk)


def _figures_text(figures: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in figures.items())
