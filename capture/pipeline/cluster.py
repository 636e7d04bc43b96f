"""Where the pipeline's chunk tasks run: in this process (the default), on a Dask
``LocalCluster`` of worker processes (``--workers N``) or on an existing Dask cluster
(``--scheduler tcp://HOST:8786``: ``dask scheduler`` and ``dask worker`` started on the lab's
machines, or a SLURM queue through ``dask-jobqueue``).

The algorithms never see Dask: :meth:`Executor.map` takes a module-level function and its
argument tuples, and returns the results in order. On a cluster each task is a Dask future; a
worker that dies takes its running tasks with it and the scheduler re-runs them on another
worker (the tasks write only their own chunks, so a re-run writes the same bytes). The store is
read and written by path: :meth:`Executor.__enter__` asks every worker whether it sees the
store's folder and stops with the workers' addresses when one does not.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from dask.distributed import Client, LocalCluster, as_completed

__all__ = ["ClusterOptions", "ClusterError", "ClusterOptionError", "Executor"]


class ClusterError(RuntimeError):
    """The cluster cannot be used (unreachable scheduler, a worker that cannot see the store)."""


class ClusterOptionError(ValueError):
    """``--workers`` or ``--scheduler`` is malformed (the message names the option)."""


@dataclass(frozen=True)
class ClusterOptions:
    """How to run the chunk tasks.

    Attributes
    ----------
    workers : int
        0: in this process, one task after the other; N >= 1: a ``LocalCluster`` of N worker
        processes, one thread each, on 127.0.0.1.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:8786``); overrides ``workers``.
    worker_memory_bytes : int, optional
        A local cluster's per-worker memory limit (Dask pauses and restarts workers above it);
        default: Dask's share of the machine.
    """

    workers: int = 0
    scheduler: str | None = None
    worker_memory_bytes: int | None = None

    def __post_init__(self) -> None:
        if self.workers < 0:
            raise ClusterOptionError(f"--workers must be >= 0, got {self.workers}")
        if self.scheduler is not None and not self.scheduler.startswith(("tcp://", "tls://", "inproc://")):
            raise ClusterOptionError(f"--scheduler must be an address like tcp://HOST:8786, got {self.scheduler!r}")

    @property
    def in_process(self) -> bool:
        return self.scheduler is None and self.workers == 0


def _sees(path: str) -> bool:
    """Run on each worker: the store folder is there and holds the database."""
    return os.path.isdir(path) and os.path.isfile(os.path.join(path, "gonio.sqlite"))


class Executor:
    """A context manager mapping chunk tasks onto this process or a Dask cluster.

    Parameters
    ----------
    options : ClusterOptions
    store_root : path
        The store folder every worker must see (checked on entry).
    say : callable(str), optional
        Receives the dashboard address and the workers' count.
    """

    def __init__(self, options: ClusterOptions = ClusterOptions(), *, store_root: str | os.PathLike,
                 say: Callable[[str], None] = lambda text: None) -> None:
        self.options, self.store_root, self.say = options, str(Path(store_root).resolve()), say
        self.client = None
        self._cluster = None
        self.dashboard: str | None = None

    def __enter__(self) -> "Executor":
        if self.options.in_process:
            return self
        try:
            if self.options.scheduler is not None:
                self.client = Client(self.options.scheduler, timeout="10s")
            else:
                kw = {} if self.options.worker_memory_bytes is None else {"memory_limit": self.options.worker_memory_bytes}
                self._cluster = LocalCluster(n_workers=self.options.workers, threads_per_worker=1, processes=True,
                                             host="127.0.0.1", dashboard_address="127.0.0.1:0", **kw)
                self.client = Client(self._cluster)
        except OSError as exc:
            self.close()
            raise ClusterError(f"cannot reach the Dask scheduler {self.options.scheduler}: {exc}") from None
        self.dashboard = self.client.dashboard_link
        seen = self.client.run(_sees, self.store_root)
        blind = sorted(addr for addr, ok in seen.items() if not ok)
        if not seen:
            self.close()
            raise ClusterError(f"the Dask scheduler {self.options.scheduler} has no workers")
        if blind:
            self.close()
            raise ClusterError(f"Dask worker(s) {', '.join(blind)} cannot see the store {self.store_root}: "
                               "workers read frames and write chunks by path, so the store must be on a "
                               "filesystem they share, mounted at the same path")
        self.say(f"dask: {len(seen)} worker(s), dashboard {self.dashboard}")
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def map(self, fn: Callable[..., Any], args: Sequence[tuple], *,
            progress: Callable[[int, int], None] | None = None) -> list[Any]:
        """``[fn(*a) for a in args]``, on the cluster when there is one (results in order).
        ``progress(done, total)`` after each finished task."""
        total = len(args)
        if self.client is None:
            out = []
            for a in args:
                out.append(fn(*a))
                if progress is not None:
                    progress(len(out), total)
            return out
        futures = [self.client.submit(fn, *a, pure=False) for a in args]
        for done, _ in enumerate(as_completed(futures), 1):
            if progress is not None:
                progress(done, total)
        return self.client.gather(futures)
