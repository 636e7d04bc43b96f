"""Exported stores as ``.tar`` / ``.tar.gz`` / ``.zip`` archives: packing, and extraction that
refuses any member that could land outside the destination."""
from __future__ import annotations

import shutil
import stat
import tarfile
import zipfile
import zlib
from pathlib import Path

from .errors import StoreError

#: archive suffixes an export may be written as, longest first
SUFFIXES = (".tar.gz", ".tgz", ".tar", ".zip")
#: an export's files (raw frames) barely compress: an archive that would expand to more than this
#: many times its own size (plus a little) is a bomb, not an export
MAX_EXPANSION = 20
EXPANSION_SLACK_BYTES = 64 << 20
#: members of one archive (a session at the plan caps holds ~1 M frames)
MAX_MEMBERS = 2_000_000


def archive_suffix(dest: Path) -> str | None:
    """The archive suffix ``dest`` ends with (case-insensitive), or None for a folder."""
    name = dest.name.lower()
    return next((s for s in SUFFIXES if name.endswith(s)), None)


def is_archive(path: Path) -> bool:
    """Whether ``path`` is a tar or zip file (by content, not by name)."""
    return path.is_file() and (tarfile.is_tarfile(path) or zipfile.is_zipfile(path))


def archive_read_only(path: Path) -> str:
    """Why a store opened from archive ``path`` refuses writes, and how to get a writable one."""
    return (f"{path} is an exported archive: gonio reads it but never writes to it (a write would go "
            f"to a temporary copy and vanish). For a writable store, extract it (mkdir STORE && tar "
            f"-xf {path} -C STORE, or unzip {path} -d STORE) and pass the folder holding gonio.sqlite "
            "as --store")


def pack(folder: Path, dest: Path, suffix: str) -> None:
    """Write ``folder`` (named by its own name inside) as archive ``dest`` of kind ``suffix``."""
    if suffix == ".zip":
        with zipfile.ZipFile(dest, "w", zipfile.ZIP_STORED, allowZip64=True) as z:
            for p in sorted(folder.rglob("*")):
                if p.is_file():
                    z.write(p, p.relative_to(folder.parent))
    else:
        mode = "w:gz" if suffix in (".tar.gz", ".tgz") else "w"
        with tarfile.open(dest, mode) as t:
            t.add(folder, arcname=folder.name)


def _unsafe_member(name: str) -> bool:
    parts = Path(name).parts
    return not parts or Path(name).is_absolute() or ".." in parts or "\\" in name


def extract_safely(archive: Path, dest: Path) -> None:
    """Extract a ``.tar``/``.zip`` export into ``dest`` after checking every member: only plain
    files and folders with relative names inside ``dest``, and in all no more bytes than
    :func:`expansion_cap` allows (a zip or tar.gz bomb); else :class:`StoreError` naming it."""
    cap = expansion_cap(archive, dest)
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as z:
                total = 0
                for n, info in enumerate(z.infolist()):
                    if _unsafe_member(info.filename) or stat.S_ISLNK(info.external_attr >> 16):
                        raise StoreError(f"{archive}: refusing unsafe member {info.filename!r} (an "
                                         "absolute path, '..' or a link); a gonio export has none")
                    total += info.file_size   # zipfile stops reading a member at its stated size
                    _check_expansion(archive, info.filename, total, n + 1, cap)
                z.extractall(dest)
            return
        with tarfile.open(archive) as t:
            total = 0
            for n, m in enumerate(t):   # streamed: a tar.gz bomb is refused at the cap, not after
                if _unsafe_member(m.name) or not (m.isfile() or m.isdir()):
                    raise StoreError(f"{archive}: refusing unsafe member {m.name!r} (an absolute "
                                     "path, '..', a link or a device); a gonio export has none")
                total += m.size
                _check_expansion(archive, m.name, total, n + 1, cap)
            t.extractall(dest, filter="data")
    except (tarfile.TarError, zipfile.BadZipFile, EOFError, zlib.error) as exc:
        raise StoreError(f"{archive}: damaged archive ({exc})") from None


def expansion_cap(archive: Path, dest: Path) -> int:
    """Bytes an archive may expand to: :data:`MAX_EXPANSION` x its size plus
    :data:`EXPANSION_SLACK_BYTES`, and never more than the free space where it is extracted."""
    free = shutil.disk_usage(dest).free - (16 << 20)
    return max(0, min(MAX_EXPANSION * archive.stat().st_size + EXPANSION_SLACK_BYTES, free))


def _check_expansion(archive: Path, member: str, total: int, count: int, cap: int) -> None:
    if count > MAX_MEMBERS:
        raise StoreError(f"{archive}: more than {MAX_MEMBERS:,} members; refusing to extract it "
                         "(a gonio export of a session at the plan caps has fewer)")
    if total > cap:
        raise StoreError(f"{archive}: refusing to extract it: by member {member!r} it would expand to "
                         f"more than {cap / 1e6:,.0f} MB ({MAX_EXPANSION} x the archive's "
                         f"{archive.stat().st_size / 1e6:,.1f} MB, or the free space where it is "
                         "extracted); an export's frames barely compress, so this is no gonio export")
