"""Freed heap pages handed back to the operating system (core.memory)."""

from __future__ import annotations

import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from panoworld.core.memory import _malloc_trim, release_free_memory


def _resident_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux") or _malloc_trim() is None, reason="glibc's malloc_trim")
def test_freed_arrays_between_kept_ones_leave_the_resident_set():
    # glibc serves arrays below its (grown) mmap threshold from a thread's arena: freeing every other one leaves holes
    # that stay resident until trimmed
    big = np.ones(16 * 2**20, np.uint8)
    del big  # frees an mmapped block: the threshold grows past the arrays below

    def fill(_):
        arrays = [np.ones(2**20 - 4096, np.uint8) for _ in range(160)]
        return arrays[::2]

    with ThreadPoolExecutor(1) as pool:
        kept = pool.submit(fill, 0).result()
    before = _resident_mb()
    release_free_memory()
    after = _resident_mb()
    assert len(kept) == 80 and before - after > 40, (before, after)  # most of the 80 freed MB
