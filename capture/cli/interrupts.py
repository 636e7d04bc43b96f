"""Ctrl-C (SIGINT) and SIGTERM for gonio's long commands: exit 3 with how to resume, never by SIGINT.

``gonio`` installs :func:`install` before any command runs. The first interrupt raises
KeyboardInterrupt in the main thread, which stops the work where it is (a store transaction
rolls back, an object file is left as a ``.tmp-`` the next writer deletes), and from then on the
process ignores SIGINT and SIGTERM: what runs after the first (rolling back, closing the rig and
its simulators, shutting a Dask cluster down, removing a partial export, Python's own exit) is
never cut short. Python's handler would raise again there, and Python puts back the default
action while it finalises (a second Ctrl-C then ended gonio by SIGINT, status -2); an ignored
signal it leaves ignored. :func:`interruptible` wraps a command's body and turns the
KeyboardInterrupt into one line, ``interrupted; ...`` with the command that resumes, and exit
status 3. While the capture runner works, :func:`counted` only counts interrupts (the first
pauses after the step, the second stops motion).
"""
from __future__ import annotations

import contextlib
import functools
import shlex
import signal
import threading
from pathlib import Path
from typing import Callable, Iterator

EXIT_INTERRUPTED = 3

_installed = False


def _ignore_interrupts() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _on_interrupt(signum: int, frame) -> None:
    _ignore_interrupts()
    raise KeyboardInterrupt


def install() -> None:
    """Route SIGINT and SIGTERM of this process through :func:`_on_interrupt` (the ``gonio``
    entry point calls it once, before any command runs)."""
    global _installed
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _on_interrupt)
        signal.signal(signal.SIGTERM, _on_interrupt)
        _installed = True


@contextlib.contextmanager
def counted() -> Iterator[list[int]]:
    """While a capture session runs and until the rig is closed, an interrupt only appends to the
    yielded list (a handler that never raises): a second one landing anywhere, even while the
    first is being handled or the rig closes, stops motion instead of killing gonio. SIGTERM (a
    system shutdown, ``kill``) counts as two: stop now, pause (resumable). Once one was counted,
    the process ignores later ones (under :func:`install`), as after its first."""
    interrupts: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield interrupts
        return
    restore = signal.signal(signal.SIGINT, lambda *_: interrupts.append(1))
    restore_term = signal.signal(signal.SIGTERM, lambda *_: interrupts.extend((1, 1)))
    try:
        yield interrupts
    finally:
        if interrupts and _installed:
            _ignore_interrupts()
        else:
            signal.signal(signal.SIGINT, restore)
            signal.signal(signal.SIGTERM, restore_term)


@contextlib.contextmanager
def interruptible(resume: Callable[[], str]) -> Iterator[None]:
    """Run a long command's body; a KeyboardInterrupt ends it with ``interrupted; <resume()>`` on
    stderr and exit status 3. ``resume()`` is called only then (it may look at the store to say
    which command continues)."""
    try:
        yield
    except KeyboardInterrupt:
        import typer   # here, not at the top: install() runs before anything heavy loads
        typer.secho(f"interrupted; {resume()}", err=True, fg=typer.colors.YELLOW)
        raise typer.Exit(EXIT_INTERRUPTED) from None


def interruptible_command(resume: Callable[..., str]) -> Callable:
    """:func:`interruptible` around a whole command; ``resume`` receives the command's arguments."""
    def wrap(command: Callable) -> Callable:
        @functools.wraps(command)
        def run(**kwargs):
            with interruptible(lambda: resume(**kwargs)):
                return command(**kwargs)
        return run
    return wrap


def command_line(*words: str | Path, **options: str | Path | bool | None) -> str:
    """A shell command line: ``words`` then each option given (``None``/``False`` left out,
    ``True`` a bare flag; ``out_dir`` becomes ``--out-dir``), every value quoted for the shell."""
    parts = [str(w) for w in words]
    for key, value in options.items():
        if value is None or value is False:
            continue
        parts.append("--" + key.replace("_", "-"))
        if value is not True:
            parts.append(str(value))
    return shlex.join(parts)
