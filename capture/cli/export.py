"""``gonio export SESSION --method M --format F[,F...] --out DIR``: a method's recovered
appearance written in formats other software reads (:mod:`capture.export.session`).

Exit status: 0 written; 2 a request it cannot carry out (unknown session, method not run,
no mesh, ``DIR`` exists, a format the method cannot give): the message says which, and nothing
is written; 3 interrupted (Ctrl-C, SIGTERM): nothing is written, the same command starts again.
"""
from __future__ import annotations

import errno
from pathlib import Path

import typer
from rich.markup import escape

from .interrupts import command_line, interruptible_command
from .session import STORE_OPTION, fail, open_store


def _format_help() -> str:
    from ..export.formats import FORMATS
    return "Comma-separated formats: " + "; ".join(f"'{k}': {v}" for k, v in FORMATS.items()) + "."


@interruptible_command(lambda session, method, formats, out, store, mesh, **_: (
    f"nothing was written to {out}; export again with: " + command_line(
        "gonio", "export", session, method=method, format=formats, out=out, store=store, mesh=mesh)))
def export(session: str = typer.Argument(..., help="Session name (see 'gonio session list')."),
           method: str = typer.Option(..., "--method", help="Whose reconstruction: lensch, sharing or "
                                      "passive (as stored by 'gonio process')."),
           formats: str = typer.Option("maps,gltf,mitsuba", "--format", help=_format_help()),
           out: Path = typer.Option(..., "--out", help="New folder to write (must not exist)."),
           store: str = STORE_OPTION,
           mesh: Path = typer.Option(None, "--mesh", help="The object's mesh gonio process used (object "
                                     "frame, mm); sessions recorded on --rig sim bring their own."),
           report: Path = typer.Option(None, "--report", help="The session report (gonio process's HTML) "
                                       "that links this export's page DIR/report.html; default: "
                                       "<session>-report.html or gonio demo's report.html beside the "
                                       "store, when it is this session's.")) -> None:
    """Export a method's recovered appearance: texture maps (EXR, 16-bit PNG), glTF 2.0, a Mitsuba 3
    scene per captured light, MERL tables; model.json names every file, its units, the exact BRDF
    formula and the export's approximation error; DIR/report.html links every file and shows Mitsuba's
    render of a held-out capture beside gonio's prediction (with Mitsuba installed).

    Exit status: 0 written, 2 a request it cannot carry out (the message says which; nothing is
    written), 3 interrupted.
    """
    from ..export.session import ExportError, export_session
    from ..pipeline.mesh_checks import load_mesh
    from ..pipeline.process import ProcessError
    kw = {}
    if mesh is not None:
        try:
            kw["mesh"] = load_mesh(mesh)
        except ProcessError as exc:
            raise fail(str(exc)) from None
    with open_store(store, readonly=True) as st:
        try:
            rep = export_session(st, session, method=method, out=out, report=report,
                                 formats=[f.strip() for f in formats.split(",") if f.strip()], **kw)
        except ExportError as exc:
            raise fail(str(exc)) from None
        except OSError as exc:   # the partial folder is removed: nothing is left
            if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            raise fail(f"the disk holding {out.resolve().parent} is full ({exc.strerror}); nothing was written: "
                       "free space and run the same command again") from None
    for fmt, files in rep.files.items():
        typer.echo(f"{fmt}: {len(files)} file(s)")
    a = rep.model.get("approximation", {})
    if "export_vs_method_held_out_rel_rms" in a:
        typer.echo(f"export vs {method} at the held-out samples: relative RMS "
                   f"{a['export_vs_method_held_out_rel_rms']:.3f} (glTF {a['gltf_vs_method_held_out_rel_rms']:.3f}); "
                   f"vs the captures {a['export_held_out_rel_rms']:.3f} ({method}: {a['method_held_out_rel_rms']:.3f})")
    typer.echo(f"written: {escape(str(rep.out.resolve()))} (model.json describes every file)")
    typer.echo(f"page: {escape(str(rep.page.resolve()))}")
    typer.echo(f"linked from: {escape(str(rep.linked_from.resolve()))}" if rep.linked_from is not None else
               "linked from no session report (none beside the store; --report FILE names one)")
