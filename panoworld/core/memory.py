"""Heap pages that freed arrays leave behind handed back to the operating system between a stage's large phases."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _malloc_trim():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc.malloc_trim
    except (OSError, AttributeError):  # not glibc: its allocator returns memory its own way
        return None


def release_free_memory() -> None:
    """glibc's malloc_trim(0): the free pages inside the heap's arenas go back to the OS. Temporaries of worker threads
    (the renderers' faces) fragment their arenas, so without it a process keeps every phase's peak resident although
    the memory is free; a no-op where the C library has no malloc_trim."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
