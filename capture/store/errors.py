"""The store's errors: each message says what was wrong and what to do."""
from __future__ import annotations


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


class ForeignDatabase(StoreError):
    """``gonio.sqlite`` is some other program's SQLite database."""


class InvalidName(StoreError, ValueError):
    """A session name outside the safe set (see :func:`check_session_name`)."""

