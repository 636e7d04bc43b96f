"""The session store: one SQLite database (WAL) plus content-addressed frame files beside it.

One module per concern: :mod:`.database` (the :class:`Store` and its SQL), :mod:`.objects`
(content-addressed files), :mod:`.migrations` (schema), :mod:`.names` (safe session names),
:mod:`.archive` (exported archives), :mod:`.journal` and :mod:`.rebuild` (the index rebuilt
from the store's own files), :mod:`.crash` (test kill points), :mod:`.version` (the code
version recorded with results), :mod:`.records` (typed rows) and :mod:`.errors`.
"""
from .database import DB_NAME, FULL_BELOW_BYTES, QUARANTINE_DIR, RESERVE_BYTES, RESERVE_NAME, STATES, Store
from .errors import (ForeignDatabase, InvalidName, ObjectDamaged, SchemaError, SessionBusy, SessionExists,
                     SessionNotFound, StoreDamaged, StoreError, StoreFull)
from .migrations import MIGRATIONS, SCHEMA_VERSION
from .names import NAME_MAX, check_session_name, inside, safe_name_from
from .objects import sha256_file
from .rebuild import RebuildReport
from .records import FrameRecord, Progress, ResultRecord, SessionInfo, StoredStep, VerifyReport
from .version import code_version

__all__ = [
    "DB_NAME", "FULL_BELOW_BYTES", "QUARANTINE_DIR", "MIGRATIONS", "NAME_MAX", "RESERVE_BYTES", "RESERVE_NAME",
    "SCHEMA_VERSION", "STATES", "ForeignDatabase", "FrameRecord", "InvalidName", "ObjectDamaged", "Progress",
    "RebuildReport", "ResultRecord",
    "SchemaError", "SessionBusy", "SessionExists", "SessionInfo", "SessionNotFound", "Store",
    "StoreDamaged", "StoreError", "StoreFull", "StoredStep", "VerifyReport", "check_session_name",
    "code_version", "inside", "safe_name_from", "sha256_file",
]
