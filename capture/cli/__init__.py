"""The ``gonio`` command line. Each command group lives in its own module of this package; the Typer
application is built in :mod:`capture.cli.commands` and reached as ``capture.cli.app``.

This module stays light: :func:`main` installs gonio's Ctrl-C handling (:mod:`capture.cli.interrupts`)
before the commands load, so that no Ctrl-C, not even one while gonio starts, ends it by SIGINT. The
command modules load typer, rich and the store; each command imports its heavy layers (the pipeline,
the simulated lab, the runner) when it runs, so ``--help`` stays quick
(``tests/capture/test_cli_import_cost.py``).
"""
from __future__ import annotations

import sys

from .interrupts import EXIT_INTERRUPTED, install


def main() -> None:  # console script entry point
    install()
    try:
        from .commands import app
    except KeyboardInterrupt:
        print("interrupted while gonio was starting; nothing was done", file=sys.stderr)
        raise SystemExit(EXIT_INTERRUPTED) from None
    app()


def __getattr__(name: str):
    """``capture.cli.app``: the Typer application, built on first use."""
    if name == "app":
        from .commands import app
        return app
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
