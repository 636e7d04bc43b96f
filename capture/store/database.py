"""The session store: one SQLite database (WAL) plus content-addressed frame files beside it.

Layout of a store directory::

    gonio.sqlite            sessions, rig snapshots, planned steps, frames, events, results
    objects/ab/cdef...      the camera's own bytes, named by their SHA-256 (read-only files)
    locks/                  advisory locks (writers, one per running session)

Durability: a frame file is written to a temporary name in its final directory, fsynced,
renamed into place and the directory fsynced; only then is its row committed (``synchronous =
FULL``). A frame row therefore never exists without its file, and identical bytes are stored
once. A crash can leave at most an unreferenced file (an *orphan*) or a ``.tmp-`` file; the next
writer that finds no other writer running removes them (:meth:`Store.writer`).

Readers (the TUI, a second ``gonio`` process) read while a session writes: WAL gives each read
transaction a consistent snapshot, write transactions are short, and ``busy_timeout`` waits
out a concurrent commit instead of failing.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import shutil
import sqlite3
import tempfile
import threading
import time
import urllib.parse
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from ..events import Event
from . import crash, version
from .archive import archive_read_only, archive_suffix, extract_safely, is_archive, pack
from .errors import (ForeignDatabase, ObjectDamaged, SchemaError, SessionBusy, SessionExists,
                     SessionNotFound, StoreDamaged, StoreError, StoreFull)
from .migrations import MIGRATIONS, SCHEMA_VERSION, foreign_tables
from .journal import Journals
from .names import check_session_name, inside
from .objects import TMP_PREFIX, ObjectFiles, copy_hashed, sha256_file
from .rebuild import RebuildReport, rebuild_index
from .records import FrameRecord, Progress, ResultRecord, SessionInfo, StoredStep, VerifyReport
from .rows import dumps, try_lock

DB_NAME = "gonio.sqlite"
STATES = ("planned", "running", "paused", "done", "aborted")
#: free space below which an SQLite I/O error is taken for a full disk, bytes
FULL_BELOW_BYTES = 1 << 20
#: disk space a writer holds back to record a pause when the disk fills, bytes
RESERVE_BYTES = 1 << 20
RESERVE_NAME = "space-reserve"
#: where unreferenced object files go instead of being deleted (see Store.collect_garbage)
QUARANTINE_DIR = "quarantine"
#: quarantined files younger than this are never purged, s (a week: time to notice a restored backup)
QUARANTINE_MIN_AGE_S = 7 * 24 * 3600.0

#: SQL condition true for a ``sha256`` column value that is not an object name (see objects.py)
_BAD_SHA_SQL = "(typeof({0}) != 'text' OR length({0}) != 64 OR {0} GLOB '*[^0-9a-f]*')"


def _is_full(exc: sqlite3.Error) -> bool:
    return getattr(exc, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL




class Store:
    """A store directory: the SQLite database and the object files beside it.

    Parameters
    ----------
    root : path
        Store directory; created (with an empty, current-schema database) when ``create``.
    create : bool
        Create the directory and database if absent. Otherwise a missing store is an error.
    durable : bool, optional
        fsync frame files, their directories and every commit (``synchronous = FULL``), so a
        stored frame survives power loss. False keeps the write order (a killed process still
        leaves a consistent store) but not power-loss durability: for scratch stores and tests.
        Default: True unless the environment sets ``GONIO_STORE_DURABLE=0``.
    readonly : bool, optional
        Open the database without writing to it (``mode=ro``: no migration, no pragmas; write
        methods raise :class:`StoreError`), for commands that only read: they then work on a
        full disk and leave a foreign file alone.
    rebuilding : bool, optional
        Accept a missing or empty database beside frame files (it is created, for
        :meth:`rebuild_index` to fill from the journals and frame files).

    Raises
    ------
    StoreDamaged
        ``gonio.sqlite`` is damaged, or empty while ``objects/`` holds frame files.
    ForeignDatabase
        ``gonio.sqlite`` is another program's SQLite database.
    StoreFull
        The disk is full and the database cannot be opened for writing.

    Notes
    -----
    One connection is shared by the threads of a process under a lock (the TUI reads on its
    thread while the runner writes on a worker). Other processes open their own ``Store``.
    """

    def __init__(self, root: str | os.PathLike, *, create: bool = True,
                 durable: bool | None = None, readonly: bool = False, rebuilding: bool = False) -> None:
        self.root = Path(root)
        self._rebuilding = rebuilding
        self.durable = os.environ.get("GONIO_STORE_DURABLE", "1") != "0" if durable is None else durable
        self.readonly = readonly
        self._readonly_why = f"{self.root} was opened read-only; this needs a writable store"
        self.db_path = self.root / DB_NAME
        if not self.db_path.is_file():
            if (self.root / "objects").is_dir() and not rebuilding:   # captured data, index lost
                raise StoreDamaged(f"{self.root} holds frame files (objects/) but no {DB_NAME}: the "
                                   "database was lost. Nothing was changed; rebuild it from the frame "
                                   f"files: gonio session rebuild-index --store {self.root}")
            if not create or readonly:
                raise StoreError(f"{self.root} is not a gonio store (no {DB_NAME}); "
                                 "give --store the folder a session was recorded in")
            self.root.mkdir(parents=True, exist_ok=True)
        self._files = ObjectFiles(self.root, self.db_path, self.durable)
        self._journals = Journals(self.root, self.durable)
        self._journal_paths: dict[int, Path | None] = {}
        self.objects = self._files.root
        self._lock = threading.RLock()
        self._cleanup: Callable[[], None] | None = None
        try:
            self._db = self._connect()
        except sqlite3.Error as exc:  # e.g. gonio.sqlite is a folder, or unreadable
            raise StoreError(f"cannot open {self.db_path}: {exc}") from None
        try:
            self._prepare()
        except BaseException:
            self._db.close()
            raise

    def _connect(self, immutable: bool = False) -> sqlite3.Connection:
        if self.readonly:
            # mode=ro never writes the file; immutable=1 also skips the WAL index (-shm), which a
            # full disk cannot create
            uri = f"file:{urllib.parse.quote(str(self.db_path))}?mode=ro" + ("&immutable=1" * immutable)
            db = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False,
                                 timeout=30.0)
        else:
            db = sqlite3.connect(self.db_path, isolation_level=None, check_same_thread=False,
                                 timeout=30.0)
        db.row_factory = sqlite3.Row
        return db

    def _prepare(self) -> None:
        """Recognise the database (gonio's, empty, damaged or foreign), then set it up: WAL,
        durability and forward migrations, or for a read-only store only the schema check."""
        try:
            try:
                tables = {r[0] for r in self._db.execute(
                    "SELECT name FROM sqlite_master WHERE type = 'table'")}
            except sqlite3.OperationalError:
                wal = self.db_path.with_name(DB_NAME + "-wal")
                if not self.readonly or (wal.exists() and wal.stat().st_size):
                    raise
                # a read-only open on a full disk: no WAL to merge, so read the file as it is
                self._db.close()
                self._db = self._connect(immutable=True)
                tables = {r[0] for r in self._db.execute(
                    "SELECT name FROM sqlite_master WHERE type = 'table'")}
            if not tables:
                files = sum(1 for _ in self._files.files())
                if files and not self._rebuilding:
                    raise StoreDamaged(
                        f"{self.db_path} is empty but {self.objects} holds {files} file(s) of "
                        "captured data: the database was lost or truncated. Nothing was changed; "
                        "rebuild it from the frame files (gonio session rebuild-index --store "
                        f"{self.root}), or restore gonio.sqlite from a backup or an export; keep "
                        "objects/ as it is")
                if self.readonly:
                    raise StoreError(f"{self.db_path} is empty: no session was ever recorded there")
            elif missing := foreign_tables(self._db):
                raise ForeignDatabase(
                    f"{self.db_path} is an SQLite database but not a gonio store (its tables: "
                    f"{', '.join(sorted(tables)[:8])}; it lacks {', '.join(missing[:5])}); gonio leaves "
                    "it untouched. Give --store a folder gonio recorded in, or a new folder")
            self._db.execute("PRAGMA busy_timeout = 30000")
            if self.readonly:
                self._check_version(self._db)
                self._check_hashes()
                return
            if self._db.execute("PRAGMA journal_mode").fetchone()[0] != "wal":
                self._db.execute("PRAGMA journal_mode = WAL")
            # FULL: a committed frame survives power loss; NORMAL (in WAL): a killed process
            self._db.execute(f"PRAGMA synchronous = {'FULL' if self.durable else 'NORMAL'}")
            self._db.execute("PRAGMA foreign_keys = ON")
            self._migrate()
            self._check_hashes()
        except sqlite3.Error as exc:
            error = self._translate(exc)
            raise (StoreError(f"cannot open {self.db_path}: {exc}") if error is exc else error) from None

    def _check_hashes(self) -> None:
        """Refuse a store with rows whose object hash is not 64 lowercase hex digits: file paths
        are built from it (a crafted ``'../x'`` would lead outside ``objects/``)."""
        bad = self._db.execute(
            f"SELECT 'frame', s.name, f.step, f.sha256 FROM frames f LEFT JOIN sessions s ON "
            f"s.id = f.session_id WHERE {_BAD_SHA_SQL.format('f.sha256')} UNION ALL "
            f"SELECT 'result artifact', s.name, o.name, o.sha256 FROM result_objects o LEFT JOIN "
            f"results r ON r.id = o.result_id LEFT JOIN sessions s ON s.id = r.session_id WHERE "
            f"{_BAD_SHA_SQL.format('o.sha256')}").fetchall()
        if bad:
            what, session, where, sha = bad[0]
            place = f"frame of step {where}" if what == "frame" else f"{what} {str(where)[:40]!r}"
            raise StoreDamaged(
                f"{self.db_path} has {len(bad)} row(s) whose object hash is not 64 lowercase hex "
                f"digits (first: {place} of session {str(session)[:40]!r}, hash "
                f"{str(sha)[:80]!r}); the database is damaged or was crafted, and gonio builds no "
                "file path from it. Nothing was changed: restore gonio.sqlite from a backup")

    def _translate(self, exc: sqlite3.Error) -> Exception:
        """An SQLite error as the store error that says what to do, or ``exc`` itself."""
        code = (getattr(exc, "sqlite_errorcode", None) or 0) & 0xFF
        if code in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB):
            files = sum(1 for _ in self._files.files())
            return StoreDamaged(
                f"{self.db_path} is damaged ({exc}). The {files} frame file(s) in {self.objects} "
                "are separate and untouched. Restore gonio.sqlite from a backup or an export "
                "('gonio session export'); 'sqlite3 gonio.sqlite .recover' can often salvage "
                "the rows. Keep objects/ as it is meanwhile")
        if code in (sqlite3.SQLITE_FULL, sqlite3.SQLITE_IOERR) and self._disk_full():
            return StoreFull(f"no space left on the disk holding {self.root}: free space, then "
                             "run the command again (read-only commands such as 'gonio session "
                             "list' still work)")
        if code == sqlite3.SQLITE_READONLY and self.readonly:
            return StoreError(f"{self.db_path} was opened read-only")
        return exc

    def _disk_full(self) -> bool:
        try:
            return shutil.disk_usage(self.root).free < FULL_BELOW_BYTES
        except OSError:
            return False

    # -- lifecycle ----------------------------------------------------------------------------
    @classmethod
    def open(cls, path: str | os.PathLike, *, create: bool = False,
             readonly: bool = False) -> "Store":
        """Open a store folder, or an exported ``.tar`` / ``.zip`` archive, always read-only
        (extracted to a temporary folder that is removed on :meth:`close`, and on every error;
        a write raises :class:`StoreError` saying how to get a writable store).

        An archive member that is absolute, climbs out with ``..``, or is a link or device
        (an export holds only folders and plain files) is refused by name before anything is
        extracted. ``readonly`` opens the database without writing to it (see :class:`Store`).
        """
        path = Path(path)
        if not is_archive(path):
            return cls(path, create=create, readonly=readonly)
        tmp = Path(tempfile.mkdtemp(prefix="gonio-store-"))
        try:
            extract_safely(path, tmp)
            inner = [p.parent for p in tmp.rglob(DB_NAME)]
            if len(inner) != 1:
                raise StoreError(f"{path}: archive holds {len(inner)} gonio stores, expected 1")
            # read-only whatever was asked: a write would land in the temporary extraction and
            # vanish with it
            store = cls(inner[0], create=False, readonly=True)
            store._readonly_why = archive_read_only(path)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        store._cleanup = lambda: shutil.rmtree(tmp, ignore_errors=True)
        return store

    def close(self) -> None:
        with self._lock:
            self._db.close()
        if self._cleanup is not None:
            self._cleanup()
            self._cleanup = None

    def __enter__(self) -> "Store":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _migrate(self) -> None:
        with self._write() as db:
            db.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)")
            row = db.execute("SELECT version FROM schema_version").fetchone()
            current = self._check_version(db)
            for v in range(current, SCHEMA_VERSION):
                MIGRATIONS[v](db)
            if row is None:
                db.execute("INSERT INTO schema_version VALUES (?)", (SCHEMA_VERSION,))
            else:
                db.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION,))

    def _check_version(self, db: sqlite3.Connection) -> int:
        row = db.execute("SELECT version FROM schema_version").fetchone()
        current = 0 if row is None else row[0]
        if current > SCHEMA_VERSION:
            raise SchemaError(f"{self.db_path} has schema version {current}; this gonio "
                              f"knows up to {SCHEMA_VERSION}: upgrade gonio to open it")
        return current

    @property
    def schema_version(self) -> int:
        return self._query("SELECT version FROM schema_version")[0][0]

    # -- transactions -------------------------------------------------------------------------
    @contextlib.contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """One short write transaction (``BEGIN IMMEDIATE``: takes the write lock up front so a
        concurrent writer waits in busy_timeout rather than failing on lock upgrade)."""
        if self.readonly:
            raise StoreError(self._readonly_why)
        with self._lock:
            # BEGIN inside the try: a KeyboardInterrupt landing just after it must not leave the
            # shared connection inside a transaction (every later BEGIN would then fail)
            try:
                self._db.execute("BEGIN IMMEDIATE")
                yield self._db
                crash.point("before_commit")
                self._db.execute("COMMIT")
            except BaseException as exc:
                if self._db.in_transaction:
                    self._db.execute("ROLLBACK")
                if isinstance(exc, sqlite3.OperationalError) and _is_full(exc):
                    raise StoreFull(f"no space left on the disk holding {self.root} to commit; "
                                    "free space and resume (nothing was recorded)") from exc
                if isinstance(exc, sqlite3.Error) and self._translate(exc) is not exc:
                    raise self._translate(exc) from exc
                raise
            crash.point("after_commit")

    @contextlib.contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        """A read transaction: every query inside sees the same snapshot."""
        with self._lock:
            try:
                self._db.execute("BEGIN")
                yield self._db
                self._db.execute("COMMIT")
            except BaseException as exc:
                if self._db.in_transaction:  # a damaged page fails COMMIT too: keep the first error
                    with contextlib.suppress(sqlite3.Error):
                        self._db.execute("ROLLBACK")
                if isinstance(exc, sqlite3.Error) and self._translate(exc) is not exc:
                    raise self._translate(exc) from exc
                raise

    def _query(self, sql: str, args: Iterable[Any] = ()) -> list[sqlite3.Row]:
        with self._read() as db:
            return db.execute(sql, tuple(args)).fetchall()

    @staticmethod
    def _insert_events(db: sqlite3.Connection, session_id: int, events: Iterable[Event]) -> None:
        db.executemany(
            "INSERT INTO events (session_id, time, kind, step, device, message, data_json) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            [(session_id, e.time, e.kind.value, e.step, e.device, e.message, dumps(e.data))
             for e in events])

    # -- locks --------------------------------------------------------------------------------
    def _lock_file(self, name: str) -> int:
        (self.root / "locks").mkdir(exist_ok=True)
        return os.open(self.root / "locks" / name, os.O_RDWR | os.O_CREAT, 0o644)

    @contextlib.contextmanager
    def writer(self, session: str) -> Iterator[list[str] | None]:
        """Hold the right to write ``session`` for the duration of the block.

        Takes the session's exclusive lock (else :class:`SessionBusy`) and a shared store-writer
        lock. If no other writer is active, first removes what crashed writers left behind (see
        :meth:`collect_garbage`); yields the removed paths, or None when another writer was
        active and cleaning had to wait. Locks die with the process, so a killed runner never
        blocks a resume.
        """
        info = self.session(session)
        sfd = self._lock_file(f"session-{info.id}.lock")
        try:
            if not try_lock(sfd):
                raise SessionBusy(f"session {session!r} is being written by another process; "
                                  "wait for it to finish or pause it there")
            wfd = self._lock_file("writers.lock")
            try:
                removed = self.collect_garbage() if try_lock(wfd) else None
                fcntl.flock(wfd, fcntl.LOCK_SH)  # converts the exclusive lock if we held it
                self._keep_reserve()
                self.write_missing_journals(info)   # a session from before journals: journaled from now on
                yield removed
            finally:
                os.close(wfd)
        finally:
            os.close(sfd)

    def _keep_reserve(self) -> None:
        """Hold :data:`RESERVE_BYTES` of disk in ``locks/space-reserve`` while writing (best
        effort), so that on a full disk :meth:`release_reserve` frees room to record the pause."""
        path = self.root / "locks" / RESERVE_NAME
        with contextlib.suppress(OSError):
            if not path.is_file() or path.stat().st_size < RESERVE_BYTES:
                fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)
                try:
                    os.posix_fallocate(fd, 0, RESERVE_BYTES)
                except OSError:
                    os.ftruncate(fd, 0)  # no room for it: better none than a partial one
                    raise
                finally:
                    os.close(fd)

    def release_reserve(self) -> bool:
        """Delete the space reserve (the disk is full); True if there was one. The next
        :meth:`writer` takes it again once there is room."""
        try:
            (self.root / "locks" / RESERVE_NAME).unlink()
        except FileNotFoundError:
            return False
        return True

    # -- sessions -----------------------------------------------------------------------------
    def create_session(self, name: str, *, plan: dict[str, Any], plan_hash: str,
                       steps: list[dict[str, Any]], plan_path: str | None = None,
                       operator: str = "", object: str = "", notes: str = "") -> SessionInfo:
        """Record a new session in state ``planned`` with its expanded steps.

        ``steps`` are JSON-serialisable dicts in execution order; each must carry ``frames``,
        the number of frames the step stores (bracket length x repeats).
        """
        check_session_name(name)
        for i, s in enumerate(steps):
            if not isinstance(s.get("frames"), int) or s["frames"] < 0:
                raise StoreError(f"steps[{i}] needs an integer 'frames' >= 0")
        now = time.time()
        journal = self._journals.path(name, now)   # first: a session row never lacks its journal
        self._journals.start(journal, {"name": name, "operator": operator, "object": object, "notes": notes,
                                       "plan": plan, "plan_hash": plan_hash, "plan_path": plan_path,
                                       "created": now, "steps": steps})
        try:
            with self._write() as db:
                cur = db.execute(
                    "INSERT INTO sessions (name, operator, object, notes, state, plan_json, "
                    "plan_hash, plan_path, created, updated) VALUES (?,?,?,?,?,?,?,?,?,?)",
                    (name, operator, object, notes, "planned", dumps(plan), plan_hash,
                     plan_path, now, now))
                sid = cur.lastrowid
                db.executemany("INSERT INTO steps (session_id, idx, step_json, frames) "
                               "VALUES (?,?,?,?)",
                               [(sid, i, dumps(s), s["frames"]) for i, s in enumerate(steps)])
        except BaseException as exc:
            journal.unlink(missing_ok=True)
            if not isinstance(exc, sqlite3.IntegrityError):
                raise
            raise SessionExists(f"a session named {name!r} already exists in {self.root}; "
                                "choose another --session name or resume it") from None
        return self.session(name)

    @staticmethod
    def _session_from_row(row: sqlite3.Row) -> SessionInfo:
        return SessionInfo(id=row["id"], name=row["name"], state=row["state"],
                           operator=row["operator"], object=row["object"], notes=row["notes"],
                           plan=json.loads(row["plan_json"]), plan_hash=row["plan_hash"],
                           plan_path=row["plan_path"], created=row["created"],
                           updated=row["updated"])

    def session(self, name: str) -> SessionInfo:
        rows = self._query("SELECT * FROM sessions WHERE name = ?", (name,))
        if not rows:
            known = [r[0] for r in self._query("SELECT name FROM sessions ORDER BY created")]
            raise SessionNotFound(f"no session {name!r} in {self.root}"
                                  + (f"; sessions: {', '.join(known)}" if known else
                                     " (the store is empty)"))
        return self._session_from_row(rows[0])

    def sessions(self) -> list[SessionInfo]:
        return [self._session_from_row(r) for r in
                self._query("SELECT * FROM sessions ORDER BY created, id")]

    def set_state(self, session_id: int, state: str, events: Iterable[Event] = ()) -> None:
        if state not in STATES:
            raise StoreError(f"state {state!r} is not one of {', '.join(STATES)}")
        with self._write() as db:
            db.execute("UPDATE sessions SET state = ?, updated = ? WHERE id = ?",
                       (state, time.time(), session_id))
            self._insert_events(db, session_id, events)

    def add_rig_snapshot(self, session_id: int, config: dict[str, Any],
                         describe: dict[str, Any]) -> None:
        """Record the rig config and every device's ``describe()`` (one per run / resume)."""
        taken = time.time()
        self._journals.append(self._journal_of(session_id), "rig_snapshot",
                              {"taken": taken, "config": config, "describe": describe})
        with self._write() as db:
            db.execute("INSERT INTO rig_snapshots (session_id, taken, config_json, describe_json) "
                       "VALUES (?,?,?,?)", (session_id, taken, dumps(config), dumps(describe)))

    def write_missing_journals(self, only: SessionInfo | None = None) -> list[str]:
        """Write the journal (:mod:`.journal`) of each session recorded before journals existed
        (``only``: of that session), from its rows: plan and steps, rig snapshots, frame rows.
        From then on a lost or restored database can be rebuilt for it too. Returns the names of
        the sessions given one; a name that is no safe file name (a store from before names were
        checked) gets none."""
        written = []
        for info in [only] if only is not None else self.sessions():
            path = self._journals.path(info.name, info.created)
            if path is None or path.is_file():
                continue
            head = {"name": info.name, "operator": info.operator, "object": info.object, "notes": info.notes,
                    "plan": info.plan, "plan_hash": info.plan_hash, "plan_path": info.plan_path,
                    "created": info.created, "steps": [s.spec for s in self.steps(info.id)]}
            frames = [{"step": f.step, "bracket_index": f.bracket_index, "repeat": f.repeat, "sha256": f.sha256,
                       "size": f.size, "filename": f.filename, "format": f.format,
                       "exposure_requested_s": f.exposure_requested_s, "exposure_s": f.exposure_s,
                       "iso": f.iso, "fnumber": f.fnumber, "positions": f.positions,
                       "captured_at": f.captured_at, "stored_at": f.stored_at, "metadata": f.metadata}
                      for f in self.frames(info.id)]
            self._journals.write_whole(path, [{"session": head}]
                                       + [{"rig_snapshot": s} for s in self.rig_snapshots(info.id)]
                                       + [{"frame": f} for f in frames])
            written.append(info.name)
        return written

    def _journal_of(self, session_id: int) -> Path | None:
        """The session's journal file (see :mod:`.journal`), looked up once."""
        if session_id not in self._journal_paths:
            row = self._query("SELECT name, created FROM sessions WHERE id = ?", (session_id,))
            self._journal_paths[session_id] = self._journals.path(*row[0]) if row else None
        return self._journal_paths[session_id]

    def rig_snapshots(self, session_id: int) -> list[dict[str, Any]]:
        return [{"taken": r["taken"], "config": json.loads(r["config_json"]),
                 "describe": json.loads(r["describe_json"])}
                for r in self._query("SELECT * FROM rig_snapshots WHERE session_id = ? "
                                     "ORDER BY id", (session_id,))]

    def add_events(self, session_id: int, events: Iterable[Event]) -> None:
        with self._write() as db:
            self._insert_events(db, session_id, events)

    def events(self, session_id: int, *, kinds: Iterable[str] | None = None,
               after_id: int = 0, limit: int | None = None) -> list[dict[str, Any]]:
        """Stored events (oldest first), each a dict with ``id`` and :class:`Event`'s fields."""
        sql = "SELECT * FROM events WHERE session_id = ? AND id > ?"
        args: list[Any] = [session_id, after_id]
        if kinds is not None:
            kinds = list(kinds)
            sql += f" AND kind IN ({','.join('?' * len(kinds))})"
            args += kinds
        sql += " ORDER BY id"
        if limit is not None:
            sql += " LIMIT ?"
            args.append(limit)
        return [{"id": r["id"], "time": r["time"], "kind": r["kind"], "step": r["step"],
                 "device": r["device"], "message": r["message"], "data": json.loads(r["data_json"])}
                for r in self._query(sql, args)]

    # -- steps --------------------------------------------------------------------------------
    def steps(self, session_id: int, *, pending_only: bool = False) -> list[StoredStep]:
        """The session's steps in execution order."""
        sql = "SELECT idx, step_json, done FROM steps WHERE session_id = ?"
        if pending_only:
            sql += " AND done = 0"
        return [StoredStep(r[0], json.loads(r[1]), bool(r[2]))
                for r in self._query(sql + " ORDER BY idx", (session_id,))]

    def progress(self, session_id: int) -> Progress:
        with self._read() as db:
            st, sd, ft = db.execute("SELECT count(*), coalesce(sum(done), 0), coalesce(sum(frames), 0) "
                                    "FROM steps WHERE session_id = ?", (session_id,)).fetchone()
            fs, bs = db.execute("SELECT count(*), coalesce(sum(size), 0) FROM frames "
                                "WHERE session_id = ?", (session_id,)).fetchone()
        return Progress(steps_total=st, steps_done=sd, frames_total=ft, frames_stored=fs,
                        bytes_stored=bs)

    # -- objects ------------------------------------------------------------------------------
    def object_path(self, sha256: str) -> Path:
        """``objects/ab/cdef...`` for a SHA-256 hex; :class:`StoreDamaged` for anything else
        (a path is never built from a malformed hash read from the database)."""
        return self._files.path(sha256)

    def read_object(self, sha256: str) -> bytes:
        """The bytes of a stored object, checked against their SHA-256 (what ``gonio session
        verify`` checks, so both name the same damage); :class:`ObjectDamaged` naming every use
        of a missing, truncated or altered file."""
        path = self.object_path(sha256)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise ObjectDamaged(self._damage_text(sha256, "is missing")) from None
        if hashlib.sha256(data).hexdigest() != sha256:
            with self._read() as db:
                row = db.execute("SELECT size FROM frames WHERE sha256 = ? LIMIT 1", (sha256,)).fetchone()
            what = (f"is truncated ({len(data)} of {row[0]} bytes)" if row is not None and len(data) < row[0]
                    else "is corrupt (its bytes no longer match their SHA-256)")
            raise ObjectDamaged(self._damage_text(sha256, what))
        return data

    def _damage_text(self, sha256: str, what: str) -> str:
        with self._read() as db:
            ids = [r[0] for r in db.execute(
                "SELECT session_id FROM frames WHERE sha256 = ? UNION SELECT r.session_id FROM "
                "result_objects o JOIN results r ON r.id = o.result_id WHERE o.sha256 = ?", (sha256, sha256))]
            names = dict(db.execute("SELECT id, name FROM sessions").fetchall())
        uses = [f"session {names.get(i, i)!r} {u}" for i in ids for u in self._uses(i, [sha256]).get(sha256, [])]
        return (f"stored file {self.object_path(sha256).relative_to(self.root)} {what}; used by "
                f"{'; '.join(uses) or 'no row'} (gonio session verify lists every damaged file)")

    def put_object(self, data: bytes) -> str:
        """Store bytes durably (without a row referencing them); return their SHA-256 hex.

        An object no row references is an orphan: the next runner that starts with no other
        writer active collects it. Use :meth:`add_result` ``artifacts`` to store and reference
        bytes in one step."""
        sha = hashlib.sha256(data).hexdigest()
        self._files.ensure(data, sha)
        return sha

    @contextlib.contextmanager
    def _writing(self) -> Iterator[None]:
        """Hold the store-writer lock shared while an object is written and its row committed:
        :meth:`writer` collects garbage only when it can take that lock exclusively, so it never
        deletes an object whose row is about to be committed (by a runner, or a calibration in
        another process)."""
        fd = self._lock_file("writers.lock")
        try:
            fcntl.flock(fd, fcntl.LOCK_SH)
            yield
        finally:
            os.close(fd)

    def _drop_if_unreferenced(self, sha: str) -> None:
        """Delete an object file nothing references any more. Checked and deleted inside a write
        transaction, so no other writer can commit a reference to it meanwhile (they re-check the
        file's presence inside theirs); a crash here leaves an orphan for garbage collection."""
        with self._write() as db:
            if self._unreferenced(db, sha):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(self.object_path(sha))

    def _unreferenced(self, db: sqlite3.Connection, sha: str) -> bool:
        return db.execute("SELECT NOT EXISTS (SELECT 1 FROM frames WHERE sha256 = ?) AND "
                          "NOT EXISTS (SELECT 1 FROM result_objects WHERE sha256 = ?)",
                          (sha, sha)).fetchone()[0] == 1

    # -- frames -------------------------------------------------------------------------------
    def add_frame(self, session_id: int, step: int, bracket_index: int, repeat: int, *,
                  data: bytes, filename: str, format: str, exposure_requested_s: float | None,
                  exposure_s: float | None, iso: float | None = None, fnumber: float | None = None,
                  positions: dict[str, Any] | None = None, captured_at: float | None = None,
                  metadata: dict[str, Any] | None = None, events: Iterable[Event] = (),
                  completes_step: bool = False) -> tuple[int, str]:
        """Store one frame durably: file first (fsync, rename, fsync dir), then its row.

        The key ``(step, bracket_index, repeat)`` is unique per session: storing it again (a step
        re-done after a crash) replaces the row, and the replaced file is deleted if nothing else
        references it. ``completes_step`` marks the step done in the same transaction (pass it
        with the step's last frame: a step is done exactly when all its frames are durable).
        ``events`` are persisted in that transaction too. Returns ``(frame id, sha256)``.

        Raises
        ------
        StoreFull
            The disk is full (nothing was recorded; the session can be resumed).
        """
        sha = hashlib.sha256(data).hexdigest()
        now = time.time()
        with self._writing():
            self._files.ensure(data, sha)
            self._journals.append(self._journal_of(session_id), "frame", {
                "step": step, "bracket_index": bracket_index, "repeat": repeat, "sha256": sha,
                "size": len(data), "filename": filename, "format": format,
                "exposure_requested_s": exposure_requested_s, "exposure_s": exposure_s, "iso": iso,
                "fnumber": fnumber, "positions": positions or {},
                "captured_at": now if captured_at is None else captured_at, "stored_at": now,
                "metadata": metadata or {}})
            with self._write() as db:
                # a concurrent writer may have dropped an identical, then-unreferenced file
                # between our check and this transaction; writes are serialised, so re-check here
                if not self.object_path(sha).exists():
                    self._files.write(data, sha)
                old = db.execute("SELECT sha256 FROM frames WHERE session_id = ? AND step = ? AND "
                                 "bracket_index = ? AND repeat = ?",
                                 (session_id, step, bracket_index, repeat)).fetchone()
                cur = db.execute(
                    "INSERT INTO frames (session_id, step, bracket_index, repeat, sha256, size, "
                    "filename, format, exposure_requested_s, exposure_s, iso, fnumber, positions_json, "
                    "captured_at, stored_at, metadata_json) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?) "
                    "ON CONFLICT (session_id, step, bracket_index, repeat) DO UPDATE SET "
                    "sha256 = excluded.sha256, size = excluded.size, filename = excluded.filename, "
                    "format = excluded.format, exposure_requested_s = excluded.exposure_requested_s, "
                    "exposure_s = excluded.exposure_s, iso = excluded.iso, fnumber = excluded.fnumber, "
                    "positions_json = excluded.positions_json, captured_at = excluded.captured_at, "
                    "stored_at = excluded.stored_at, metadata_json = excluded.metadata_json "
                    "RETURNING id",
                    (session_id, step, bracket_index, repeat, sha, len(data), filename, format,
                     exposure_requested_s, exposure_s, iso, fnumber, dumps(positions or {}),
                     now if captured_at is None else captured_at, now, dumps(metadata or {})))
                frame_id = cur.fetchone()[0]
                self._insert_events(db, session_id, events)
                if completes_step:
                    db.execute("UPDATE steps SET done = 1, done_at = ? WHERE session_id = ? AND idx = ?",
                               (now, session_id, step))
                    db.execute("UPDATE sessions SET updated = ? WHERE id = ?", (now, session_id))
            if old is not None and old[0] != sha:
                # only after the commit: a crash before it must leave the old row's file in place
                self._drop_if_unreferenced(old[0])
        return frame_id, sha

    @staticmethod
    def _frame_from_row(r: sqlite3.Row) -> FrameRecord:
        return FrameRecord(id=r["id"], session_id=r["session_id"], step=r["step"],
                           bracket_index=r["bracket_index"], repeat=r["repeat"], sha256=r["sha256"],
                           size=r["size"], filename=r["filename"], format=r["format"],
                           exposure_requested_s=r["exposure_requested_s"],
                           exposure_s=r["exposure_s"], iso=r["iso"], fnumber=r["fnumber"],
                           positions=json.loads(r["positions_json"]), captured_at=r["captured_at"],
                           stored_at=r["stored_at"], metadata=json.loads(r["metadata_json"]))

    def frames(self, session_id: int, *, step: int | None = None) -> list[FrameRecord]:
        sql, args = "SELECT * FROM frames WHERE session_id = ?", [session_id]
        if step is not None:
            sql += " AND step = ?"
            args.append(step)
        return [self._frame_from_row(r) for r in
                self._query(sql + " ORDER BY step, repeat, bracket_index", args)]

    def frame(self, frame_id: int) -> FrameRecord:
        rows = self._query("SELECT * FROM frames WHERE id = ?", (frame_id,))
        if not rows:
            raise StoreError(f"no frame with id {frame_id}")
        return self._frame_from_row(rows[0])

    # -- results with provenance --------------------------------------------------------------
    def add_result(self, session_id: int, category: str, kind: str, *, result: dict[str, Any],
                   params: dict[str, Any] | None = None, input_frames: Iterable[int] = (),
                   artifacts: dict[str, bytes] | None = None) -> int:
        """Record a calibration or reconstruction result with its provenance.

        Parameters
        ----------
        category : {'calibration', 'reconstruction'}
        kind : str
            What it is (``intrinsics``, ``light_positions``, ``lensch2003`` ...).
        result : dict
            JSON-serialisable summary (numbers, small arrays as lists).
        params : dict
            The parameters the computation ran with.
        input_frames : iterable of int
            Frame ids it was computed from.
        artifacts : dict of str -> bytes
            Large outputs (``.npz``, ``.tiff``, ``.png``) stored as content-addressed objects.

        Returns
        -------
        int
            The result id. ``code_version`` (gonio version + git commit) is recorded with it.
        """
        if category not in ("calibration", "reconstruction"):
            raise StoreError(f"category {category!r} must be 'calibration' or 'reconstruction'")
        frame_ids = sorted(set(int(i) for i in input_frames))
        blobs = {name: (hashlib.sha256(blob).hexdigest(), blob)
                 for name, blob in (artifacts or {}).items()}
        code = version.code_version()  # may run git: never while holding the database's write lock
        with self._writing():
            for sha, blob in blobs.values():
                self._files.ensure(blob, sha)
            with self._write() as db:
                for sha, blob in blobs.values():  # as in add_frame: re-check inside
                    if not self.object_path(sha).exists():
                        self._files.write(blob, sha)
                stored = {name: (sha, len(blob)) for name, (sha, blob) in blobs.items()}
                if frame_ids:
                    known = db.execute(f"SELECT count(*) FROM frames WHERE session_id = ? AND id IN "
                                       f"({','.join('?' * len(frame_ids))})",
                                       (session_id, *frame_ids)).fetchone()[0]
                    if known != len(frame_ids):
                        raise StoreError(f"input_frames: {len(frame_ids) - known} of the ids are not "
                                         "frames of this session")
                cur = db.execute("INSERT INTO results (session_id, category, kind, created, params_json, "
                                 "result_json, input_frames_json, code_version) VALUES (?,?,?,?,?,?,?,?)",
                                 (session_id, category, kind, time.time(), dumps(params or {}),
                                  dumps(result), dumps(frame_ids), code))
                rid = cur.lastrowid
                db.executemany("INSERT INTO result_objects (result_id, name, sha256, size) VALUES (?,?,?,?)",
                               [(rid, n, sha, size) for n, (sha, size) in stored.items()])
        return rid

    def add_calibration(self, session_id: int, kind: str, **kw: Any) -> int:
        """:meth:`add_result` with ``category='calibration'``."""
        return self.add_result(session_id, "calibration", kind, **kw)

    def add_reconstruction(self, session_id: int, method: str, **kw: Any) -> int:
        """:meth:`add_result` with ``category='reconstruction'``."""
        return self.add_result(session_id, "reconstruction", method, **kw)

    def results(self, session_id: int, category: str | None = None) -> list[ResultRecord]:
        """Stored results of a session (of one ``category`` if given), oldest first."""
        sql, args = "SELECT * FROM results WHERE session_id = ?", [session_id]
        if category is not None:
            sql += " AND category = ?"
            args.append(category)
        with self._read() as db:
            rows = db.execute(sql + " ORDER BY id", args).fetchall()
            out = []
            for r in rows:
                arts = {a[0]: a[1] for a in db.execute(
                    "SELECT name, sha256 FROM result_objects WHERE result_id = ?", (r["id"],))}
                out.append(ResultRecord(id=r["id"], category=r["category"], kind=r["kind"],
                                        created=r["created"], params=json.loads(r["params_json"]),
                                        result=json.loads(r["result_json"]),
                                        input_frames=json.loads(r["input_frames_json"]),
                                        code_version=r["code_version"], artifacts=arts))
        return out

    # -- integrity ----------------------------------------------------------------------------
    def _referenced(self) -> set[str]:
        with self._read() as db:
            return ({r[0] for r in db.execute("SELECT sha256 FROM frames")}
                    | {r[0] for r in db.execute("SELECT sha256 FROM result_objects")})

    def orphans(self, *, min_age_s: float = 0.0) -> list[Path]:
        """Object files no row references, and temporary files of interrupted writes, last
        modified at least ``min_age_s`` seconds ago (a running writer's file in flight is young).
        """
        refs = self._referenced()
        cutoff = time.time() - min_age_s
        out = []
        for p in self._files.files():
            if p.name.startswith(TMP_PREFIX) or p.parent.name + p.name not in refs:
                with contextlib.suppress(FileNotFoundError):
                    if p.stat().st_mtime <= cutoff:
                        out.append(p)
        return out

    def _lock_held(self, name: str) -> bool:
        """Whether another holder has lock file ``name`` (probed without waiting)."""
        try:  # a holder creates the file: a missing one is not held (and a reader creates nothing)
            fd = os.open(self.root / "locks" / name, os.O_RDONLY)
        except FileNotFoundError:
            return False
        try:
            return not try_lock(fd)
        finally:
            os.close(fd)  # closing releases the probe's lock

    def session_active(self, session: str) -> bool:
        """True while a runner (this process or another) holds ``session``'s writer lock. A
        session left ``running`` without one was interrupted (a crash, a kill, a power cut)."""
        return self._lock_held(f"session-{self.session(session).id}.lock")

    def writer_active(self) -> bool:
        """True while some runner (this process or another) holds the store's writer lock."""
        return self._lock_held("writers.lock")

    def collect_garbage(self) -> list[str]:
        """Take orphans out of ``objects/`` (see :meth:`orphans`): ``.tmp-`` files of interrupted
        writes are deleted; unreferenced object files are *moved* to ``quarantine/``, never
        deleted (a database restored from an older backup does not list newer frames: their
        files may be the only copy; :meth:`rebuild_index` takes them back). Returns the paths
        taken out, relative to the store. Only safe with no writer running: use :meth:`writer`,
        which calls this when it holds the store exclusively."""
        removed = []
        for p in self.orphans():
            with contextlib.suppress(FileNotFoundError):
                if p.name.startswith(TMP_PREFIX):
                    p.unlink()
                else:
                    self.quarantine.mkdir(exist_ok=True)
                    os.replace(p, self.quarantine / (p.parent.name + p.name))
                removed.append(str(p.relative_to(self.root)))
        return removed

    @property
    def quarantine(self) -> Path:
        """``quarantine/``: object files no row referenced when a writer started, by SHA-256."""
        return self.root / QUARANTINE_DIR

    def quarantined(self) -> list[Path]:
        """Files in :attr:`quarantine`, sorted."""
        return sorted(self.quarantine.iterdir()) if self.quarantine.is_dir() else []

    def purge_quarantine(self, min_age_s: float = QUARANTINE_MIN_AGE_S) -> list[str]:
        """Delete quarantined files that have been there at least ``min_age_s`` seconds (their
        inode change time is when they were moved in); returns their paths. Refused while a
        session is written (:class:`SessionBusy`), like :meth:`remove_orphans`."""
        fd = self._lock_file("writers.lock")
        try:
            if not try_lock(fd):
                raise SessionBusy(f"a session in {self.root} is being written; try again once it ends")
            cutoff, removed = time.time() - min_age_s, []
            for p in self.quarantined():
                with contextlib.suppress(FileNotFoundError):
                    if p.stat().st_ctime <= cutoff:
                        p.unlink()
                        removed.append(str(p.relative_to(self.root)))
            return removed
        finally:
            os.close(fd)

    def rebuild_index(self) -> "RebuildReport":
        """Put back the sessions and frames the database lacks, from the session journals and
        the frame files (:mod:`capture.store.rebuild`)."""
        return rebuild_index(self)

    def remove_orphans(self) -> list[str]:
        """Take orphans out now (what :meth:`writer` does when a runner starts: ``.tmp-`` files
        deleted, object files moved to ``quarantine/``, see :meth:`collect_garbage`),
        returning their paths relative to the store.

        Raises
        ------
        SessionBusy
            Something is writing this store right now (its files in flight look like orphans).
        """
        fd = self._lock_file("writers.lock")
        try:
            if not try_lock(fd):
                raise SessionBusy(f"a session in {self.root} is being written; orphans are removed "
                                  "when the next runner starts, or try again once it ends")
            return self.collect_garbage()
        finally:
            os.close(fd)

    def verify(self, session: str, *, progress: Callable[[int, int], None] | None = None
               ) -> VerifyReport:
        """Re-hash every file of a session; list missing and corrupt files, store-wide orphans
        and done steps whose stored frame count differs from the plan. While a runner writes,
        orphans younger than a minute are not reported (they may be frames in flight).

        ``progress(i, n)`` is called after each file (for a progress bar).
        """
        info = self.session(session)
        with self._read() as db:
            shas = sorted({r[0] for r in db.execute(
                "SELECT sha256 FROM frames WHERE session_id = ? UNION SELECT o.sha256 FROM "
                "result_objects o JOIN results r ON r.id = o.result_id WHERE r.session_id = ?",
                (info.id, info.id))})
            incomplete = [r[0] for r in db.execute(
                "SELECT s.idx FROM steps s WHERE s.session_id = ? AND s.done = 1 AND s.frames != "
                "(SELECT count(*) FROM frames f WHERE f.session_id = s.session_id AND f.step = s.idx) "
                "ORDER BY s.idx", (info.id,))]
        journal = self._journals.path(info.name, info.created)
        report = VerifyReport(incomplete_steps=incomplete, journaled=journal is not None and journal.is_file())
        for i, sha in enumerate(shas):
            path = self.object_path(sha)
            if not path.is_file():
                report.missing.append(sha)
            elif sha256_file(path) != sha:
                report.corrupt.append(sha)
            report.checked += 1
            if progress is not None:
                progress(i + 1, len(shas))
        bad = report.missing + report.corrupt
        if bad:
            report.where = self._uses(info.id, bad)
        # with a writer running, an unreferenced file younger than a minute may be a frame between
        # its rename and its commit: not reported
        min_age = 60.0 if self.writer_active() else 0.0
        report.orphans = [str(p.relative_to(self.root)) for p in self.orphans(min_age_s=min_age)]
        return report

    def _uses(self, session_id: int, shas: list[str]) -> dict[str, list[str]]:
        """Where session ``session_id`` uses each of ``shas``: its frames and result artifacts."""
        marks = ",".join("?" * len(shas))
        with self._read() as db:
            frames = db.execute(f"SELECT sha256, step, bracket_index, repeat, filename FROM frames "
                                f"WHERE session_id = ? AND sha256 IN ({marks}) ORDER BY step, "
                                "repeat, bracket_index", (session_id, *shas)).fetchall()
            arts = db.execute(f"SELECT o.sha256, r.kind, r.id, o.name FROM result_objects o JOIN "
                              f"results r ON r.id = o.result_id WHERE r.session_id = ? AND "
                              f"o.sha256 IN ({marks}) ORDER BY r.id", (session_id, *shas)).fetchall()
        where: dict[str, list[str]] = {}
        for sha, step, b, r, name in frames:
            where.setdefault(sha, []).append(f"step {step} frame {b} of the bracket, repeat {r} "
                                             f"({name})")
        for sha, kind, rid, name in arts:
            where.setdefault(sha, []).append(f"result {kind} #{rid} artifact {name}")
        return where

    def free_bytes(self) -> int:
        """Free space on the disk holding the store, bytes."""
        return shutil.disk_usage(self.root).free

    # -- export -------------------------------------------------------------------------------
    def export(self, session: str, dest: str | os.PathLike) -> Path:
        """Write a self-contained store holding only ``session``: a folder, or a ``.tar`` /
        ``.tar.gz`` / ``.zip`` archive of one (chosen by ``dest``'s suffix).

        The database is copied with SQLite's online backup API (a consistent snapshot even while
        the session is being written); other sessions are then deleted from the copy. Every
        object file is re-hashed while copied; a corrupt one aborts the export.
        """
        dest = Path(dest)
        archive = archive_suffix(dest)
        if dest.exists() and (archive or any(dest.iterdir())):
            raise StoreError(f"export destination {dest} already exists; choose a new path")
        info = self.session(session)
        dest.parent.mkdir(parents=True, exist_ok=True)
        if dest.resolve().is_relative_to(self.root.resolve()):
            raise StoreError(f"export destination {dest} is inside the store {self.root}; "
                             "choose a path outside it")
        work = Path(tempfile.mkdtemp(prefix="gonio-export-", dir=dest.parent)) if archive else dest
        created = not dest.exists()
        try:  # names of older stores were not checked: one that is unsafe exports under its id
            folder = inside(work, check_session_name(info.name)) if archive else dest
        except StoreError:
            folder = work / f"session-{info.id}"
        try:
            folder.mkdir(parents=True, exist_ok=True)
            copy = sqlite3.connect(folder / DB_NAME, isolation_level=None)
            try:
                with self._lock:
                    self._db.backup(copy)
                copy.execute("PRAGMA foreign_keys = ON")
                copy.execute("DELETE FROM sessions WHERE id != ?", (info.id,))
                shas = {r[0] for r in copy.execute(
                    "SELECT sha256 FROM frames UNION SELECT sha256 FROM result_objects")}
                copy.execute("VACUUM")
            finally:
                copy.close()
            for sha in sorted(shas):
                src = self.object_path(sha)  # checks the hash before any path is built
                dst = folder / "objects" / src.relative_to(self.objects)
                dst.parent.mkdir(parents=True, exist_ok=True)
                if not src.is_file():
                    raise StoreError(f"cannot export {session!r}: object {sha} is missing; "
                                     f"run 'gonio session verify {session}'")
                if copy_hashed(src, dst) != sha:
                    raise StoreError(f"cannot export {session!r}: object {sha} is corrupt; "
                                     f"run 'gonio session verify {session}'")
                os.chmod(dst, 0o444)
            journal = self._journal_of(info.id)
            if journal is not None and journal.is_file():   # the export can rebuild its own index
                (folder / journal.parent.name).mkdir(exist_ok=True)
                shutil.copyfile(journal, folder / journal.parent.name / journal.name)
            if archive is None:
                return dest
            pack(folder, dest, archive)
            return dest
        except BaseException as exc:  # leave nothing half-exported behind
            if archive and dest.exists():
                dest.unlink()
            elif not archive and created:
                shutil.rmtree(dest, ignore_errors=True)
            elif not archive:  # it was an empty folder: empty it again
                for child in dest.iterdir():
                    shutil.rmtree(child) if child.is_dir() else child.unlink()
            if (isinstance(exc, sqlite3.Error) and _is_full(exc)
                    or isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)):
                raise StoreFull(f"no space left on the disk holding {dest} to export {session!r}; "
                                "nothing was left there: free space (or choose another disk) and "
                                "export again") from None
            raise
        finally:
            if archive:
                shutil.rmtree(work, ignore_errors=True)

