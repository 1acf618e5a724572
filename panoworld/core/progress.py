"""Progress bars of long work: on a terminal, and in a stage's output where the runner shows it on one."""

from __future__ import annotations

import os

PROGRESS_ENV = "PANOWORLD_PROGRESS"
"""Set to 1 by the runner for the stages it starts while a terminal shows their output (`runner.py run`'s echo): their
output is a pipe, so their bars are drawn on purpose, every RUNNER_INTERVAL_S (the stage's log holds each redraw)."""
RUNNER_INTERVAL_S = 2.0


def bar(iterable=None, *, on: bool = True, **kwargs):
    """tqdm(iterable, **kwargs) drawn where someone watches: never when not on, always when the runner asks for it
    (PROGRESS_ENV), else only on a terminal (tqdm's own test)."""
    from tqdm import tqdm

    drawn = os.environ.get(PROGRESS_ENV) == "1"
    if drawn and on:
        kwargs.setdefault("mininterval", RUNNER_INTERVAL_S)
    return tqdm(iterable, disable=True if not on else (False if drawn else None), **kwargs)
