"""The stages' own thread maps: how many workers they take."""

from __future__ import annotations

import os

from panoworld.core.parallel import cpu_threads


def test_cpu_threads_follows_omp_num_threads_else_the_cpus(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert cpu_threads(8) == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert cpu_threads(2) == 2 and cpu_threads(8) == 3
    cpus = len(os.sched_getaffinity(0))
    for unusable in ("", "0", "2,1", "many"):  # unset, zero or a nested list: the CPUs this process may run on
        monkeypatch.setenv("OMP_NUM_THREADS", unusable)
        assert cpu_threads(64) == cpus and cpu_threads(1) == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert cpu_threads(64) == cpus
