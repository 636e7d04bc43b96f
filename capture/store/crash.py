"""Crash hook points: tests kill the process at the N-th write/rename/commit point.

Callers use ``crash.point(name)`` through the module, so a test can replace :func:`point`.
"""
from __future__ import annotations

import os
import signal
import threading

_lock = threading.Lock()
#: hook points passed since the process started (or a test reset it)
count = 0


def point(name: str) -> None:
    """Kill this process with SIGKILL at the N-th hook point if ``GONIO_CRASH_AFTER=N`` is set.

    The crash test walks N over every write/rename/commit point of a session to prove that a
    kill at any of them leaves a store that ``resume`` completes with exactly the planned frames.
    """
    after = os.environ.get("GONIO_CRASH_AFTER")
    if not after:
        return
    global count
    with _lock:
        count += 1
        if count == int(after):
            os.write(2, f"GONIO_CRASH at {name}\n".encode())  # fd 2: unbuffered, never redirected
            os.kill(os.getpid(), signal.SIGKILL)
