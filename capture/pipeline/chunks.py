"""Chunked arrays of a session in its store folder: Zarr groups with their provenance and
per-task completion markers, so a re-run reuses what is stored and valid.

A group lives at ``<store>/arrays/<session>/<name>.zarr`` (outside ``objects/``: the store's
garbage collection never touches it). Its ``provenance`` attribute is the JSON of everything the
arrays were computed from (calibration result ids, frame ids, mesh digest, parameters, the
layout's version); :class:`ChunkGroup` opens a group whose provenance matches and wipes and
recreates one that does not, so stale arrays are never read. Each unit of work (one view's
pass) writes only its own chunks and then a marker file ``done/<task>`` (written whole, then
renamed into place): a run killed at any point resumes at the first task without a marker, and a
task re-run after a worker died rewrites the same chunks with the same bytes.

Every path is a plain folder a cluster's workers must see at the same path (a shared
filesystem): :mod:`capture.pipeline.cluster` checks that before sending work.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import zarr

__all__ = ["LAYOUT_VERSION", "ChunkGroup", "provenance_digest", "arrays_folder"]

#: bump when the arrays' meaning or layout changes: older groups are then recomputed
LAYOUT_VERSION = 1


def provenance_digest(provenance: dict[str, Any]) -> str:
    """SHA-256 of the provenance's canonical JSON (sorted keys)."""
    return hashlib.sha256(json.dumps(provenance, sort_keys=True, default=str).encode()).hexdigest()


def arrays_folder(store_root: str | os.PathLike, session: str) -> Path:
    """``<store>/arrays/<session>``: where a session's chunked arrays live."""
    return Path(store_root) / "arrays" / session


class ChunkGroup:
    """A Zarr group valid for one ``provenance`` (JSON-able dict): opened when its stored
    provenance matches, else emptied and made anew (``fresh`` tells which)."""

    def __init__(self, path: str | os.PathLike, provenance: dict[str, Any]) -> None:
        self.path = Path(path)
        self.provenance = {"layout": LAYOUT_VERSION, **provenance}
        self.digest = provenance_digest(self.provenance)
        self.fresh = True
        if self.path.exists():
            try:
                stored = zarr.open_group(str(self.path), mode="r").attrs.get("digest")
            except (FileNotFoundError, ValueError, KeyError, zarr.errors.GroupNotFoundError):
                stored = None
            if stored == self.digest:
                self.fresh = False
            else:
                shutil.rmtree(self.path)
        if self.fresh:
            group = zarr.open_group(str(self.path), mode="w")
            group.attrs.update({"digest": self.digest, "provenance": json.loads(json.dumps(self.provenance, default=str))})
        (self.path / "done").mkdir(exist_ok=True)

    def array(self, name: str, shape: tuple[int, ...], chunks: tuple[int, ...], dtype) -> zarr.Array:
        """The array ``name``, created (zero-filled, Zstd-compressed) unless it exists with this
        shape and dtype."""
        group = zarr.open_group(str(self.path), mode="a")
        if name in group:
            a = group[name]
            if a.shape == tuple(shape) and a.dtype == np.dtype(dtype):
                return a
            del group[name]
        return group.create_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=0)

    def open(self, name: str, mode: str = "r") -> zarr.Array:
        """An existing array (what a worker opens by path)."""
        return zarr.open_array(str(self.path / name), mode=mode)

    def done(self, task: str) -> bool:
        return (self.path / "done" / task).is_file()

    def mark_done(self, task: str) -> None:
        mark_done(self.path, task)


def mark_done(path: Path, task: str) -> None:
    """Record that ``task``'s chunks are all written (atomic: a whole file renamed into place)."""
    tmp = Path(path) / "done" / f".{task}.tmp{os.getpid()}"
    tmp.write_text("ok")
    os.replace(tmp, Path(path) / "done" / task)
