"""The methods' per-block results in Zarr, beside the lumitexels: a run interrupted as a whole
(Ctrl-C, SIGKILL, power) resumes from them, computing only the blocks without a stored result.

A method on a :class:`capture.pipeline.methods.BlockRoute` runs its per-texel steps as tasks
``fn(blocks, i, *model_so_far)`` (Lambertian's albedo, Lensch's statistics, labels, projection,
normal fitting ...). :class:`BlockResults` wraps the route's ``map_blocks``: each task, where it
runs (here or on a worker), writes what it returns to its own Zarr group
``<store>/arrays/<session>/block_results.zarr/<key>/`` (one array per returned array, the block
being the chunk; the return's shape, e.g. a tuple of arrays and sums, in the group's
``structure`` attribute) and then its marker ``done/<key>``; a task whose marker exists is read
back instead of run. ``key`` is the method's name and the task's provenance digest: the code
(a digest of the ``reconstruct`` and ``capture`` sources, so an uncommitted edit is new code),
the method, its options and seed, the task's function and every argument after the blocks (the
model so far, so a task after a changed step is a new task), and the group's own provenance is
the stored lumitexels' digest and the block layout (a new lumitexel set or block size wipes the
group). Read back, a result is bit for bit what the task returned, so a resumed run gives the
same figures and arrays as an uninterrupted one. Once a method has run to the end,
:meth:`BlockResults.prune` deletes that method's results no task of the run asked for (earlier
options or code), so the folder holds one run's results per method, not every run's.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import pickle
import shutil
from pathlib import Path
from typing import Any, Callable

import numpy as np
import zarr

from .chunks import ChunkGroup, mark_done
from .stored_blocks import StoredBlocks

__all__ = ["BlockResults", "read_result", "write_result"]

#: python scalars a task may return (stored as 0-d arrays, given back as the same type)
_PY_SCALARS = (bool, int, float)


class BlockResults:
    """The stored per-block results of one method's run over ``blocks``.

    ``provenance`` (JSON-able: the method, its options, the seed) keys every task with the
    function and arguments; :attr:`computed` and :attr:`reused` count the tasks this run
    computed and read back, :attr:`used` holds their keys."""

    def __init__(self, blocks: StoredBlocks, provenance: dict[str, Any]) -> None:
        arrays = blocks.arrays
        self.group = ChunkGroup(arrays.path.parent / "block_results.zarr",
                                {"lumitexels": arrays.digest, "blocks": [list(p) for p in blocks.parts]})
        self.blocks = blocks
        self.method = str(provenance.get("method", "task"))
        self.prefix = json.dumps({"code": sources_digest(), **provenance}, sort_keys=True, default=str).encode()
        self.computed = self.reused = 0
        self.used: set[str] = set()

    def key(self, fn: Callable, args: tuple) -> str:
        """The provenance digest of the task ``fn(*args)`` (``args[0]`` these blocks)."""
        if args[0] is not self.blocks:
            raise ValueError(f"a block task's first argument must be the route's blocks, got {type(args[0]).__name__}")
        h = hashlib.sha256(self.prefix)
        h.update(f"{fn.__module__}.{fn.__qualname__}".encode())
        for a in args[1:]:
            _digest(a, h)
        return f"{self.method}-{h.hexdigest()}"

    def prune(self) -> int:
        """Delete this method's stored results that no task of this run asked for (results of
        earlier options or code, which no run will read again); return how many. Call it only
        after the method ran to the end: an interrupted run's keys are not all known yet."""
        done = self.group.path / "done"
        stale = [p.name for p in done.glob(f"{self.method}-*") if p.name not in self.used]
        for key in stale:
            (done / key).unlink()   # the marker first: a half-deleted group is then never read
            shutil.rmtree(self.group.path / key, ignore_errors=True)
        return len(stale)

    def map(self, run: Callable[[Callable, list], list]) -> Callable[[Callable, list], list]:
        """``map_blocks`` for a :class:`capture.pipeline.methods.BlockRoute`: the tasks of ``fn``
        over ``args`` whose results are stored read back, the others run with ``run`` (an
        executor's ``map``) and stored as each finishes; results in order. Tasks over anything
        but these texel blocks (passive's blocks of pixels of its one image, seconds of work)
        just run."""
        def map_blocks(fn: Callable, args: list) -> list:
            if not all(a and a[0] is self.blocks for a in args):
                return run(fn, args)
            keys = [self.key(fn, a) for a in args]
            self.used.update(keys)
            todo = [k for k, key in enumerate(keys) if not self.group.done(key)]
            fresh = run(_stored_task, [(str(self.group.path), keys[k], fn, *args[k]) for k in todo]) if todo else []
            self.computed += len(todo)
            self.reused += len(args) - len(todo)
            out = dict(zip(todo, fresh))
            return [out[k] if k in out else read_result(self.group.path, key) for k, key in enumerate(keys)]
        return map_blocks


@functools.cache
def sources_digest() -> str:
    """SHA-256 of the ``reconstruct`` and ``capture`` packages' Python sources (paths and bytes),
    the code a block task runs: unlike the git commit it changes with an uncommitted edit, and it
    is the same for an installed copy of the same code. ~30 ms, once a process."""
    import reconstruct
    import capture
    h = hashlib.sha256()
    for package in (reconstruct, capture):
        root = Path(package.__file__).parent
        for path in sorted(root.rglob("*.py")):
            h.update(path.relative_to(root.parent).as_posix().encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def _stored_task(path: str, key: str, fn: Callable, *args: Any) -> Any:
    """``fn(*args)``, its result written to ``path/key`` and marked done (a per-block task)."""
    result = fn(*args)
    write_result(Path(path), key, result)
    mark_done(Path(path), key)
    return result


def write_result(path: Path, key: str, result: Any) -> None:
    """``result`` (arrays, scalars, None, and tuples, lists, str-keyed dicts and dataclasses of
    them) as the Zarr group ``path/key``: one array per leaf, named by its place ("0", "1.2",
    "weights" ...), its shape in the ``structure`` attribute."""
    group = zarr.open_group(str(path / key), mode="w")
    leaves: dict[str, np.ndarray] = {}
    group.attrs["structure"] = _flatten(result, "r", leaves)
    for name, value in leaves.items():
        a = group.create_array(name, shape=value.shape, dtype=value.dtype, chunks=tuple(max(n, 1) for n in value.shape),
                               fill_value=None)
        a[...] = value


def read_result(path: Path, key: str) -> Any:
    """What :func:`write_result` stored, as the task returned it (bit for bit)."""
    group = zarr.open_group(str(path / key), mode="r")
    return _unflatten(group.attrs["structure"], group)


def _flatten(obj: Any, name: str, leaves: dict[str, np.ndarray]) -> Any:
    if obj is None:
        return {"t": "none"}
    if isinstance(obj, np.ndarray):
        if obj.dtype.hasobject:
            raise TypeError(f"a block task returned an object array at {name}: not storable")
        leaves[name] = obj
        return {"t": "array", "name": name}
    if isinstance(obj, np.generic):
        leaves[name] = np.asarray(obj)
        return {"t": "scalar", "name": name}
    if isinstance(obj, _PY_SCALARS):
        leaves[name] = np.asarray(obj)
        return {"t": type(obj).__name__, "name": name}
    if isinstance(obj, (tuple, list)):
        return {"t": type(obj).__name__, "items": [_flatten(v, f"{name}.{k}", leaves) for k, v in enumerate(obj)]}
    if isinstance(obj, dict) and all(isinstance(k, str) for k in obj):
        return {"t": "dict", "items": {k: _flatten(v, f"{name}.{k}", leaves) for k, v in obj.items()}}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        cls = type(obj)
        return {"t": "dataclass", "class": f"{cls.__module__}:{cls.__qualname__}",
                "items": {f.name: _flatten(getattr(obj, f.name), f"{name}.{f.name}", leaves)
                          for f in dataclasses.fields(obj)}}
    raise TypeError(f"a block task returned a {type(obj).__name__} at {name}: not storable "
                    "(arrays, scalars, None, tuples, lists, dicts and dataclasses of them are)")


def _unflatten(node: dict, group: zarr.Group) -> Any:
    t = node["t"]
    if t == "none":
        return None
    if t == "array":
        return group[node["name"]][...]
    if t == "scalar":
        return group[node["name"]][...][()]
    if t in ("bool", "int", "float"):
        return {"bool": bool, "int": int, "float": float}[t](group[node["name"]][...][()])
    if t in ("tuple", "list"):
        items = [_unflatten(v, group) for v in node["items"]]
        return tuple(items) if t == "tuple" else items
    if t == "dict":
        return {k: _unflatten(v, group) for k, v in node["items"].items()}
    module, qualname = node["class"].split(":")
    cls = __import__(module, fromlist=[qualname])
    for part in qualname.split("."):
        cls = getattr(cls, part)
    return cls(**{k: _unflatten(v, group) for k, v in node["items"].items()})


def _digest(obj: Any, h) -> None:
    """Feed ``obj`` (a task argument) to the hash ``h``: arrays by dtype, shape and bytes,
    containers item by item, anything else by its pickle."""
    if isinstance(obj, np.ndarray):
        h.update(f"a{obj.dtype.str}{obj.shape}".encode())
        h.update(np.ascontiguousarray(obj).tobytes())
    elif isinstance(obj, (tuple, list)):
        h.update(f"{type(obj).__name__}{len(obj)}".encode())
        for v in obj:
            _digest(v, h)
    else:
        h.update(pickle.dumps(obj, protocol=5))
