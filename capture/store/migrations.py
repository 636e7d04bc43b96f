"""The database schema and its ordered forward migrations."""
from __future__ import annotations

import sqlite3
from typing import Callable


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

