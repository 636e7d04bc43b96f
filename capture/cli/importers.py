"""``gonio import``: image sets recorded elsewhere become sessions (see :mod:`capture.importers`).

- ``gonio import diligent DIR [--store S] [--session NAME] [--hold-out-every 4]``: a DiLiGenT-
  layout folder (images, light directions and intensities, mask, optional ground-truth normals).

Exit status: 0 imported; 2 the set is malformed (the message names the file and the fault) or
the session exists; nothing is written then; 3 interrupted (Ctrl-C, SIGTERM): the same command
continues the import.
"""
from __future__ import annotations

from pathlib import Path

import typer

from ..store import StoreError
from .interrupts import command_line, interruptible_command
from .session import STORE_OPTION, fail, unwrap

app = typer.Typer(name="import", no_args_is_help=True, help=unwrap("""
    Import image sets recorded elsewhere as sessions of the store, with their provenance (source
    folder, every file's SHA-256). 'gonio process SESSION' then reconstructs from them."""))


@interruptible_command(lambda folder, store, session, hold_out_every, **_: (
    "the files stored so far are kept; continue with: " + command_line(
        "gonio", "import", "diligent", folder, store=store, session=session,
        hold_out_every=None if hold_out_every == 4 else hold_out_every)))
def diligent(folder: Path = typer.Argument(..., help="A DiLiGenT-layout folder: filenames.txt, "
                                           "the images, light_directions.txt, "
                                           "light_intensities.txt, mask.png, [Normal_gt.mat]."),
             store: str = STORE_OPTION,
             session: str = typer.Option(None, "--session", help="Session name (default: "
                                         "diligent-<folder name>)."),
             hold_out_every: int = typer.Option(4, "--hold-out-every", help="Mark every n-th light "
                                                "held out (scored, never fitted); 0: none.")) -> None:
    """Import a multi-light photometric-stereo set in the DiLiGenT layout.

    Writes one session into --store: every file's bytes as a frame, the set's lights and
    orthographic camera as its calibration, the source folder and every file's SHA-256 in its
    plan. The set is checked whole before anything is written.

    Exit status: 0 imported, 2 a malformed set (the message names the file) or an existing
    session, 3 interrupted (the same command continues).
    """
    from ..importers import DiligentFormatError, import_diligent
    try:
        name = import_diligent(folder, store, session, hold_out_every=hold_out_every)
    except (DiligentFormatError, StoreError) as exc:
        raise fail(str(exc)) from None
    typer.echo(f"imported {folder} as session {name!r} in {store}; next: gonio process {name} "
               f"--store {store}")


app.command("diligent", help=unwrap(diligent.__doc__))(diligent)   # rich keeps a later paragraph's line breaks
