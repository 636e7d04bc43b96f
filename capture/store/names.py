"""Session names: the safe set (names become folder names in exports) and path confinement."""
from __future__ import annotations

import re
from pathlib import Path

from .errors import InvalidName, StoreError

#: letters, digits, ``_``, then also ``.`` and ``-``: never ``.``/``..``, a separator, a control
#: character or a leading ``-`` (read as an option); names become folder names in exports
_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
NAME_MAX = 100


def check_session_name(name: object, argument: str = "session name") -> str:
    """Return ``name`` if it is a safe session name, else raise :class:`InvalidName`.

    A safe name is 1 to :data:`NAME_MAX` characters of ``A-Z a-z 0-9 _ . -``, starting with a
    letter, digit or ``_`` (so never ``.``, ``..``, a path or an option).
    """
    if not isinstance(name, str) or not name:
        raise InvalidName(f"{argument} must be a non-empty string, not {name!r}")
    if len(name) > NAME_MAX or not _NAME_RE.fullmatch(name):
        raise InvalidName(f"{argument} {name[:NAME_MAX + 20]!r} is not allowed: use 1-{NAME_MAX} "
                          "ASCII letters, digits, '_', '.' or '-', starting with a letter, digit or '_'")
    return name


def safe_name_from(text: str, fallback: str = "session") -> str:
    """A safe session-name stem made from free text (a plan's name): unsafe runs become ``-``."""
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip(".-")[:NAME_MAX - 20]
    return stem if stem and _NAME_RE.fullmatch(stem) else fallback


def inside(base: Path, *parts: str) -> Path:
    """``base / parts`` after checking that it stays inside ``base`` (no ``..``, no absolute
    part, no symlink out); raises :class:`StoreError` otherwise."""
    path = base.joinpath(*parts)
    if not path.resolve().is_relative_to(base.resolve()):
        raise StoreError(f"refusing {path}: it leads outside {base}")
    return path

