"""Base of the serial firmware simulators: a device on a pseudo-terminal.

A simulator owns the master side of an ``os.openpty()`` pair and serves requests on a thread;
the driver opens the slave through a stable symlink (``port``), exactly as it would open
``/dev/ttyUSB0``. ``disconnect()`` closes the pty (the driver's next read fails as on a pulled
cable); ``reconnect()`` makes a new pty behind the same symlink, like a device re-enumerating.

Faults are armed with :meth:`SerialSim.inject` and consumed one request at a time. The base class
implements the protocol-independent ones:

- ``no_reply``   the request is swallowed (the driver must time out, not hang);
- ``garble``     the reply's bytes are corrupted;
- ``disconnect`` the pty closes instead of replying.

Subclasses implement their own (``busy``, ``alarm``, ``limit``, ...) by calling
:meth:`take_fault` in :meth:`handle`.
"""
from __future__ import annotations

import os
import select
import shutil
import tempfile
import threading
import time
import tty
import weakref

from .faults import FaultInjection


class SerialSim(FaultInjection):
    """Firmware simulator skeleton.

    Parameters
    ----------
    name : str
        Device role, used for the symlink name (``turntable``).
    fast : bool
        Complete motion instantly (tests). Otherwise motion takes the modelled time.
    """

    #: bytes that end one request (None: the subclass frames requests in :meth:`split`)
    terminator: bytes | None = b"\n"
    #: fault names :meth:`inject` accepts; subclasses add their device faults
    FAULTS: frozenset[str] = frozenset({"no_reply", "garble", "disconnect"})

    def __init__(self, name: str, *, fast: bool = False) -> None:
        self.name = name
        self.fast = fast
        self._init_faults()
        self.requests: list[bytes] = []  # every request received, for tests
        self._dir = tempfile.mkdtemp(prefix=f"gonio-sim-{name}-")
        # removed by stop(), when the simulator is collected, or at interpreter exit (Ctrl-C,
        # an error): a simulated rig leaves no folder behind
        self._remove_dir = weakref.finalize(self, shutil.rmtree, self._dir, ignore_errors=True)
        self.port = os.path.join(self._dir, name)
        self._master: int | None = None
        self._slave: int | None = None
        self._thread: threading.Thread | None = None
        self._running = False

    # -- lifecycle ----------------------------------------------------------------------------
    def start(self) -> str:
        """Open the pty and serve; return the port path to give the driver."""
        self._open_pty()
        self._running = True
        self._thread = threading.Thread(target=self._serve, name=f"sim-{self.name}", daemon=True)
        self._thread.start()
        return self.port

    def stop(self) -> None:
        """Stop serving, close the pty and remove the port's temporary folder."""
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2)
        self._close_pty()
        self._remove_dir()

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        self._master, self._slave = master, slave
        if not self._remove_dir.alive:  # started again after stop()
            os.makedirs(self._dir, exist_ok=True)
            self._remove_dir = weakref.finalize(self, shutil.rmtree, self._dir, ignore_errors=True)
        tmp = self.port + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.port)

    def _close_pty(self) -> None:
        with self._lock:
            for fd in (self._master, self._slave):
                if fd is not None:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
            self._master = self._slave = None

    def disconnect(self) -> None:
        """Pull the cable: close the pty now. The serving thread keeps waiting for a reconnect."""
        self._close_pty()
        self.on_disconnect()

    def reconnect(self) -> None:
        """Plug back in: a fresh pty behind the same port path, firmware state as after power-up."""
        self._close_pty()
        self._open_pty()
        self.on_power_up()

    # -- hooks for subclasses -----------------------------------------------------------------
    def handle(self, request: bytes) -> bytes | None:
        """Answer one request (terminator stripped); None sends nothing."""
        raise NotImplementedError

    def split(self, buf: bytearray) -> list[bytes]:
        """Cut complete requests off the front of ``buf`` (in place). Default: by terminator."""
        out = []
        assert self.terminator is not None
        while True:
            i = buf.find(self.terminator)
            if i < 0:
                return out
            out.append(bytes(buf[:i]))
            del buf[: i + len(self.terminator)]

    def tick(self) -> bytes | None:
        """Called about every 5 ms; may return unsolicited bytes (e.g. an alarm message)."""
        return None

    def on_disconnect(self) -> None:
        """The cable was pulled (motion stops on a real device when it loses power)."""

    def on_power_up(self) -> None:
        """Reset firmware state as after power-up."""

    # -- faults (inject / take_fault / clear_faults: sims.faults.FaultInjection) ------------
    @staticmethod
    def garble(reply: bytes) -> bytes:
        """Corrupt a reply the way line noise does: flipped bits, a lost byte, terminator kept."""
        body = bytearray(reply.rstrip(b"\r\n"))
        tail = reply[len(body):]
        for i in range(0, len(body), 3):
            body[i] ^= 0x5A
        if len(body) > 4:
            del body[len(body) // 2]
        return bytes(body) + tail

    # -- serving ------------------------------------------------------------------------------
    def send(self, data: bytes) -> None:
        with self._lock:
            if self._master is None:
                return
            try:
                os.write(self._master, data)
            except OSError:
                pass

    def _serve(self) -> None:
        buf = bytearray()
        while self._running:
            master = self._master
            if master is None:
                time.sleep(0.005)
                continue
            try:
                ready, _, _ = select.select([master], [], [], 0.005)
                data = os.read(master, 65536) if ready else b""
            except OSError:
                # no reader on the slave side (between driver sessions) or pty closed
                time.sleep(0.005)
                data = b""
            if data:
                buf += data
                for request in self.split(buf):
                    self._dispatch(request)
            unsolicited = self.tick()
            if unsolicited:
                self.send(unsolicited)

    def _dispatch(self, request: bytes) -> None:
        self.requests.append(request)
        if self.take_fault("no_reply"):
            return
        if self.take_fault("disconnect"):
            self.disconnect()
            return
        reply = self.handle(request)
        if reply is None:
            return
        if self.take_fault("garble"):
            reply = self.garble(reply)
        self.send(reply)
