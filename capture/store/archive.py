"""Exported stores as ``.tar`` / ``.tar.gz`` / ``.zip`` archives: packing, and extraction that
refuses any member that could land outside the destination."""
from __future__ import annotations

import stat
import tarfile
import zipfile
import zlib
from pathlib import Path

from .errors import StoreError

#: archive suffixes an export may be written as, longest first
SUFFIXES = (".tar.gz", ".tgz", ".tar", ".zip")


def archive_suffix(dest: Path) -> str | None:
    """The archive suffix ``dest`` ends with (case-insensitive), or None for a folder."""
    name = dest.name.lower()
    return next((s for s in SUFFIXES if name.endswith(s)), None)


def is_archive(path: Path) -> bool:
    """Whether ``path`` is a tar or zip file (by content, not by name)."""
    return path.is_file() and (tarfile.is_tarfile(path) or zipfile.is_zipfile(path))


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
    files and folders with relative names inside ``dest``; else :class:`StoreError` naming it."""
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as z:
                for info in z.infolist():
                    if _unsafe_member(info.filename) or stat.S_ISLNK(info.external_attr >> 16):
                        raise StoreError(f"{archive}: refusing unsafe member {info.filename!r} (an "
                                         "absolute path, '..' or a link); a gonio export has none")
                z.extractall(dest)
            return
        with tarfile.open(archive) as t:
            for m in t.getmembers():
                if _unsafe_member(m.name) or not (m.isfile() or m.isdir()):
                    raise StoreError(f"{archive}: refusing unsafe member {m.name!r} (an absolute "
                                     "path, '..', a link or a device); a gonio export has none")
            t.extractall(dest, filter="data")
    except (tarfile.TarError, zipfile.BadZipFile, EOFError, zlib.error) as exc:
        raise StoreError(f"{archive}: damaged archive ({exc})") from None
