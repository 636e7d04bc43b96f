"""What the database and the rebuild share: rows' JSON columns as the store writes them, and the
non-blocking writer lock."""
from __future__ import annotations

import fcntl
import json
from typing import Any


def dumps(obj: Any) -> str:
    """JSON of a row's column: keys sorted, compact; numpy values and tuples as lists, sets sorted."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=_json_default)


def _json_default(obj: Any) -> Any:
    # numpy scalars / arrays and tuples from device read-backs
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")


def try_lock(fd: int) -> bool:
    """Take ``fd``'s exclusive flock without waiting; False when another holder has it."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True
