"""Per-session journals: what the database records of a session's plan, rig snapshots and frames,
also written as JSON lines beside the frame files, so that a lost database, or one restored from
an older backup, can be rebuilt from the store's own files (``gonio session rebuild-index``).

One file per session, ``journal/<created>-<name>.jsonl``: a ``session`` line (name, plan, steps,
created ...) written before the session's row, then a ``rig_snapshot`` line per run and a
``frame`` line per frame, each appended (and fsynced in a durable store) after the frame's file
is in place and before its row commits. A kill can therefore leave a line whose row never
committed (its file is there: the frame was captured) but never a row without its line. A torn
last line is skipped when read.
"""
from __future__ import annotations

import errno
import json
import os
from pathlib import Path
from typing import Any, Iterator

from .errors import StoreFull
from .names import check_session_name

JOURNAL_DIR = "journal"


class Journals:
    """The ``journal/`` folder of the store at ``store_root``."""

    def __init__(self, store_root: Path, durable: bool) -> None:
        self.root = store_root / JOURNAL_DIR
        self.durable = durable

    def path(self, name: str, created: float) -> Path | None:
        """The journal of the session ``name`` created at ``created`` (epoch s); None for a name
        that is no safe file name (a store from before names were checked)."""
        try:
            check_session_name(name)
        except ValueError:
            return None
        return self.root / f"{created:.6f}-{name}.jsonl"

    def start(self, path: Path, session: dict[str, Any]) -> None:
        """Begin a new session's journal with its ``session`` record."""
        self.root.mkdir(exist_ok=True)
        self._append(path, {"session": session}, mode="w")

    def append(self, path: Path | None, kind: str, record: dict[str, Any]) -> None:
        """Add a ``kind`` record to an existing journal (none for sessions older than journals)."""
        if path is not None and path.is_file():
            self._append(path, {kind: record}, mode="a")

    def write_whole(self, path: Path, records: list[dict[str, Any]]) -> None:
        """Write a whole journal at once (a session recorded before journals, from its rows):
        a temporary file renamed into place, so a kill leaves the full journal or none."""
        self.root.mkdir(exist_ok=True)
        tmp = path.with_name(f".tmp-{path.name}")
        try:
            with open(tmp, "w", encoding="utf-8") as f:
                f.writelines(json.dumps(r, separators=(",", ":"), allow_nan=True) + "\n" for r in records)
                f.flush()
                if self.durable:
                    os.fsync(f.fileno())
            os.replace(tmp, path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise StoreFull(f"no space left on the disk holding {self.root.parent} while writing "
                                "a session journal; free space and try again") from None
            raise

    def _append(self, path: Path, record: dict[str, Any], mode: str) -> None:
        line = json.dumps(record, separators=(",", ":"), allow_nan=True) + "\n"
        try:
            with open(path, mode, encoding="utf-8") as f:
                f.write(line)
                f.flush()
                if self.durable:
                    os.fsync(f.fileno())
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise StoreFull(f"no space left on the disk holding {self.root.parent} while writing "
                                "the session journal; free space and resume") from None
            raise

    def read(self) -> Iterator[tuple[Path, list[dict[str, Any]]]]:
        """Every journal with its records, oldest session first (a torn last line dropped)."""
        if not self.root.is_dir():
            return
        for path in sorted(self.root.glob("*.jsonl")):
            records = []
            for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
                try:
                    records.append(json.loads(line))
                except json.JSONDecodeError:
                    continue   # a line a kill cut short
            yield path, records
