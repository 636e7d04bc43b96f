"""Serial transport: the one place where pyserial is called.

Drivers get a :class:`SerialTransport` (or anything with the same methods, e.g. a scripted fake
in protocol tests) and never see pyserial's exceptions: a vanished port becomes ``Disconnected``,
a missing answer ``DeviceTimeout``. A lock makes one request/reply exchange atomic, so a
poll thread and the caller can share a port. An emergency stop is written *without* the lock
(``write`` needs none): it must not wait for an exchange in flight, and each ``write`` of a short
request is one ``write(2)``, which a tty does not interleave with another thread's (Linux holds
the tty's write lock for the whole call); the driver then reads the stop's reply under the lock.
"""
from __future__ import annotations

import logging
import os
import select
import termios
import threading
import time
from typing import Callable, TypeVar

import serial

from .errors import DeviceTimeout, Disconnected, ProtocolError

T = TypeVar("T")

log = logging.getLogger("gonio.rig.wire")

#: what a vanished port raises: pyserial's own errors, OS errors, and termios.error from
#: tcdrain/tcflush on a closed pty (not an OSError subclass)
_PORT_ERRORS = (serial.SerialException, OSError, termios.error)


class SerialTransport:
    """A byte pipe over a serial port (a real ``/dev/ttyUSB0`` or a simulator's pty).

    Parameters
    ----------
    port : str
        Device path.
    baudrate : int
        Line speed (8N1 framing).
    timeout_s : float
        Default time to wait for a reply, seconds.
    device : str
        Device name for error messages and the wire log.
    """

    def __init__(self, port: str, baudrate: int = 115200, *, timeout_s: float = 1.0,
                 device: str = "") -> None:
        self.port = port
        self.baudrate = baudrate
        self.timeout_s = timeout_s
        self.device = device
        self.lock = threading.RLock()
        self._serial: serial.Serial | None = None
        self._rx = bytearray()  # bytes received but not yet consumed

    # -- link ---------------------------------------------------------------------------------
    def open(self) -> None:
        self._rx.clear()
        try:
            self._serial = serial.Serial(self.port, self.baudrate, bytesize=8, parity="N",
                                         stopbits=1, timeout=self.timeout_s, write_timeout=self.timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise Disconnected(f"cannot open {self.port}: {exc}", device=self.device) from None

    def close(self) -> None:
        if self._serial is not None:
            try:
                self._serial.close()
            except _PORT_ERRORS:
                pass
            self._serial = None

    @property
    def is_open(self) -> bool:
        return self._serial is not None and self._serial.is_open

    def _port(self) -> serial.Serial:
        if self._serial is None:
            raise Disconnected(f"port {self.port} is not open", device=self.device)
        return self._serial

    # -- bytes --------------------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        log.debug("%s > %r", self.device, data)
        try:
            port = self._port()
            self._send(port, data, time.monotonic() + self.timeout_s)
            port.flush()
        except _PORT_ERRORS as exc:
            self.close()
            raise Disconnected(f"write to {self.port} failed: {exc}", device=self.device) from None

    def _send(self, port: serial.Serial, data: bytes, deadline: float) -> None:
        """Write every byte of ``data``, waiting for the port to take them until ``deadline``.

        Not pyserial's ``write``: on POSIX it raises "Write timeout" whenever the call as a
        whole outlasts ``write_timeout``, even after ``os.write`` took every byte (pyserial
        issue #281, open). A thread descheduled on a loaded machine then reported a command it
        had sent as a failed write and dropped the link. Here only bytes the port did not take
        in time are a timeout. (The port is open non-blocking, so ``os.write`` never waits.)
        """
        fd = port.fileno()
        left = memoryview(data)
        while True:
            try:
                left = left[os.write(fd, left):]
            except BlockingIOError:
                pass
            if not left:
                return
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([], [fd], [], remaining)[1]:
                raise serial.SerialTimeoutException(
                    f"the port took {len(data) - len(left)} of {len(data)} bytes in "
                    f"{self.timeout_s:g} s")

    def _fill(self, port: serial.Serial, deadline: float) -> bool:
        """Append what the port has to the receive buffer, waiting until ``deadline`` at most.

        Reads whole chunks with ``select`` + ``os.read`` instead of pyserial's byte-at-a-time
        ``read_until`` and never changes the port's timeout (each change is a ``tcsetattr``):
        this halves a request/reply round trip. Returns False on timeout.
        """
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return False
        fd = port.fileno()
        ready, _, _ = select.select([fd], [], [], remaining)
        if not ready:
            return False
        chunk = os.read(fd, 4096)
        if not chunk:  # readable but empty: the other end is gone
            raise OSError("device reports readiness to read but returned no data")
        self._rx += chunk
        return True

    def read_until(self, terminator: bytes = b"\n", timeout_s: float | None = None) -> bytes:
        """Read up to and including ``terminator``; raise ``DeviceTimeout`` if it does not come."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        port = self._port()
        deadline = time.monotonic() + timeout
        try:
            while (i := self._rx.find(terminator)) < 0:
                if not self._fill(port, deadline):
                    raise DeviceTimeout(f"no complete reply (got {bytes(self._rx)!r})",
                                        device=self.device, timeout_s=timeout)
        except _PORT_ERRORS as exc:
            self.close()
            raise Disconnected(f"read from {self.port} failed: {exc}", device=self.device) from None
        out = bytes(self._rx[: i + len(terminator)])
        del self._rx[: i + len(terminator)]
        log.debug("%s < %r", self.device, out)
        return out

    def read_exactly(self, n: int, timeout_s: float | None = None) -> bytes:
        """Read exactly ``n`` bytes or raise ``DeviceTimeout``."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        port = self._port()
        deadline = time.monotonic() + timeout
        try:
            while len(self._rx) < n:
                if not self._fill(port, deadline):
                    raise DeviceTimeout(f"expected {n} bytes, got {bytes(self._rx)!r}",
                                        device=self.device, timeout_s=timeout)
        except _PORT_ERRORS as exc:
            self.close()
            raise Disconnected(f"read from {self.port} failed: {exc}", device=self.device) from None
        out = bytes(self._rx[:n])
        del self._rx[:n]
        log.debug("%s < %r", self.device, out)
        return out

    def reset_input(self) -> None:
        """Drop unread bytes (stale replies after a timeout)."""
        self._rx.clear()
        try:
            self._port().reset_input_buffer()
        except _PORT_ERRORS as exc:
            self.close()
            raise Disconnected(f"{self.port}: {exc}", device=self.device) from None


class ScriptedTransport:
    """A fake transport that plays a scripted byte exchange (protocol tests, no port).

    Modelled on PyMeasure's ``expected_protocol``: ``script`` is a list of
    ``(request_bytes, reply_bytes)`` pairs. Each ``write`` must equal the next expected request
    (else ``AssertionError`` naming both); its reply is then readable. A reply of ``None`` means the
    device stays silent, so the next read times out with ``DeviceTimeout``. ``unsolicited``
    bytes are readable before the first request (a power-up banner). After the test,
    :meth:`assert_done` checks that every pair was used and no reply byte is left unread.
    """

    def __init__(self, script: list[tuple[bytes, bytes | None]], *, unsolicited: bytes = b"",
                 device: str = "", port: str = "scripted") -> None:
        self.script = list(script)
        self.device = device
        self.port = port
        self.timeout_s = 0.05
        self.lock = threading.RLock()
        self._rx = bytearray(unsolicited)
        self._open = False
        self.written: list[bytes] = []

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    def write(self, data: bytes) -> None:
        if not self._open:
            raise Disconnected("scripted port is not open", device=self.device)
        self.written.append(bytes(data))
        assert self.script, f"unexpected write {data!r}: the script is exhausted"
        expected, reply = self.script.pop(0)
        assert data == expected, f"wrote {data!r}, the script expected {expected!r}"
        if reply is not None:
            self._rx += reply

    def read_until(self, terminator: bytes = b"\n", timeout_s: float | None = None) -> bytes:
        i = self._rx.find(terminator)
        if i < 0:
            raise DeviceTimeout(f"no complete reply (got {bytes(self._rx)!r})", device=self.device,
                                timeout_s=self.timeout_s if timeout_s is None else timeout_s)
        out = bytes(self._rx[: i + len(terminator)])
        del self._rx[: i + len(terminator)]
        return out

    def read_exactly(self, n: int, timeout_s: float | None = None) -> bytes:
        if len(self._rx) < n:
            raise DeviceTimeout(f"expected {n} bytes, got {bytes(self._rx)!r}", device=self.device,
                                timeout_s=self.timeout_s if timeout_s is None else timeout_s)
        out = bytes(self._rx[:n])
        del self._rx[:n]
        return out

    def reset_input(self) -> None:
        self._rx.clear()

    def assert_done(self) -> None:
        """Every scripted request was sent and every reply byte read."""
        assert not self.script, f"script not finished; still expected {self.script[0][0]!r}"
        assert not self._rx, f"unread reply bytes left: {bytes(self._rx)!r}"


class SerialDriver:
    """The link bookkeeping every serial driver shares (mixed in before its device base class).

    The driver sets ``transport`` (a :class:`SerialTransport` or a stand-in) and ``name`` in its
    ``__init__``, and ``_connected = True`` at the end of a successful ``connect()``.
    """

    transport: SerialTransport
    name: str
    poll_retries: int = 2
    _connected: bool = False

    def close(self) -> None:
        """Mark the link down and close the port. Safe to call twice."""
        self._connected = False
        self.transport.close()

    @property
    def connected(self) -> bool:
        return self._connected and self.transport.is_open

    def _require(self) -> None:
        """Raise ``Disconnected`` unless ``connect()`` succeeded and the port is still open."""
        if not self.connected:
            raise Disconnected("not connected; call connect() first", device=self.name)

    def _poll(self, request: Callable[[], T]) -> T:
        """``request()``, an idempotent status poll, retried up to ``self.poll_retries`` more
        times on line noise or a lost reply, which must not fail a move."""
        failures = 0
        while True:
            try:
                return request()
            except (ProtocolError, DeviceTimeout):
                failures += 1
                if failures > self.poll_retries:
                    raise
