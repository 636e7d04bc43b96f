"""Future-like status of a device action (a move, a homing run, a capture).

Modelled on ophyd-async's ``AsyncStatus``: ``move_to()`` returns at once with a ``MoveStatus``;
the work runs on a background thread. The status is waitable from threads (``wait``) and
awaitable from asyncio (``await status``), so the CLI, the runner and the Textual UI share it.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
import threading
import time
from typing import Any, Callable

from .errors import DeviceTimeout


class MoveStatus:
    """The status of one running action.

    Parameters
    ----------
    target : object
        What the action moves towards (for display: ``12.5`` degrees, ``(az, el)``).
    device : str
        Name of the device, for messages.
    """

    def __init__(self, target: Any = None, *, device: str = "") -> None:
        self.target = target
        self.device = device
        self.started = time.monotonic()
        self._future: concurrent.futures.Future = concurrent.futures.Future()
        self._future.set_running_or_notify_cancel()

    # -- creation -----------------------------------------------------------------------------
    @classmethod
    def run(cls, fn: Callable[[], Any], *, target: Any = None, device: str = "",
            name: str = "move") -> "MoveStatus":
        """Run ``fn`` on a daemon thread and return its status at once."""
        status = cls(target, device=device)

        def _worker() -> None:
            try:
                status._set_result(fn())
            except BaseException as exc:  # noqa: BLE001 - delivered to the waiter
                status._set_exception(exc)

        threading.Thread(target=_worker, name=f"{device}-{name}", daemon=True).start()
        return status

    @classmethod
    def completed(cls, result: Any = None, *, target: Any = None, device: str = "") -> "MoveStatus":
        """A status that is already done (e.g. a move to the current position)."""
        status = cls(target, device=device)
        status._set_result(result)
        return status

    def _set_result(self, result: Any) -> None:
        self._future.set_result(result)

    def _set_exception(self, exc: BaseException) -> None:
        self._future.set_exception(exc)

    # -- inspection ---------------------------------------------------------------------------
    @property
    def done(self) -> bool:
        return self._future.done()

    @property
    def success(self) -> bool:
        return self.done and self._future.exception() is None

    def exception(self) -> BaseException | None:
        """The error the action ended with, or None (also None while still running)."""
        return self._future.exception() if self.done else None

    def add_callback(self, fn: Callable[["MoveStatus"], None]) -> None:
        """Call ``fn(status)`` when done (at once if already done), on the finishing thread."""
        self._future.add_done_callback(lambda _f: fn(self))

    def wait(self, timeout: float | None = None) -> Any:
        """Block until done; return the result or raise the action's error.

        Raises
        ------
        DeviceTimeout
            If the action has not finished within ``timeout`` seconds.
        """
        try:
            return self._future.result(timeout)
        except concurrent.futures.TimeoutError:
            raise DeviceTimeout(f"{self._what()} did not finish", device=self.device,
                                timeout_s=timeout) from None

    def __await__(self):
        return asyncio.wrap_future(self._future).__await__()

    def _what(self) -> str:
        return "action" if self.target is None else f"move to {self.target!r}"

    def __repr__(self) -> str:
        if not self.done:
            state = "pending"
        elif self._future.exception() is not None:
            state = f"errored: {self._future.exception()!r}"
        else:
            state = "done"
        return f"<MoveStatus {self.device} {self._what()} {state}>"


def wait_all(statuses: list[MoveStatus], timeout: float | None = None) -> list[Any]:
    """Wait for several statuses (moves on different devices run at the same time).

    All are waited for even if one fails — with any exception, not only a rig error — so no
    device is left moving unobserved; the first error is then raised.
    """
    deadline = None if timeout is None else time.monotonic() + timeout
    results, first_error = [], None
    for st in statuses:
        remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
        try:
            results.append(st.wait(remaining))
        except Exception as exc:  # noqa: BLE001 - re-raised once every status has been waited for
            results.append(None)
            first_error = first_error or exc
    if first_error is not None:
        raise first_error
    return results
