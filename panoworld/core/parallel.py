"""An ordered map over worker threads with a bounded number of calls in flight."""

from __future__ import annotations

from collections.abc import Callable, Iterable


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
