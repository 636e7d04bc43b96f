"""Files gonio writes outside its store (reports, renders): where they may go and how.

A file name built from a stored session name stays in its folder (a store written before names
were checked, or a hostile archive, may hold ``../../escape``); an ``--out`` given by the user is
checked before any work (a folder, a device such as ``/dev/full``, a missing or read-only folder
are refused by name); and a file is written whole or not at all (a temporary file beside it,
fsynced, then renamed), so a full disk never leaves a 0-byte report where the last good one was.
"""
from __future__ import annotations

import contextlib
import os
import re
import stat
import tempfile
from pathlib import Path

__all__ = ["OutputError", "session_file", "check_out_file", "check_out_folder", "write_atomically",
           "safe_stem"]

_STEM = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,99}")


class OutputError(ValueError):
    """An output path gonio must not or cannot write; the message names the path and why."""


def safe_stem(text: str) -> bool:
    """Whether ``text`` is a file stem that names a plain file in its folder (1-100 of
    ``A-Z a-z 0-9 _ . -``, first a letter, digit or ``_``: never ``..``, a separator or an option)."""
    return isinstance(text, str) and _STEM.fullmatch(text) is not None


def session_file(folder: str | Path, session: str, session_id: int, suffix: str) -> Path:
    """``folder/<session><suffix>``, or ``folder/session-<id><suffix>`` when the stored name is
    not a safe file stem (``..``, an absolute path, a control character ...)."""
    folder = Path(folder)
    stem = session if safe_stem(session) else f"session-{int(session_id)}"
    path = folder / f"{stem}{suffix}"
    if not path.resolve().parent == folder.resolve():   # a link in the way cannot lead it out
        raise OutputError(f"refusing {path}: it leads outside {folder}")
    return path


def check_out_file(path: str | Path, option: str = "--out") -> Path:
    """An ``--out FILE`` gonio may write: not a folder, a device or a link to one, in a folder
    that exists and is writable (a temporary file and a rename need both). Returns the path."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise OutputError(f"{option} {path}: cannot look at it ({exc.strerror or exc})") from None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{option} {path} is a folder; give a file name (e.g. {path / 'report.html'})")
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{option} {path} is not a regular file (a device or a pipe); give a file "
                          "name in a folder")
    parent = path.resolve().parent
    if not parent.is_dir():
        raise OutputError(f"{option} {path}: the folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{option} {path}: the folder {parent} is not writable")
    return path


def check_out_folder(path: str | Path, option: str = "--out") -> Path:
    """An ``--out FOLDER``: a folder or nothing yet (it is created), never a file or a device; an
    empty string (it would be the current folder) is refused. Returns the path."""
    if not str(path).strip():
        raise OutputError(f"{option} is empty; give a folder ('.' for the current one)")
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{option} {path} is a file, not a folder")
    return path


def write_atomically(path: str | Path, data: bytes | str) -> Path:
    """Write ``data`` to ``path`` whole or not at all: a temporary file in the same folder,
    fsynced, renamed over ``path``. On any error (``ENOSPC`` ...) the temporary file is removed,
    ``path`` keeps what it held, and the ``OSError`` propagates (``filename``: ``path``)."""
    path = Path(path)
    raw = data.encode("utf-8") if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename is None:   # say which file met the full disk
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    return path

