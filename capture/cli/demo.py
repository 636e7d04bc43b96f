"""``gonio demo``: the whole job on the simulated lab in one command (see :mod:`capture.pipeline.demo`).

Prints the folder it works in, a progress bar per stage, the methods table and the path of
``report.html``. Exit status: 0 done; 1 a method failed; 2 a bad --out (a file, or a folder that
already holds a demo); 3 interrupted (Ctrl-C, SIGTERM: the message names the commands that
finish the job from what was stored).
"""
from __future__ import annotations

import contextlib
import tempfile
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape

from ..outputs import OutputError, check_out_folder
from .interrupts import command_line, interruptible
from .process import EXIT_FAILED, EXIT_OK, print_outcome, process_command, progress_bar
from .session import fail


def demo(quick: bool = typer.Option(False, "--quick", help="A small plan at 320 x 240 (under 3 minutes "
                                    "on 2 cores) instead of the full demo."),
         out: str = typer.Option(None, "--out", help="Folder for the store and report.html (default: a "
                                  "new temporary folder)."),
         quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar.")) -> None:
    """Capture, calibrate and reconstruct on the simulated lab, then write report.html.

    Writes into --out (printed): store/, the session store (session demo, or demo-quick with
    --quick), and report.html with its report.json.

    Exit status: 0 done, 1 a method failed, 2 a bad --out, 3 interrupted (the message says how to
    finish from what was stored).
    """
    from ..pipeline.demo import run_demo
    if out is not None:
        try:
            out = check_out_folder(out)
        except OutputError as exc:
            raise fail(str(exc)) from None
        if (out / "store").exists():   # the demo's session name is fixed: a second run cannot add it
            raise fail(f"--out {out} already holds a demo (its store {out / 'store'}); give a new folder, "
                       f"or process that one again: gonio process NAME --store {out / 'store'} (NAME from "
                       f"gonio session list --store {out / 'store'})")
    out = Path(tempfile.mkdtemp(prefix="gonio-demo-")) if out is None else out
    console = Console()
    bar, update = progress_bar(quiet)
    with interruptible(lambda: _resume_demo(out)), bar:
        rep = run_demo(out, quick=quick, progress=update,
                       say=lambda text: console.print(escape(text), highlight=False, soft_wrap=True))
    print_outcome(rep, console)
    raise typer.Exit(EXIT_FAILED if any(m.status == "failed" for m in rep.methods) else EXIT_OK)


def _resume_demo(out: Path) -> str:
    """The commands that finish an interrupted demo from its store (``out/store``)."""
    from ..store import Store, StoreError
    store = out / "store"
    sessions = []
    with contextlib.suppress(StoreError), Store(store, create=False, readonly=True) as st:
        sessions = st.sessions()
    if not sessions:
        return f"nothing was captured; run the demo again with a new --out (or remove {out})"
    info = sessions[-1]
    process = process_command(info.name, str(store), out=out / "report.html")
    if info.state == "done":
        return f"the capture and whatever was processed are kept; resume with: {process}"
    return ("every frame stored is kept; resume with: "
            + command_line("gonio", "capture", "resume", info.name, rig="sim", store=store)
            + f", then {process}")
