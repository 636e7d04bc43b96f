"""Give the memory a finished stage freed back to the operating system.

numpy's arrays below glibc's mmap threshold (which grows to 32 MiB as large arrays are freed)
come from the process's heap; freed, their pages stay resident until the heap's top is free, so
the resident set after a stage of many block-sized arrays stays at that stage's high-water mark
and the next stage's arrays pile on top of it. ``malloc_trim(0)`` hands every whole free page
back (glibc >= 2.8 trims inside the heap too, not only its top). Elsewhere (macOS, Windows, musl
without it) this is a no-op: the limit then holds what is live, not what the allocator keeps.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools

__all__ = ["release_freed_memory"]


@functools.cache
def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


def release_freed_memory() -> None:
    """Return the heap's free pages to the OS (glibc's ``malloc_trim``; elsewhere nothing)."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
