"""Serial transport: the one place where pyserial is called.

Drivers get a :class:`SerialTransport` (or anything with the same methods, e.g. a scripted fake
in protocol tests) and never see pyserial's exceptions: a vanished port becomes ``Disconnected``,
a missing answer ``DeviceTimeout``. A lock makes one request/reply exchange atomic, so a
poll thread and the caller can share a port.
"""
from __future__ import annotations

import logging
import threading
import time

import serial

from .errors import DeviceTimeout, Disconnected

log = logging.getLogger("gonio.rig.wire")


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

    # -- link ---------------------------------------------------------------------------------
    def open(self) -> None:
        try:
            self._serial = serial.Serial(self.port, self.baudrate, bytesize=8, parity="N",
                                         stopbits=1, timeout=self.timeout_s, write_timeout=self.timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise Disconnected(f"cannot open {self.port}: {exc}", device=self.device) from None

    def close(self) -> None:
        if self._serial is not None:
            try:
                self._serial.close()
            except (serial.SerialException, OSError):
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
            self._port().write(data)
            self._port().flush()
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise Disconnected(f"write to {self.port} failed: {exc}", device=self.device) from None

    def read_until(self, terminator: bytes = b"\n", timeout_s: float | None = None) -> bytes:
        """Read up to and including ``terminator``; raise ``DeviceTimeout`` if it does not come."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        port = self._port()
        try:
            if port.timeout != timeout:  # reconfiguring the tty costs a syscall; do it only on change
                port.timeout = timeout
            buf = port.read_until(terminator)  # pyserial returns early on timeout
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise Disconnected(f"read from {self.port} failed: {exc}", device=self.device) from None
        if not buf.endswith(terminator):
            raise DeviceTimeout(f"no complete reply (got {bytes(buf)!r})", device=self.device,
                                timeout_s=timeout)
        log.debug("%s < %r", self.device, buf)
        return bytes(buf)

    def read_exactly(self, n: int, timeout_s: float | None = None) -> bytes:
        """Read exactly ``n`` bytes or raise ``DeviceTimeout``."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        port = self._port()
        deadline = time.monotonic() + timeout
        buf = bytearray()
        try:
            while len(buf) < n:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(f"expected {n} bytes, got {bytes(buf)!r}", device=self.device,
                                        timeout_s=timeout)
                if port.timeout != remaining:
                    port.timeout = remaining
                buf += port.read(n - len(buf))
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise Disconnected(f"read from {self.port} failed: {exc}", device=self.device) from None
        log.debug("%s < %r", self.device, bytes(buf))
        return bytes(buf)

    def reset_input(self) -> None:
        """Drop unread bytes (stale replies after a timeout)."""
        try:
            self._port().reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise Disconnected(f"{self.port}: {exc}", device=self.device) from None
