"""Shared pytest setup: single-threaded torch (2-core machines) and a session cache of synthetic scenes."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")


def pytest_configure(config):
    try:
        import torch
    except ImportError:
        return
    torch.set_num_threads(1)
