"""Rebuild a store's index from its own files: the session journals (:mod:`.journal`) and the
frame files in ``objects/`` and ``quarantine/``.

What a database restored from an older backup (or recreated empty) lacks is put back: sessions
it does not know (their plan, steps and rig snapshots), and frames whose row is missing or older.
A frame comes back only when its file is present and hashes to its name; a quarantined file is
moved back into ``objects/``. Steps whose frames are all there are marked done; a recreated
session is ``done`` when every step is, else ``paused`` (``gonio capture resume`` continues it).
Calibration and reconstruction results are derived data and are not journaled: ``gonio process``
computes them again.

Sessions recorded before journals existed have none: the rebuild first writes one for each such
session the database still lists (and every writer does for its session), so that from then on
they can be rebuilt too. What it cannot do is put back the frames of such a session once its rows
are lost: a frame file names neither its session nor its step. Those files are kept (in
``objects/`` or ``quarantine/``) and counted in the report as files no row and no journal lists.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .errors import SessionBusy
from .objects import TMP_PREFIX, sha256_file
from .rows import dumps, try_lock

if TYPE_CHECKING:
    from .database import Store


@dataclass
class RebuildReport:
    """What :func:`rebuild_index` put back: sessions recreated (names), frame rows added or
    replaced, files taken back from quarantine, and notes (a journal without its session line,
    a frame whose file is missing ...)."""

    sessions_added: list[str] = field(default_factory=list)
    frames_added: int = 0
    unquarantined: int = 0
    notes: list[str] = field(default_factory=list)
    #: sessions recorded before journals, given one from their rows
    journals_written: list[str] = field(default_factory=list)
    #: files (and their bytes) that no row and no journal lists: kept, but no session to put them in
    unlisted_files: int = 0
    unlisted_bytes: int = 0


def rebuild_index(store: "Store") -> RebuildReport:
    """Put back what the database lacks from the journals and frame files (see the module).

    Raises
    ------
    SessionBusy
        A session of the store is being written (its rows are in flight).
    """
    fd = store._lock_file("writers.lock")
    try:
        if not try_lock(fd):
            raise SessionBusy(f"a session in {store.root} is being written; rebuild the index once it ends")
        report = RebuildReport(journals_written=store.write_missing_journals())
        for path, records in store._journals.read():
            head = records[0].get("session") if records else None
            if not isinstance(head, dict):
                report.notes.append(f"{path.name}: no session line; skipped")
                continue
            frames = {}
            for r in records:   # the last line of a (step, bracket, repeat) wins: a re-done step
                f = r.get("frame")
                if isinstance(f, dict):
                    frames[(f["step"], f["bracket_index"], f["repeat"])] = f
            if not frames:
                continue   # created, never captured: nothing to lose
            with store._write() as db:
                row = db.execute("SELECT id, created FROM sessions WHERE name = ?", (head["name"],)).fetchone()
                if row is not None and abs(row[1] - head["created"]) < 1e-6:
                    sid, new = row[0], False
                else:
                    name = head["name"] if row is None else _free_name(db, head["name"])
                    if row is not None:
                        report.notes.append(f"a newer session is named {head['name']!r}: the journal's "
                                            f"session is restored as {name!r}")
                    sid = db.execute(
                        "INSERT INTO sessions (name, operator, object, notes, state, plan_json, plan_hash, "
                        "plan_path, created, updated) VALUES (?,?,?,?,?,?,?,?,?,?)",
                        (name, head["operator"], head["object"], head["notes"], "paused", dumps(head["plan"]),
                         head["plan_hash"], head["plan_path"], head["created"], time.time())).lastrowid
                    db.executemany("INSERT INTO steps (session_id, idx, step_json, frames) VALUES (?,?,?,?)",
                                   [(sid, i, dumps(s), s["frames"]) for i, s in enumerate(head["steps"])])
                    report.sessions_added.append(name)
                    new = True
                taken = {r[0] for r in db.execute("SELECT taken FROM rig_snapshots WHERE session_id = ?", (sid,))}
                for r in records:
                    snap = r.get("rig_snapshot")
                    if isinstance(snap, dict) and snap["taken"] not in taken:
                        db.execute("INSERT INTO rig_snapshots (session_id, taken, config_json, describe_json) "
                                   "VALUES (?,?,?,?)", (sid, snap["taken"], dumps(snap["config"]),
                                                        dumps(snap["describe"])))
                have = {(r[0], r[1], r[2]): r[3] for r in db.execute(
                    "SELECT step, bracket_index, repeat, sha256 FROM frames WHERE session_id = ?", (sid,))}
                for key, f in sorted(frames.items()):
                    if have.get(key) == f["sha256"]:
                        continue
                    where = _take_back(store, f["sha256"], report)
                    if where is None:
                        report.notes.append(f"{head['name']} step {key[0]} frame {key[1]} of the bracket, "
                                            f"repeat {key[2]}: its file is missing or damaged; not restored")
                        continue
                    db.execute(
                        "INSERT INTO frames (session_id, step, bracket_index, repeat, sha256, size, filename, "
                        "format, exposure_requested_s, exposure_s, iso, fnumber, positions_json, captured_at, "
                        "stored_at, metadata_json) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?) "
                        "ON CONFLICT (session_id, step, bracket_index, repeat) DO UPDATE SET "
                        "sha256 = excluded.sha256, size = excluded.size, filename = excluded.filename, "
                        "format = excluded.format, exposure_requested_s = excluded.exposure_requested_s, "
                        "exposure_s = excluded.exposure_s, iso = excluded.iso, fnumber = excluded.fnumber, "
                        "positions_json = excluded.positions_json, captured_at = excluded.captured_at, "
                        "stored_at = excluded.stored_at, metadata_json = excluded.metadata_json",
                        (sid, *key, f["sha256"], f["size"], f["filename"], f["format"],
                         f["exposure_requested_s"], f["exposure_s"], f["iso"], f["fnumber"],
                         json.dumps(f["positions"]), f["captured_at"], f["stored_at"], json.dumps(f["metadata"])))
                    report.frames_added += 1
                db.execute("UPDATE steps SET done = 1, done_at = coalesce(done_at, ?) WHERE session_id = ? AND "
                           "done = 0 AND frames = (SELECT count(*) FROM frames f WHERE f.session_id = steps.session_id "
                           "AND f.step = steps.idx)", (time.time(), sid))
                if new and not db.execute("SELECT 1 FROM steps WHERE session_id = ? AND done = 0", (sid,)).fetchone():
                    db.execute("UPDATE sessions SET state = 'done' WHERE id = ?", (sid,))
        referenced = store._referenced()
        unlisted = [p for p in store.orphans() + store.quarantined()
                    if not p.name.startswith(TMP_PREFIX) and p.name not in referenced]
        report.unlisted_files, report.unlisted_bytes = len(unlisted), sum(p.stat().st_size for p in unlisted)
        return report
    finally:
        os.close(fd)


def _free_name(db, name: str) -> str:
    for k in range(1, 1000):
        candidate = f"{name[:90]}.restored{k if k > 1 else ''}"
        if db.execute("SELECT 1 FROM sessions WHERE name = ?", (candidate,)).fetchone() is None:
            return candidate
    raise ValueError(f"no free name for the restored session {name!r}")


def _take_back(store: "Store", sha: str, report: RebuildReport) -> str | None:
    """Where frame ``sha`` now is (``objects``), moving it back from quarantine if there; None
    when no intact file has it."""
    path = store.object_path(sha)
    if path.is_file() and sha256_file(path) == sha:
        return "objects"
    held = store.quarantine / sha
    if held.is_file() and sha256_file(held) == sha:
        path.parent.mkdir(parents=True, exist_ok=True)
        os.replace(held, path)
        report.unquarantined += 1
        return "objects"
    return None
