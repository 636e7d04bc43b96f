"""Structured events of a capture session and a thread-safe bus to fan them out.

The runner emits one :class:`Event` per thing that happens (session started, step started,
moved, frame stored, fault, retry, paused, resumed, done, aborted ...). The CLI progress bar,
the TUI (which runs the runner in a thread worker and forwards events as messages) and the log
subscribe to the same :class:`EventBus`; the runner also persists every event in the store.
"""
from __future__ import annotations

import enum
import logging
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

log = logging.getLogger("gonio.capture")


class EventKind(str, enum.Enum):
    """What happened. The value is the name stored in the database and shown in logs."""

    SESSION_STARTED = "session_started"
    RESUMED = "resumed"
    STEP_STARTED = "step_started"
    MOVED = "moved"
    METERED = "metered"            # auto-exposure decided from metering shots
    TARGET = "target"              # the scene must change (checkerboard in, lens cap on ...)
    FRAME_STORED = "frame_stored"
    STEP_DONE = "step_done"
    RETRY = "retry"
    FAULT = "fault"
    LOW_DISK = "low_disk"
    PAUSED = "paused"
    DONE = "done"
    ABORTED = "aborted"
    NOTE = "note"                  # housekeeping worth a line in the log (orphans removed ...)


#: kinds logged at WARNING rather than INFO
_WARN = {EventKind.RETRY, EventKind.FAULT, EventKind.LOW_DISK, EventKind.PAUSED, EventKind.ABORTED}


@dataclass(frozen=True)
class Event:
    """One thing that happened in a session.

    Attributes
    ----------
    kind : EventKind
        What happened.
    session : str
        Session name.
    message : str
        One human-readable line.
    step : int or None
        Step index (0-based, in execution order) the event belongs to.
    device : str or None
        Device role for faults and retries (``turntable``, ``camera`` ...).
    data : dict
        Machine-readable details (JSON-serialisable): positions in degrees / millimetres,
        ``sha256``, ``attempt``, ``delay_s``, counters ``steps_done`` / ``steps_total`` /
        ``frames_done`` / ``frames_total`` and ``eta_s`` where known.
    time : float
        Unix seconds.
    """

    kind: EventKind
    session: str
    message: str = ""
    step: int | None = None
    device: str | None = None
    data: dict[str, Any] = field(default_factory=dict)
    time: float = field(default_factory=time.time)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["kind"] = self.kind.value
        return d

    def __str__(self) -> str:
        where = f" step {self.step}" if self.step is not None else ""
        dev = f" [{self.device}]" if self.device else ""
        return f"{self.session}{where}{dev} {self.kind.value}: {self.message}"


Subscriber = Callable[[Event], None]


class EventBus:
    """Delivers events to subscribers, synchronously, on the emitting thread.

    Subscribing, unsubscribing and emitting are safe from any thread. A subscriber that raises is
    logged and kept; it never breaks the runner (a broken progress bar must not stop a capture).
    Subscribers that touch a GUI must hop threads themselves (Textual: ``post_message`` or
    ``call_from_thread``).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subscribers: list[Subscriber] = []

    def subscribe(self, fn: Subscriber) -> Callable[[], None]:
        """Add ``fn``; return a function that removes it again."""
        with self._lock:
            self._subscribers = [*self._subscribers, fn]

        def unsubscribe() -> None:
            with self._lock:
                self._subscribers = [s for s in self._subscribers if s is not fn]
        return unsubscribe

    def emit(self, event: Event) -> None:
        with self._lock:
            subscribers = self._subscribers  # copy-on-write list: iterate without the lock
        for fn in subscribers:
            try:
                fn(event)
            except Exception:  # noqa: BLE001 - a faulty consumer must not stop the capture
                log.exception("event subscriber %r failed on %s", fn, event.kind.value)


def log_subscriber(logger: logging.Logger = log) -> Subscriber:
    """A subscriber writing each event as one log line (WARNING for faults, retries, pauses)."""
    def _log(event: Event) -> None:
        logger.log(logging.WARNING if event.kind in _WARN else logging.INFO, "%s", event)
    return _log
