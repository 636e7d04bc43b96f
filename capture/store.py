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
import functools
import hashlib
import json
import os
import re
import shutil
import signal
import sqlite3
import stat
import subprocess
import tarfile
import tempfile
import threading
import time
import urllib.parse
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from .events import Event

DB_NAME = "gonio.sqlite"
STATES = ("planned", "running", "paused", "done", "aborted")
_TMP_PREFIX = ".tmp-"
#: free space below which an SQLite I/O error is taken for a full disk, bytes
FULL_BELOW_BYTES = 1 << 20
#: disk space a writer holds back to record a pause when the disk fills, bytes
RESERVE_BYTES = 1 << 20
RESERVE_NAME = "space-reserve"


class StoreError(Exception):
    """Base of the store's errors; the message says what to do."""


class SessionNotFound(StoreError):
    """No session of that name in this store."""


class SessionExists(StoreError):
    """A session of that name already exists."""


class SessionBusy(StoreError):
    """Another process (or runner) is writing this session right now."""


class StoreFull(StoreError):
    """The disk holding the store ran out of space while writing a frame."""


class SchemaError(StoreError):
    """The database was written by a newer gonio (unknown schema version)."""


class StoreDamaged(StoreError):
    """The database file is damaged, truncated or empty while frame files exist."""


class ObjectDamaged(StoreDamaged):
    """A stored file (a frame or a result's artifact) is missing or its bytes no longer hash to
    its name; the message names where the session uses it (step, bracket, repeat, file name)."""


class ForeignDatabase(StoreError):
    """``gonio.sqlite`` is some other program's SQLite database."""


class InvalidName(StoreError, ValueError):
    """A session name outside the safe set (see :func:`check_session_name`)."""


#: letters, digits, ``_``, then also ``.`` and ``-``: never ``.``/``..``, a separator, a control
#: character or a leading ``-`` (read as an option); names become folder names in exports
_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
NAME_MAX = 100
#: an object's name: its SHA-256 as 64 lowercase hex digits (paths are built from it)
_SHA_RE = re.compile(r"[0-9a-f]{64}")
#: SQL condition true for a ``sha256`` column value that is not such a hash
_BAD_SHA_SQL = "(typeof({0}) != 'text' OR length({0}) != 64 OR {0} GLOB '*[^0-9a-f]*')"


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


# -- crash hook points (tests kill the process here: GONIO_CRASH_AFTER=N) -----------------------
_crash_lock = threading.Lock()
_crash_count = 0


def _crash_point(name: str) -> None:
    """Kill this process with SIGKILL at the N-th hook point if ``GONIO_CRASH_AFTER=N`` is set.

    The crash test walks N over every write/rename/commit point of a session to prove that a
    kill at any of them leaves a store that ``resume`` completes with exactly the planned frames.
    """
    after = os.environ.get("GONIO_CRASH_AFTER")
    if not after:
        return
    global _crash_count
    with _crash_lock:
        _crash_count += 1
        if _crash_count == int(after):
            os.write(2, f"GONIO_CRASH at {name}\n".encode())  # fd 2: unbuffered, never redirected
            os.kill(os.getpid(), signal.SIGKILL)


# -- schema and forward migrations ------------------------------------------------------------
def _run_script(db: sqlite3.Connection, script: str) -> None:
    # statement by statement: executescript() would COMMIT the migration transaction midway
    for statement in script.split(";"):
        if statement.strip():
            db.execute(statement)


def _m1_initial(db: sqlite3.Connection) -> None:
    _run_script(db, """
    CREATE TABLE sessions (
        id INTEGER PRIMARY KEY,
        name TEXT NOT NULL UNIQUE,
        operator TEXT NOT NULL DEFAULT '',
        object TEXT NOT NULL DEFAULT '',
        notes TEXT NOT NULL DEFAULT '',
        state TEXT NOT NULL CHECK (state IN ('planned','running','paused','done','aborted')),
        plan_json TEXT NOT NULL,
        plan_hash TEXT NOT NULL,
        plan_path TEXT,
        created REAL NOT NULL,
        updated REAL NOT NULL
    );
    CREATE TABLE rig_snapshots (
        id INTEGER PRIMARY KEY,
        session_id INTEGER NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
        taken REAL NOT NULL,
        config_json TEXT NOT NULL,
        describe_json TEXT NOT NULL
    );
    CREATE TABLE steps (
        session_id INTEGER NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
        idx INTEGER NOT NULL,
        step_json TEXT NOT NULL,
        frames INTEGER NOT NULL,
        done INTEGER NOT NULL DEFAULT 0,
        done_at REAL,
        PRIMARY KEY (session_id, idx)
    );
    CREATE TABLE frames (
        id INTEGER PRIMARY KEY,
        session_id INTEGER NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
        step INTEGER NOT NULL,
        bracket_index INTEGER NOT NULL,
        repeat INTEGER NOT NULL,
        sha256 TEXT NOT NULL,
        size INTEGER NOT NULL,
        filename TEXT NOT NULL,
        format TEXT NOT NULL,
        exposure_requested_s REAL,
        exposure_s REAL,
        iso REAL,
        fnumber REAL,
        positions_json TEXT NOT NULL,
        captured_at REAL NOT NULL,
        stored_at REAL NOT NULL,
        metadata_json TEXT NOT NULL,
        UNIQUE (session_id, step, bracket_index, repeat)
    );
    CREATE TABLE events (
        id INTEGER PRIMARY KEY,
        session_id INTEGER NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
        time REAL NOT NULL,
        kind TEXT NOT NULL,
        step INTEGER,
        device TEXT,
        message TEXT NOT NULL,
        data_json TEXT NOT NULL
    );
    CREATE TABLE results (
        id INTEGER PRIMARY KEY,
        session_id INTEGER NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
        category TEXT NOT NULL CHECK (category IN ('calibration','reconstruction')),
        kind TEXT NOT NULL,
        created REAL NOT NULL,
        params_json TEXT NOT NULL,
        result_json TEXT NOT NULL,
        input_frames_json TEXT NOT NULL,
        code_version TEXT NOT NULL
    );
    CREATE TABLE result_objects (
        result_id INTEGER NOT NULL REFERENCES results(id) ON DELETE CASCADE,
        name TEXT NOT NULL,
        sha256 TEXT NOT NULL,
        size INTEGER NOT NULL,
        PRIMARY KEY (result_id, name)
    );
    """)


def _m2_indexes(db: sqlite3.Connection) -> None:
    # reference look-ups (dedupe, garbage collection) and per-session event queries
    _run_script(db, """
    CREATE INDEX frames_sha ON frames(sha256);
    CREATE INDEX result_objects_sha ON result_objects(sha256);
    CREATE INDEX events_session ON events(session_id, id);
    """)


#: ordered forward migrations; migration i brings the schema to version i + 1
MIGRATIONS: list[Callable[[sqlite3.Connection], None]] = [_m1_initial, _m2_indexes]
SCHEMA_VERSION = len(MIGRATIONS)


@functools.cache
def code_version() -> str:
    """``gonio <version>`` plus ``+g<commit>`` when the code runs from a git checkout."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        text = f"gonio {version('gonio')}"
    except PackageNotFoundError:
        text = "gonio (not installed)"
    try:
        commit = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=Path(__file__).parent,
                                capture_output=True, text=True, timeout=5)
        if commit.returncode == 0 and commit.stdout.strip():
            text += f"+g{commit.stdout.strip()}"
    except (OSError, subprocess.SubprocessError):
        pass
    return text


# -- records ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class SessionInfo:
    """One session row. ``plan`` is the canonical plan dict; times are Unix seconds."""

    id: int
    name: str
    state: str
    operator: str
    object: str
    notes: str
    plan: dict[str, Any]
    plan_hash: str
    plan_path: str | None
    created: float
    updated: float


@dataclass(frozen=True)
class FrameRecord:
    """One stored frame. Exposures in seconds; ``positions`` are read-backs (degrees, mm)."""

    id: int
    session_id: int
    step: int
    bracket_index: int
    repeat: int
    sha256: str
    size: int
    filename: str
    format: str
    exposure_requested_s: float | None
    exposure_s: float | None
    iso: float | None
    fnumber: float | None
    positions: dict[str, Any]
    captured_at: float
    stored_at: float
    metadata: dict[str, Any]


@dataclass(frozen=True)
class Progress:
    """Counts of a session: planned and done steps, planned frames, stored frames and bytes."""

    steps_total: int
    steps_done: int
    frames_total: int
    frames_stored: int
    bytes_stored: int


@dataclass
class VerifyReport:
    """Outcome of :meth:`Store.verify`: lists of SHA-256 names / paths, empty when all is well."""

    checked: int = 0
    missing: list[str] = field(default_factory=list)
    corrupt: list[str] = field(default_factory=list)
    orphans: list[str] = field(default_factory=list)
    incomplete_steps: list[int] = field(default_factory=list)
    #: sha256 -> where the session uses it (``step 3 frame 1 ...``, ``result dark #2 ...``)
    where: dict[str, list[str]] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not (self.missing or self.corrupt or self.orphans or self.incomplete_steps)


def _dumps(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=_json_default)


def _json_default(obj: Any) -> Any:
    # numpy scalars / arrays and tuples from device read-backs
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")


def _is_full(exc: sqlite3.Error) -> bool:
    return getattr(exc, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _copy_hashed(src: Path, dst: Path, chunk: int = 1 << 22) -> str:
    """Copy ``src`` to a new file ``dst`` in one pass, returning the SHA-256 hex of the bytes
    copied. ``dst`` is created exclusively ("xb"): an existing file (the source itself, say) is
    never truncated."""
    h = hashlib.sha256()
    with open(src, "rb") as fin, open(dst, "xb") as fout:
        while block := fin.read(chunk):
            h.update(block)
            fout.write(block)
    return h.hexdigest()


def _try_lock(fd: int) -> bool:
    """Take ``fd``'s exclusive flock without waiting; False when another holder has it."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def sha256_file(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _unsafe_member(name: str) -> bool:
    parts = Path(name).parts
    return not parts or Path(name).is_absolute() or ".." in parts or "\\" in name


def _extract_safely(archive: Path, dest: Path) -> None:
    """Extract a ``.tar``/``.zip`` export into ``dest`` after checking every member: only plain
    files and folders with relative names inside ``dest``; else :class:`StoreError` naming it."""
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as z:
                for info in z.infolist():
                    if _unsafe_member(info.filename) or stat.S_ISLNK(info.external_attr >> 16):
                        raise StoreError(f"{archive}: refusing unsafe member {info.filename!r} (an "
                                         "absolute path, '..' or a link); a gonio export has none")
                z.extractall(dest)
            return
        with tarfile.open(archive) as t:
            for m in t.getmembers():
                if _unsafe_member(m.name) or not (m.isfile() or m.isdir()):
                    raise StoreError(f"{archive}: refusing unsafe member {m.name!r} (an absolute "
                                     "path, '..', a link or a device); a gonio export has none")
            t.extractall(dest, filter="data")
    except (tarfile.TarError, zipfile.BadZipFile, EOFError, zlib.error) as exc:
        raise StoreError(f"{archive}: damaged archive ({exc})") from None


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
                 durable: bool | None = None, readonly: bool = False) -> None:
        self.root = Path(root)
        self.durable = os.environ.get("GONIO_STORE_DURABLE", "1") != "0" if durable is None else durable
        self.readonly = readonly
        self.db_path = self.root / DB_NAME
        if not self.db_path.is_file():
            if not create or readonly:
                raise StoreError(f"{self.root} is not a gonio store (no {DB_NAME}); "
                                 "give --store the folder a session was recorded in")
            self.root.mkdir(parents=True, exist_ok=True)
        self.objects = self.root / "objects"
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
                files = sum(1 for _ in self._object_files())
                if files:
                    raise StoreDamaged(
                        f"{self.db_path} is empty but {self.objects} holds {files} file(s) of "
                        "captured data: the database was lost or truncated. Nothing was changed; "
                        "restore gonio.sqlite from a backup or an export, and keep objects/ as it is")
                if self.readonly:
                    raise StoreError(f"{self.db_path} is empty: no session was ever recorded there")
            elif not {"schema_version", "sessions"} <= tables:
                raise ForeignDatabase(
                    f"{self.db_path} is an SQLite database but not a gonio store (its tables: "
                    f"{', '.join(sorted(tables)[:8])}); gonio leaves it untouched. Give --store "
                    "a folder gonio recorded in, or a new folder")
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
            files = sum(1 for _ in self._object_files())
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
        """Open a store folder, or an exported ``.tar`` / ``.zip`` archive (extracted to a
        temporary folder that is removed on :meth:`close`, and on every error).

        An archive member that is absolute, climbs out with ``..``, or is a link or device
        (an export holds only folders and plain files) is refused by name before anything is
        extracted. ``readonly`` opens the database without writing to it (see :class:`Store`).
        """
        path = Path(path)
        if not (path.is_file() and (tarfile.is_tarfile(path) or zipfile.is_zipfile(path))):
            return cls(path, create=create, readonly=readonly)
        tmp = Path(tempfile.mkdtemp(prefix="gonio-store-"))
        try:
            _extract_safely(path, tmp)
            inner = [p.parent for p in tmp.rglob(DB_NAME)]
            if len(inner) != 1:
                raise StoreError(f"{path}: archive holds {len(inner)} gonio stores, expected 1")
            store = cls(inner[0], create=False, readonly=readonly)
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
            for version in range(current, SCHEMA_VERSION):
                MIGRATIONS[version](db)
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
            raise StoreError(f"{self.root} was opened read-only; this needs a writable store")
        with self._lock:
            # BEGIN inside the try: a KeyboardInterrupt landing just after it must not leave the
            # shared connection inside a transaction (every later BEGIN would then fail)
            try:
                self._db.execute("BEGIN IMMEDIATE")
                yield self._db
                _crash_point("before_commit")
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
            _crash_point("after_commit")

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
            [(session_id, e.time, e.kind.value, e.step, e.device, e.message, _dumps(e.data))
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
            if not _try_lock(sfd):
                raise SessionBusy(f"session {session!r} is being written by another process; "
                                  "wait for it to finish or pause it there")
            wfd = self._lock_file("writers.lock")
            try:
                removed = self.collect_garbage() if _try_lock(wfd) else None
                fcntl.flock(wfd, fcntl.LOCK_SH)  # converts the exclusive lock if we held it
                self._keep_reserve()
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
        try:
            with self._write() as db:
                cur = db.execute(
                    "INSERT INTO sessions (name, operator, object, notes, state, plan_json, "
                    "plan_hash, plan_path, created, updated) VALUES (?,?,?,?,?,?,?,?,?,?)",
                    (name, operator, object, notes, "planned", _dumps(plan), plan_hash,
                     plan_path, now, now))
                sid = cur.lastrowid
                db.executemany("INSERT INTO steps (session_id, idx, step_json, frames) "
                               "VALUES (?,?,?,?)",
                               [(sid, i, _dumps(s), s["frames"]) for i, s in enumerate(steps)])
        except sqlite3.IntegrityError:
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
        with self._write() as db:
            db.execute("INSERT INTO rig_snapshots (session_id, taken, config_json, describe_json) "
                       "VALUES (?,?,?,?)", (session_id, time.time(), _dumps(config), _dumps(describe)))

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
    def steps(self, session_id: int, *, pending_only: bool = False) -> list[tuple[int, dict, bool]]:
        """``(index, step dict, done)`` in execution order."""
        sql = "SELECT idx, step_json, done FROM steps WHERE session_id = ?"
        if pending_only:
            sql += " AND done = 0"
        return [(r[0], json.loads(r[1]), bool(r[2]))
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
        if not isinstance(sha256, str) or not _SHA_RE.fullmatch(sha256):
            raise StoreDamaged(f"{self.db_path}: refusing object hash {str(sha256)[:80]!r}: not 64 "
                               "lowercase hex digits (a damaged or crafted row)")
        return self.objects / sha256[:2] / sha256[2:]

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

    def _write_object(self, data: bytes | memoryview, sha: str) -> None:
        path = self.object_path(sha)
        try:
            if not self.objects.is_dir():
                self.objects.mkdir(parents=True, exist_ok=True)
                self._sync_dir(self.root)
            if not path.parent.is_dir():
                path.parent.mkdir(exist_ok=True)
                self._sync_dir(self.objects)
            self._write_file(data, path)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise StoreFull(f"no space left on the disk holding {self.root} while writing a "
                                f"{len(data) / 1e6:.1f} MB frame; free space and resume") from None
            raise

    def _sync_dir(self, path: Path) -> None:
        if self.durable:
            _fsync_dir(path)

    def _write_file(self, data: bytes | memoryview, path: Path) -> None:
        """Temp file in the final directory, fsync, rename, fsync the directory."""
        fd, tmp = tempfile.mkstemp(prefix=_TMP_PREFIX, dir=path.parent)
        try:
            view = memoryview(data)
            half = len(view) // 2
            with os.fdopen(fd, "wb") as f:
                f.write(view[:half])
                f.flush()
                _crash_point("object_half_written")
                f.write(view[half:])
                f.flush()
                if self.durable:
                    os.fsync(f.fileno())
            os.chmod(tmp, 0o444)  # content-addressed files are immutable
            _crash_point("object_fsynced")
            os.replace(tmp, path)
            _crash_point("object_renamed")
            self._sync_dir(path.parent)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise

    def _ensure_object(self, data: bytes | memoryview, sha: str) -> None:
        path = self.object_path(sha)
        try:
            if path.stat().st_size == len(data):
                return  # identical bytes are stored once
        except FileNotFoundError:
            pass
        self._write_object(data, sha)

    def put_object(self, data: bytes) -> str:
        """Store bytes durably (without a row referencing them); return their SHA-256 hex.

        An object no row references is an orphan: the next runner that starts with no other
        writer active collects it. Use :meth:`add_result` ``artifacts`` to store and reference
        bytes in one step."""
        sha = hashlib.sha256(data).hexdigest()
        self._ensure_object(data, sha)
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
            self._ensure_object(data, sha)
            with self._write() as db:
                # a concurrent writer may have dropped an identical, then-unreferenced file
                # between our check and this transaction; writes are serialised, so re-check here
                if not self.object_path(sha).exists():
                    self._write_object(data, sha)
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
                     exposure_requested_s, exposure_s, iso, fnumber, _dumps(positions or {}),
                     now if captured_at is None else captured_at, now, _dumps(metadata or {})))
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
        version = code_version()  # may run git: never while holding the database's write lock
        with self._writing():
            for sha, blob in blobs.values():
                self._ensure_object(blob, sha)
            with self._write() as db:
                for sha, blob in blobs.values():  # as in add_frame: re-check inside
                    if not self.object_path(sha).exists():
                        self._write_object(blob, sha)
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
                                 (session_id, category, kind, time.time(), _dumps(params or {}),
                                  _dumps(result), _dumps(frame_ids), version))
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

    def results(self, session_id: int, category: str | None = None) -> list[dict[str, Any]]:
        """Stored results, oldest first; ``artifacts`` maps name -> sha256 (read with
        :meth:`read_object`)."""
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
                out.append({"id": r["id"], "category": r["category"], "kind": r["kind"],
                            "created": r["created"], "params": json.loads(r["params_json"]),
                            "result": json.loads(r["result_json"]),
                            "input_frames": json.loads(r["input_frames_json"]),
                            "code_version": r["code_version"], "artifacts": arts})
        return out

    # -- integrity ----------------------------------------------------------------------------
    def _referenced(self) -> set[str]:
        with self._read() as db:
            return ({r[0] for r in db.execute("SELECT sha256 FROM frames")}
                    | {r[0] for r in db.execute("SELECT sha256 FROM result_objects")})

    def _object_files(self) -> Iterator[Path]:
        if self.objects.is_dir():
            for sub in sorted(self.objects.iterdir()):
                if sub.is_dir():
                    yield from sorted(sub.iterdir())

    def orphans(self, *, min_age_s: float = 0.0) -> list[Path]:
        """Object files no row references, and temporary files of interrupted writes, last
        modified at least ``min_age_s`` seconds ago (a running writer's file in flight is young).
        """
        refs = self._referenced()
        cutoff = time.time() - min_age_s
        out = []
        for p in self._object_files():
            if p.name.startswith(_TMP_PREFIX) or p.parent.name + p.name not in refs:
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
            return not _try_lock(fd)
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
        """Delete orphans (see :meth:`orphans`). Only safe with no writer running: use
        :meth:`writer`, which calls this when it holds the store exclusively."""
        removed = []
        for p in self.orphans():
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
                removed.append(str(p.relative_to(self.root)))
        return removed

    def remove_orphans(self) -> list[str]:
        """Delete orphans and ``.tmp-`` files now (what :meth:`writer` does when a runner starts),
        returning their paths relative to the store.

        Raises
        ------
        SessionBusy
            Something is writing this store right now (its files in flight look like orphans).
        """
        fd = self._lock_file("writers.lock")
        try:
            if not _try_lock(fd):
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
        report = VerifyReport(incomplete_steps=incomplete)
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
        name = dest.name.lower()
        archive = next((s for s in (".tar.gz", ".tgz", ".tar", ".zip") if name.endswith(s)), None)
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
                if _copy_hashed(src, dst) != sha:
                    raise StoreError(f"cannot export {session!r}: object {sha} is corrupt; "
                                     f"run 'gonio session verify {session}'")
                os.chmod(dst, 0o444)
            if archive is None:
                return dest
            if archive == ".zip":
                with zipfile.ZipFile(dest, "w", zipfile.ZIP_STORED, allowZip64=True) as z:
                    for p in sorted(folder.rglob("*")):
                        if p.is_file():
                            z.write(p, p.relative_to(work))
            else:
                mode = "w:gz" if archive in (".tar.gz", ".tgz") else "w"
                with tarfile.open(dest, mode) as t:
                    t.add(folder, arcname=folder.name)
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
