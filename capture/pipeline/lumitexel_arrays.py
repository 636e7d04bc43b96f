"""Lumitexels assembled out of core: one view at a time, samples written to texel-chunked Zarr
arrays in the session's store folder (:mod:`capture.pipeline.chunks`).

:func:`stream_lumitexels` runs :func:`reconstruct.lumitexels.assemble_lumitexels`'s two passes as
tasks an :class:`capture.pipeline.cluster.Executor` maps onto this process or a Dask cluster:

1. per view (no image read): ray-cast the object, store its hit pixels and rejection map
   (``hits/<k>.npz``: one view's pixels, not texel-chunked) and its visible pixels per face (a
   column of ``areas`` (F, V));
2. here: the best view per face and the texels it makes, written in view order to
   ``texels/{position,normal,best_view,pixel}`` (T, ...);
3. per view: decode and merge its raw brackets (:func:`capture.pipeline.process.merge_pose`),
   make the view, sample it over the texels block by block and write each block's column of
   ``samples`` (T, V, 16) float32, chunked (block, 1, 16): per (texel, view) ``wi``, ``wo``,
   ``reflectance``, ``diffuse``, ``specular`` (3 each) and 1 where the pair holds a sample (one
   array, one write per chunk: Zarr's per-call cost is ~5 ms on a loaded machine). A view's task
   writes only its own chunks, then its ``done`` marker.

Nothing holds more than one view's images and one texel block's samples; the memory a task
needs is set by the camera's size and ``block_texels``. Each texel's sample of a view depends on
that texel alone, so the stored samples equal the in-memory assembly's bit for bit; row-major
order over (texel, view) is the in-memory assembly's sample order. A run stopped at any point
resumes at the first view without a marker; a run with other inputs (calibration, frames, mesh,
block size) recomputes everything (:class:`capture.pipeline.chunks.ChunkGroup`).

Frames: object frame, mm; reflectance ``f_r cos theta_i`` in the calibration's units.
"""
from __future__ import annotations

import dataclasses
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
import zarr

from reconstruct.camera import CameraModel
from reconstruct.lensch import SvbrdfOptions
from reconstruct.lumitexels import (AssemblyGeometry, LumitexelError, Lumitexels, ViewHits, assembly_geometry,
                                    best_views, footprint_normal_spread, object_frame_camera,
                                    object_frame_point, view_hits, view_samples, view_texels)

from .chunks import ChunkGroup, arrays_folder, mark_done
from .cluster import Executor
from ..store import Store
from .images import SessionImages
from .process import PoseSpec, SessionCalibration, ViewPlan, merge_pose, session_images

__all__ = ["LumitexelArrays", "MemoryLimitError", "TexelBlock", "stream_lumitexels", "store_lumitexels",
           "block_texels_for", "default_memory_limit", "discovery_texels_for", "method_texels_for",
           "reject_filter_for"]

_SAMPLE_FIELDS = ("wi", "wo", "reflectance", "diffuse", "specular")
#: the channel of ``samples`` that says whether the (texel, view) pair holds a sample
_MASK = 3 * len(_SAMPLE_FIELDS)
_CHANNELS = _MASK + 1
#: bytes a texel of a block costs while a view is sampled or a block is read back (geometry,
#: frames, per view mask + five float32 triples), measured ~ 40 + 61 V; rounded up
_TEXEL_BYTES_FIXED, _TEXEL_BYTES_PER_VIEW = 200, 80
#: bytes per pixel a view's task holds: raw bracket frames, the merge's float64 planes, the
#: demosaiced radiance, diffuse, specular and validity (measured ~ 140 at 320 x 240, 2 x 2 frames)
_PIXEL_BYTES = 160
#: bytes of one sample in the gathered lumitexels: texel int64, view int32, weight and wi, wo,
#: reflectance, diffuse, specular float32 (76), rounded up
_GATHERED_SAMPLE_BYTES = 80


#: texels per block at most: a view's chunk of ``samples`` is then 16 MiB, past which a bigger
#: block saves no per-call overhead and only delays the first write
_MAX_BLOCK = 1 << 18


def reject_filter_for(width: int) -> int:
    """The depth/shadow-edge rejection box: 5 px at 1200 px wide (the assembly's default), at
    least 3 (at 320 x 240 a 5 px box dropped 40 % more samples for the same accuracy), odd."""
    return max(3, int(round(5 * width / 1200)) | 1)


def default_memory_limit() -> int:
    """Half of this machine's physical memory, bytes (the rest for the methods and the OS)."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2


class MemoryLimitError(ValueError):
    """``--memory-limit`` cannot hold one view's images per worker (the message says how much it needs)."""


def block_texels_for(memory_bytes: int, *, n_views: int, pixels: int, workers: int = 1) -> int:
    """Texels per block so that ``workers`` tasks, each holding one view's images and one
    block, stay within ``memory_bytes`` (at least 1024: below that the per-chunk overhead rules;
    at most 2**18).

    Raises
    ------
    MemoryLimitError
        The limit cannot hold even one view's images per worker (says how much it needs).
    """
    per_worker = memory_bytes / max(workers, 1)
    image = _PIXEL_BYTES * pixels
    if per_worker < 1.25 * image:
        raise MemoryLimitError(f"--memory-limit {memory_bytes / 2**20:.0f} MiB cannot hold one view's images "
                         f"per worker ({workers} x {image / 2**20:.0f} MiB at {pixels} pixels); give at least "
                         f"{1.25 * image * max(workers, 1) / 2**20:.0f} MiB")
    fit = (per_worker - image) // (_TEXEL_BYTES_FIXED + _TEXEL_BYTES_PER_VIEW * n_views)
    return int(min(_MAX_BLOCK, max(1024, fit)))


#: bytes a texel of a block costs per training view while a method works on it: Lensch's normal
#: fitting pads each texel's samples for its batched Levenberg-Marquardt (residuals, Jacobian,
#: per-basis values); measured ~ 520 above the assembly's at 960 x 720 (10 485-texel blocks),
#: x 3 for a margin
_METHOD_BYTES_PER_VIEW = 1600
#: bytes a texel of Lensch's material-discovery subsample holds per training view: its samples
#: as read and in the current normals' frames (float64), its lobe geometry; ~ 250, rounded up
_DISCOVERY_BYTES_PER_VIEW = 400


def method_texels_for(memory_bytes: int, n_train_views: int) -> int:
    """The most texels of one block a block method may work on within half of ``memory_bytes``
    (the other half for Lensch's material-discovery subsample), every texel counted with a
    sample in every training view (a bound); at least 1000."""
    return max(1000, int(memory_bytes // (2 * _METHOD_BYTES_PER_VIEW * max(n_train_views, 1))))


def discovery_texels_for(memory_bytes: int, n_train_views: int) -> int:
    """Lensch's material-discovery subsample within half of ``memory_bytes``, capped at the
    method's default (:attr:`reconstruct.lensch.SvbrdfOptions.discovery_texels`); at least 1000."""
    fit = int(memory_bytes // (2 * _DISCOVERY_BYTES_PER_VIEW * max(n_train_views, 1)))
    return max(1000, min(SvbrdfOptions().discovery_texels, fit))


@dataclass(frozen=True)
class _Job:
    """What every task of one assembly needs (pickled to the workers)."""

    path: str
    digest: str
    store_root: str
    session: str
    mesh: trimesh.Trimesh
    reject_filter_px: int
    block_texels: int
    separated: bool


#: per worker process: the assembly geometry (its ray-casting scene) of the job being run,
#: built once instead of once per task
_GEOMETRY: dict[str, AssemblyGeometry] = {}


#: per worker process: the session's images (a read-only store connection and its master darks)
_IMAGES: dict[tuple[str, str], SessionImages] = {}


def _images(job: _Job) -> SessionImages:
    key = (job.store_root, job.session)
    if key not in _IMAGES:
        _IMAGES.clear()
        _IMAGES[key] = session_images(Store(job.store_root, readonly=True), job.session)
    return _IMAGES[key]


def _geometry(job: _Job) -> AssemblyGeometry:
    if job.digest not in _GEOMETRY:
        _GEOMETRY.clear()
        _GEOMETRY[job.digest] = assembly_geometry(job.mesh, reject_filter_px=job.reject_filter_px)
    return _GEOMETRY[job.digest]


def _hits_task(job: _Job, k: int, cam: CameraModel, light: np.ndarray) -> None:
    """Pass 1 of view ``k``: its hits and rejection map, and its column of ``areas``."""
    geom = _geometry(job)
    hits = view_hits(geom, cam, light)
    folder = Path(job.path) / "hits"
    folder.mkdir(exist_ok=True)
    tmp = folder / f".{k}.tmp{os.getpid()}.npz"
    np.savez(tmp, **{name: getattr(hits, name) for name in ("pixel", "face", "position", "normal", "reject")})
    os.replace(tmp, folder / f"{k}.npz")
    zarr.open_array(str(Path(job.path) / "areas"), mode="r+")[:, k] = hits.face_areas(geom.n_faces)
    mark_done(Path(job.path), f"hits-{k}")


def _read_hits(path: str, k: int) -> ViewHits:
    with np.load(Path(path) / "hits" / f"{k}.npz") as z:
        return ViewHits(*(z[name] for name in ("pixel", "face", "position", "normal", "reject")))


def _samples_task(job: _Job, k: int, pose: PoseSpec, cal: SessionCalibration, cam: CameraModel,
                  light: np.ndarray, n_texels: int) -> None:
    """Pass 2 of view ``k``: merge its brackets, sample it block by block, write its column."""
    geom = _geometry(job)
    view = merge_pose(_images(job), pose, cal)
    with np.load(Path(job.path) / "hits" / f"{k}.npz") as z:
        reject = z["reject"]   # only the rejection map: an npz member is read when asked for
    root = Path(job.path)
    position = zarr.open_array(str(root / "texels" / "position"), mode="r")
    normal = zarr.open_array(str(root / "texels" / "normal"), mode="r")
    out = zarr.open_array(str(root / "samples"), mode="r+")
    for t0 in range(0, n_texels, job.block_texels):
        t1 = min(t0 + job.block_texels, n_texels)
        s = view_samples(geom, view, cam, light, reject, position[t0:t1], normal[t0:t1], separated=job.separated)
        dense = np.zeros((t1 - t0, _CHANNELS), np.float32)
        dense[s.texel, _MASK] = 1.0
        for c, name in enumerate(_SAMPLE_FIELDS[:5 if job.separated else 3]):
            dense[s.texel, 3 * c:3 * c + 3] = getattr(s, name)
        out[t0:t1, k, :] = dense
    mark_done(root, f"samples-{k}")


def _mesh_digest(mesh: trimesh.Trimesh) -> str:
    h = hashlib.sha256(np.ascontiguousarray(mesh.vertices, np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, np.int64).tobytes())
    return h.hexdigest()


def _provenance(session: str, cal: SessionCalibration, plan: ViewPlan, mesh: trimesh.Trimesh,
                reject_px: int, block: int) -> dict:
    cam = cal.camera
    return {"session": session, "calibration_ids": cal.ids, "mesh_sha256": _mesh_digest(mesh),
            "camera": {"K": cam.K.tolist(), "dist": np.asarray(cam.dist).tolist(), "R": cam.R.tolist(),
                       "t": np.asarray(cam.t).tolist(), "size": [cam.width, cam.height]},
            "light_intensity": np.asarray(cal.light_intensity, float).tolist(), "angle_scale": cal.angle_scale,
            "views": [{"frames": list(p.frame_ids), "steps": list(p.steps_all), "reading": p.reading,
                       "light_mm": np.asarray(p.light_mm).tolist()} for p in plan.ordered],
            "reject_filter_px": reject_px, "block_texels": block}


@dataclass(frozen=True)
class LumitexelArrays:
    """The stored lumitexels of a session: ``n_texels`` texels (in view order of their making),
    ``n_views`` views of which the first ``n_train`` are training views, the samples (T, V, 16)
    per (texel, view) pair; read a block with
    :meth:`block` or everything with :meth:`gather`."""

    path: Path
    digest: str
    n_texels: int
    n_views: int
    n_train: int
    block_texels: int
    separated: bool
    reused_views: int

    def _open(self, *parts: str) -> zarr.Array:
        return zarr.open_array(str(self.path.joinpath(*parts)), mode="r")

    @property
    def blocks(self) -> list[tuple[int, int]]:
        """The texel blocks ``(t0, t1)``: the chunks of every array."""
        return [(t0, min(t0 + self.block_texels, self.n_texels)) for t0 in range(0, self.n_texels, self.block_texels)]

    def block(self, t0: int, t1: int) -> tuple[Lumitexels, np.ndarray]:
        """Texels ``t0:t1`` with all their samples (texel indices from 0 within the block), and
        the boolean per sample telling a held-out view's sample. Texels without a training
        sample are left out (as :func:`capture.pipeline.process.split_samples` does)."""
        block = _rows(self._open("samples"), t0, t1)
        mask = block[:, :, _MASK] > 0
        keep = np.flatnonzero(mask[:, :self.n_train].any(axis=1))
        rows, cols = np.nonzero(mask[keep])   # row-major: by texel, then view: the assembly's order
        picked = block[keep[rows], cols]      # no copy of the kept texels' whole rows first
        del block
        fields = {name: np.ascontiguousarray(picked[:, 3 * c:3 * c + 3])
                  for c, name in enumerate(_SAMPLE_FIELDS[:5 if self.separated else 3])}
        tex = {name: self._open("texels", name)[t0:t1][keep] for name in ("position", "normal", "best_view", "pixel")}
        lt = Lumitexels(**tex, texel=rows.astype(np.int64), view=cols.astype(np.int32),
                        weight=np.ones(len(rows), np.float32), **fields)
        return lt, cols >= self.n_train

    def training_texels_per_block(self, blocks: list[tuple[int, int]]) -> np.ndarray:
        """Texels with a training sample in each of ``blocks`` (texel ranges), (n_blocks,): reads
        only the training views' sample flags."""
        flags = self._open("samples")
        out = np.zeros(len(blocks), np.int64)
        for k, (t0, t1) in enumerate(blocks):
            seen = np.zeros(t1 - t0, bool)
            for v in range(self.n_train):   # one chunk at a time (see _rows)
                seen |= flags[t0:t1, v, _MASK] > 0
            out[k] = seen.sum()
        return out

    def parts(self, max_texels: int | None = None) -> list[tuple[int, int]]:
        """:attr:`blocks` cut into parts of at most ``max_texels`` texels (a part of a chunk is
        read by decompressing the chunk and keeping the part's rows: a method holds more per
        texel than the assembly did)."""
        step = self.block_texels if max_texels is None else max(1, min(max_texels, self.block_texels))
        return [(a, min(a + step, t1)) for t0, t1 in self.blocks for a in range(t0, t1, step)]

    def iter_blocks(self, max_texels: int | None = None):
        """The texel blocks (:meth:`parts` of ``max_texels``) in order, each read when asked for
        (:class:`TexelBlock`): one block's samples in memory at a time."""
        first = 0
        for t0, t1 in self.parts(max_texels):
            lt, held = self.block(t0, t1)
            yield TexelBlock(first, lt, held)
            first += lt.n_texels

    def gathered_bytes(self) -> int:
        """The most bytes :meth:`gather` holds, from the arrays' shape alone: every (texel, view)
        pair a sample of :data:`_GATHERED_SAMPLE_BYTES`, twice (the blocks read, then joined)."""
        return 2 * _GATHERED_SAMPLE_BYTES * self.n_texels * self.n_views

    def gatherable_texels(self, memory_bytes: int) -> int:
        """The most texels whose samples :meth:`gather` (``texels=``) holds within ``memory_bytes``
        (every texel counted with a sample in every view: a bound); at least 1."""
        return max(1, int(memory_bytes // (2 * _GATHERED_SAMPLE_BYTES * max(self.n_views, 1))))

    def gather(self, texels: np.ndarray | None = None, *,
               max_texels: int | None = None) -> tuple[Lumitexels, Lumitexels]:
        """``(train, held_out)`` over every texel with a training sample, in memory: what
        :func:`capture.pipeline.process.lumitexels_with_held_out` returns, bit for bit. With
        ``texels`` (sorted, unique, in that numbering) only those texels, renumbered from 0;
        blocks read :meth:`parts` of ``max_texels``."""
        parts = list(self.iter_blocks(max_texels)) if texels is None else self._picked(texels, max_texels)
        def join(select_held: bool) -> Lumitexels:
            kw = {name: np.concatenate([getattr(b.lumitexels, name) for b in parts])
                  for name in ("position", "normal", "best_view", "pixel")}
            for name in ("view", "wi", "wo", "reflectance", "weight", *(("diffuse", "specular") if self.separated else ())):
                kw[name] = np.concatenate([getattr(b.lumitexels, name)[b.held == select_held] for b in parts])
            kw["texel"] = np.concatenate([b.lumitexels.texel[b.held == select_held] + b.first_texel for b in parts])
            return Lumitexels(**kw)
        train, held = join(False), join(True)
        # a texel's spread compares it with its pixel neighbours, which other blocks may hold
        train.footprint_spread_deg = held.footprint_spread_deg = footprint_normal_spread(train)
        return train, held

    def _picked(self, texels: np.ndarray, max_texels: int | None) -> list["TexelBlock"]:
        """The blocks of :meth:`iter_blocks` cut down to ``texels`` (gathered numbering), each
        block's first texel renumbered among the picked."""
        texels = np.asarray(texels, np.int64)
        out, first = [], 0
        for b in self.iter_blocks(max_texels):
            span = b.texels
            local = texels[(texels >= span.start) & (texels < span.stop)] - span.start
            if len(local):
                keep = np.isin(b.lumitexels.texel, local)
                out.append(TexelBlock(first, b.lumitexels.subset(local), b.held[keep]))
                first += len(local)
        return out


#: bytes of whole chunks one read of a block's samples decodes at once (:func:`_rows`)
_DECODED_BYTES = 4 * 2**20


def _rows(samples: zarr.Array, t0: int, t1: int) -> np.ndarray:
    """``samples[t0:t1]``, read a few views' chunks at a time (as many as
    :data:`_DECODED_BYTES` of whole chunks hold, at least one): Zarr reading several chunks in
    one call decodes them together on its threads (whole chunks, whatever rows are kept: 118 MiB
    for 2 621 of a 51 247-texel chunk's texels at 36 views, 3.3 MiB a view), and those threads'
    heaps keep their high-water mark (8 such reads at 9x: +76 MiB peak, 55 kept after
    ``malloc_trim``; a view a call: +28, 21); a view a call on small chunks pays Zarr's per-call
    overhead 36 times (+60 % CPU per block read on the quick demo; 6 views a call: +20 %)."""
    V = samples.shape[1]
    chunk = samples.chunks[0] * int(np.prod(samples.chunks[2:])) * samples.dtype.itemsize
    step = max(1, _DECODED_BYTES // chunk)
    out = np.empty((t1 - t0, *samples.shape[1:]), samples.dtype)
    for v in range(0, V, step):
        out[:, v:v + step] = samples[t0:t1, v:v + step]
    return out


@dataclass(frozen=True)
class TexelBlock:
    """One texel block of :class:`LumitexelArrays`: its ``lumitexels`` (texels numbered from 0
    within the block, training and held-out samples together), ``held`` (S,) bool telling the
    held-out samples, and ``first_texel``, the number of the block's first texel among all
    texels with a training sample (the numbering of :meth:`LumitexelArrays.gather` and of every
    fitted model's per-texel arrays)."""

    first_texel: int
    lumitexels: Lumitexels
    held: np.ndarray

    @property
    def texels(self) -> slice:
        """The block's texels in the gathered numbering."""
        return slice(self.first_texel, self.first_texel + self.lumitexels.n_texels)


def stream_lumitexels(images: SessionImages, session: str, cal: SessionCalibration, plan: ViewPlan,
                      mesh: trimesh.Trimesh, executor: Executor, *, block_texels: int,
                      progress: Callable[[int, int], None] | None = None) -> LumitexelArrays:
    """Assemble the session's lumitexels into ``<store>/arrays/<session>/lumitexels.zarr``
    (reusing what a previous run with the same inputs stored).

    Parameters
    ----------
    images, session
        The session's images (:func:`capture.pipeline.process.session_images`: its store, whose
        folder holds the arrays, and master darks) and its name.
    cal, plan
        The session's calibration and its views as files
        (:func:`capture.pipeline.process.view_plan`).
    mesh : trimesh.Trimesh
        The object's mesh, object frame, mm.
    executor : Executor
        Where the per-view tasks run.
    block_texels : int
        Texels per chunk (:func:`block_texels_for` from a memory limit).
    progress : callable(done, total), optional
        After each task of either pass (one count over both).

    Raises
    ------
    reconstruct.lumitexels.LumitexelError
        The object is not visible in any view, or no point is both seen and lit.
    """
    store_root = str(Path(images.store.root).resolve())
    _IMAGES.clear()
    _IMAGES[(store_root, session)] = images   # an in-process run merges through the caller's store
    poses = plan.ordered
    V = len(poses)
    reject_px = reject_filter_for(cal.camera.width)
    group = ChunkGroup(arrays_folder(store_root, session) / "lumitexels.zarr",
                       _provenance(session, cal, plan, mesh, reject_px, block_texels))
    separated = all(p.separated for p in poses)
    job = _Job(str(group.path), group.digest, store_root, session, mesh, reject_px, block_texels, separated)
    cams = [object_frame_camera(cal.camera, cal.object_pose(p.reading)) for p in poses]
    lights = [object_frame_point(cal.object_pose(p.reading), p.light_mm) for p in poses]
    F = len(mesh.faces)
    group.array("areas", (F, V), (F, 1), np.int64)
    hits_todo = [k for k in range(V) if not group.done(f"hits-{k}")]
    samples_todo = [k for k in range(V) if not group.done(f"samples-{k}")]
    total, done = len(hits_todo) + len(samples_todo), 0

    def tick(_d: int, _t: int) -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    executor.map(_hits_task, [(job, k, cams[k], lights[k]) for k in hits_todo], progress=tick)
    T = _write_texels(group, V, [c.width for c in cams], block_texels)
    # a chunk no longer than the texels: Zarr writes a partial chunk whole, so a (block, 1, 16)
    # chunk far beyond T cost its full size per view (0.4 s a view on the quick demo)
    block = min(block_texels, T)
    job = dataclasses.replace(job, block_texels=block)
    group.array("samples", (T, V, _CHANNELS), (block, 1, _CHANNELS), np.float32)
    # a view's task needs no probe map: keep it out of what is sent to the workers
    slim = dataclasses.replace(cal, environment=None, environment_weight=None)
    executor.map(_samples_task, [(job, k, poses[k], slim, cams[k], lights[k], T) for k in samples_todo],
                 progress=tick)
    n_train = sum(not p.held_out for p in poses)
    return LumitexelArrays(group.path, group.digest, T, V, n_train, block, separated,
                           reused_views=V - len(samples_todo))


def _write_texels(group: ChunkGroup, V: int, widths: list[int], block: int) -> int:
    """Pass 1's reduction: the best view per face and the texels each view makes, written in view
    order (one view's hits in memory at a time). Returns the texel count."""
    areas = zarr.open_array(str(group.path / "areas"), mode="r")[...]
    best = best_views(areas)
    T = int(areas[np.arange(len(areas)), best].sum())
    if group.done("texels"):
        return T
    if T == 0:
        raise LumitexelError("the object is not visible in any view (check poses and the mesh frame)")
    block = min(block, T)
    out = {"position": group.array("texels/position", (T, 3), (block, 3), np.float64),
           "normal": group.array("texels/normal", (T, 3), (block, 3), np.float64),
           "best_view": group.array("texels/best_view", (T,), (block,), np.int32),
           "pixel": group.array("texels/pixel", (T, 2), (block, 2), np.float32)}
    at = 0
    for k in range(V):
        part = view_texels(_read_hits(str(group.path), k), best, k, widths[k])
        n = len(part.position)
        if n == 0:
            continue
        normal = part.normal / np.linalg.norm(part.normal, axis=1, keepdims=True)
        for name, value in (("position", part.position), ("normal", normal), ("best_view", part.best_view),
                            ("pixel", part.pixel)):
            out[name][at:at + n] = value
        at += n
    group.mark_done("texels")
    return T



def store_lumitexels(lt: Lumitexels, n_train_views: int, path: str | os.PathLike, *,
                     block_texels: int) -> LumitexelArrays:
    """Lumitexels assembled elsewhere (synthesised for a test or a benchmark, or in memory)
    written in :func:`stream_lumitexels`'s layout at ``path`` (a ``.zarr`` folder, replaced when
    its content differs): views ``0 .. n_train_views - 1`` are training views, the rest held out.

    Raises
    ------
    ValueError
        Two samples share a (texel, view) pair (the layout holds one sample per pair), or a view
        is negative.
    """
    T, V = lt.n_texels, int(lt.view.max()) + 1 if lt.n_samples else n_train_views
    pair = lt.texel.astype(np.int64) * V + lt.view
    if lt.n_samples and (lt.view.min() < 0 or len(np.unique(pair)) != lt.n_samples):
        raise ValueError("store_lumitexels: each (texel, view) pair may hold one sample, views >= 0")
    separated = lt.diffuse is not None and lt.specular is not None
    h = hashlib.sha256()
    for name in ("position", "normal", "texel", "view", "wi", "wo", "reflectance", *(("diffuse", "specular") if separated else ())):
        h.update(np.ascontiguousarray(getattr(lt, name)).tobytes())
    block = max(1, min(block_texels, T))
    group = ChunkGroup(path, {"synthesised": h.hexdigest(), "n_train": n_train_views, "block_texels": block})
    if not group.done("stored"):
        dense = np.zeros((T, V, _CHANNELS), np.float32)
        dense[lt.texel, lt.view, _MASK] = 1.0
        for c, name in enumerate(_SAMPLE_FIELDS[:5 if separated else 3]):
            dense[lt.texel, lt.view, 3 * c:3 * c + 3] = getattr(lt, name)
        group.array("samples", (T, V, _CHANNELS), (block, 1, _CHANNELS), np.float32)[...] = dense
        for name, width, dtype in (("position", 3, np.float64), ("normal", 3, np.float64),
                                   ("best_view", 0, np.int32), ("pixel", 2, np.float32)):
            shape, chunks = ((T, width), (block, width)) if width else ((T,), (block,))
            group.array(f"texels/{name}", shape, chunks, dtype)[...] = getattr(lt, name)
        group.mark_done("stored")
    return LumitexelArrays(group.path, group.digest, T, V, n_train_views, block, separated, reused_views=0)
