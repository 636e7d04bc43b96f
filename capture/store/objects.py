"""Content-addressed object files: ``objects/ab/cdef...``, the bytes named by their SHA-256.

A file is written to a temporary name in its final directory, fsynced, renamed into place and
the directory fsynced, so a crash leaves either the whole file or a ``.tmp-`` file (collected
later), never a partial object. Objects are read-only and identical bytes are stored once.
"""
from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import tempfile
from pathlib import Path
from typing import Iterator

from . import crash
from .errors import StoreDamaged, StoreFull

#: prefix of a file being written (an interrupted write leaves one behind)
TMP_PREFIX = ".tmp-"
#: an object's name: its SHA-256 as 64 lowercase hex digits (paths are built from it)
_SHA_RE = re.compile(r"[0-9a-f]{64}")


def sha256_file(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def copy_hashed(src: Path, dst: Path, chunk: int = 1 << 22) -> str:
    """Copy ``src`` to a new file ``dst`` in one pass, returning the SHA-256 hex of the bytes
    copied. ``dst`` is created exclusively ("xb"): an existing file (the source itself, say) is
    never truncated."""
    h = hashlib.sha256()
    with open(src, "rb") as fin, open(dst, "xb") as fout:
        while block := fin.read(chunk):
            h.update(block)
            fout.write(block)
    return h.hexdigest()


class ObjectFiles:
    """The ``objects/`` folder of the store at ``store_root``.

    ``durable`` fsyncs files and directories (see :class:`~capture.store.Store`); ``db_path``
    only names the database in the error for a malformed hash read from it.
    """

    def __init__(self, store_root: Path, db_path: Path, durable: bool) -> None:
        self.store_root = store_root
        self.root = store_root / "objects"
        self.db_path = db_path
        self.durable = durable

    def path(self, sha256: str) -> Path:
        """``objects/ab/cdef...`` for a SHA-256 hex; :class:`StoreDamaged` for anything else
        (a path is never built from a malformed hash read from the database)."""
        if not isinstance(sha256, str) or not _SHA_RE.fullmatch(sha256):
            raise StoreDamaged(f"{self.db_path}: refusing object hash {str(sha256)[:80]!r}: not 64 "
                               "lowercase hex digits (a damaged or crafted row)")
        return self.root / sha256[:2] / sha256[2:]

    def files(self) -> Iterator[Path]:
        """Every file under ``objects/`` (objects and ``.tmp-`` files), sorted."""
        if self.root.is_dir():
            for sub in sorted(self.root.iterdir()):
                if sub.is_dir():
                    yield from sorted(sub.iterdir())

    def write(self, data: bytes | memoryview, sha: str) -> None:
        """Write ``data`` as object ``sha`` (replacing any file of that name)."""
        path = self.path(sha)
        try:
            if not self.root.is_dir():
                self.root.mkdir(parents=True, exist_ok=True)
                self._sync_dir(self.store_root)
            if not path.parent.is_dir():
                path.parent.mkdir(exist_ok=True)
                self._sync_dir(self.root)
            self._write_file(data, path)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise StoreFull(f"no space left on the disk holding {self.store_root} while writing "
                                f"a {len(data) / 1e6:.1f} MB frame; free space and resume") from None
            raise

    def ensure(self, data: bytes | memoryview, sha: str) -> None:
        """Write object ``sha`` unless a file of its size is already there."""
        path = self.path(sha)
        try:
            if path.stat().st_size == len(data):
                return  # identical bytes are stored once
        except FileNotFoundError:
            pass
        self.write(data, sha)

    def _sync_dir(self, path: Path) -> None:
        if self.durable:
            fsync_dir(path)

    def _write_file(self, data: bytes | memoryview, path: Path) -> None:
        """Temp file in the final directory, fsync, rename, fsync the directory."""
        fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX, dir=path.parent)
        try:
            view = memoryview(data)
            half = len(view) // 2
            with os.fdopen(fd, "wb") as f:
                f.write(view[:half])
                f.flush()
                crash.point("object_half_written")
                f.write(view[half:])
                f.flush()
                if self.durable:
                    os.fsync(f.fileno())
            os.chmod(tmp, 0o444)  # content-addressed files are immutable
            crash.point("object_fsynced")
            os.replace(tmp, path)
            crash.point("object_renamed")
            self._sync_dir(path.parent)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
