"""An ordered map over worker threads with a bounded number of calls in flight."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable


def cpu_threads(most: int) -> int:
    """Worker threads for a stage's own thread map: OMP_NUM_THREADS where set (the batch executors cap a stage's
    threads so), else the CPUs this process may run on; at least 1 and at most `most`."""
    env = os.environ.get("OMP_NUM_THREADS", "")
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    n = int(env) if env.isdigit() and int(env) > 0 else cpus
    return max(1, min(most, n))


def map_ahead(fn: Callable, items: Iterable, *, workers: int):
    """fn(item) for each item, in order, computed on `workers` threads with `workers` calls beyond the one being
    consumed in flight (items are drawn from the iterable in the caller's thread)."""
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    def call(box: list):  # the item leaves the box, so it dies with fn's call, not with the pool's work item, which
        return fn(box.pop())  # a busy worker thread may hold on to until after the result is handed over

    with ThreadPoolExecutor(workers) as pool:
        pending: deque = deque()
        for item in items:
            pending.append(pool.submit(call, [item]))
            del item
            if len(pending) > workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
