"""Progress bars: drawn on a terminal, in a stage's output when the runner shows that output on one, never when off."""

from __future__ import annotations

import io
import sys

from panoworld.core import progress
from panoworld.framework.execute import run_logged

STAGE = "from panoworld.core.progress import bar\nfor _ in bar(range(3), desc='long work'):\n    pass\nprint('done')"


class Pipe(io.StringIO):
    """sys.stderr where it is no terminal (the runner echoes a stage's output to its .buffer)."""

    sink = io.BytesIO()

    @property
    def buffer(self):
        return self.sink


class Terminal(Pipe):
    def isatty(self):
        return True


def test_bar_is_drawn_where_someone_watches(monkeypatch):
    monkeypatch.delenv(progress.PROGRESS_ENV, raising=False)
    shown = {}
    for env in (None, "1"):
        if env:
            monkeypatch.setenv(progress.PROGRESS_ENV, env)
        for on in (True, False):
            for stream in (Terminal(), Pipe()):
                list(progress.bar(range(3), desc="long work", on=on, file=stream))
                shown[env, on, type(stream).__name__] = "long work" in stream.getvalue()
    assert shown == {(None, True, "Terminal"): True, (None, True, "Pipe"): False,  # tqdm's own terminal test
                     (None, False, "Terminal"): False, (None, False, "Pipe"): False,
                     ("1", True, "Terminal"): True, ("1", True, "Pipe"): True,  # the runner shows this output
                     ("1", False, "Terminal"): False, ("1", False, "Pipe"): False}


def test_a_stage_the_runner_echoes_to_a_terminal_draws_its_bars_into_its_log(tmp_path, monkeypatch):
    """run_logged (how the runner starts every stage): the stage's output is a pipe, so its bars are drawn only when
    the runner echoes that output to a terminal; its log then holds them, else only what the stage printed."""
    monkeypatch.delenv(progress.PROGRESS_ENV, raising=False)
    for echo, stderr, drawn in ((True, Terminal(), True), (True, Pipe(), False), (False, Terminal(), False)):
        monkeypatch.setattr(sys, "stderr", stderr)
        log = tmp_path / f"{echo}-{type(stderr).__name__}.log"
        code, _, _ = run_logged([sys.executable, "-c", STAGE], log, echo=echo)
        text = log.read_text()
        assert code == 0 and text.rstrip().endswith("done")
        assert ("long work: " in text) == drawn, (echo, type(stderr).__name__, text)  # not the command line
