"""Running one stage of a scene as a subprocess: its command line, params file, log and exit status."""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from panoworld.framework.dag import StageNode
from panoworld.framework.scene import Scene, input_paths
from panoworld.io import manifest as art


def stage_command(node: StageNode, scene: Scene, params_file: str, python: str = sys.executable) -> list[str]:
    """`python -m <stage module> --out ... --params-file ... --<input> PATH...` for one stage of a scene."""
    cmd = [python, "-m", node.module, "--out", str(scene.artifact_dir(node.name)), "--params-file", params_file]
    for name, p in input_paths(node, scene).items():
        if p is not None:
            cmd += [f"--{name.replace('_', '-')}", str(p)]
    return cmd


def pending_log(log: Path) -> Path:
    """Where a stage's log is written while it runs; it becomes `log` unless the stage refused its input (exit 2)."""
    return log.with_name(f".{log.name}.{os.getpid()}.part")


def run_logged(cmd: list[str], log: Path, echo: bool = False, env_extra: dict[str, str] | None = None) -> tuple[int, float, float]:
    """Run cmd from the repository root with its output in `log`; returns (exit code, seconds, peak RSS MB).

    On exit code 2 (bad input) the output stays in pending_log(log), for the runner to read and delete: a refused
    input leaves no log behind, and the previous run's log stays. With echo on a terminal, cmd draws its progress bars
    into its output (core.progress.PROGRESS_ENV), so they show there."""
    import subprocess
    import threading

    from panoworld.core.progress import PROGRESS_ENV

    log = Path(log)
    log.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(art.REPO_ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env.update(env_extra or {})
    if echo and sys.stderr.isatty():
        env[PROGRESS_ENV] = "1"
    t0 = time.perf_counter()
    part = pending_log(log)
    with open(part, "wb") as logf:
        logf.write(f"$ {' '.join(cmd)}\n".encode())
        logf.flush()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, cwd=art.REPO_ROOT)

        def pump():
            assert proc.stdout is not None
            for chunk in iter(lambda: proc.stdout.read1(4096), b""):
                logf.write(chunk)
                logf.flush()
                if echo:
                    sys.stderr.buffer.write(chunk)
                    sys.stderr.flush()

        t = threading.Thread(target=pump, daemon=True)
        t.start()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        t.join()
    if proc.returncode != 2:
        os.replace(part, log)
    return proc.returncode, time.perf_counter() - t0, usage.ru_maxrss / 1024.0


PARAMS_FILE_PREFIX = ".params-"
"""Params files live beside the stage's log (never in /tmp) and are deleted after the stage; a run that holds the
scene lock deletes those a killed runner left."""


def run_with_params_file(template: list[str], params: dict, log: Path, echo: bool = False,
                         env_extra: dict[str, str] | None = None) -> tuple[int, float, float]:
    """Write the params file beside the log, run the stage command template ({params_file}, {python}), delete it."""
    import threading

    log = Path(log)
    log.parent.mkdir(parents=True, exist_ok=True)
    params_file = log.parent / f"{PARAMS_FILE_PREFIX}{log.stem}-{os.getpid()}-{threading.get_ident()}.json"
    params_file.write_text(json.dumps(params))
    try:
        cmd = [c.replace("{params_file}", str(params_file)).replace("{python}", sys.executable) for c in template]
        return run_logged(cmd, log, echo, env_extra)
    finally:
        params_file.unlink(missing_ok=True)


def runner_env(scene: Scene) -> dict[str, str]:
    """What a stage started by this process needs to check, before it commits, that its runner still holds the lock."""
    from panoworld.framework.stage import LOCK_ENV, LOCK_INODE_ENV, RUNNER_PID_ENV

    try:
        st = os.stat(scene.artifacts)
        inode = f"{st.st_dev}:{st.st_ino}"
    except OSError:
        inode = ""
    return {LOCK_ENV: str(scene.artifacts / art.LOCK_FILE), LOCK_INODE_ENV: inode, RUNNER_PID_ENV: str(os.getpid())}


def run_subprocess(node: StageNode, scene: Scene, params: Any, echo: bool) -> tuple[int, float, float]:
    """Run `python -m <stage module>` with explicit inputs; returns (exit code, seconds, peak RSS MB)."""
    from panoworld.framework.stage_cli import REFUSAL_ENV
    from panoworld.framework.stage_params import params_to_dict

    template = stage_command(node, scene, "{params_file}", python="{python}")
    env = {**runner_env(scene), REFUSAL_ENV: str(refusal_file(scene.log_file(node.name)))}
    return run_with_params_file(template, params_to_dict(params), scene.log_file(node.name), echo, env)


def refusal_file(log: Path) -> Path:
    """Where a stage started by this runner writes the one line refusing its input (exit 2)."""
    return log.with_name(f".{log.stem}.refusal")


StageExecutor = Callable[[StageNode, Scene, Any, bool], tuple[int, float, float]]
"""Runs one stage whose cache decision was taken (pipeline.run's `execute` hook): (node, scene, params, echo) ->
(exit code, seconds, peak RSS MB). The default runs a local subprocess; panoworld.tools.batch submits Ray tasks."""


MAX_REASON_CHARS = 400
"""A failed stage's reason is cut to this many characters in the run table and on stderr (the log has it all)."""


def failure_line(log: Path, stage: str) -> str:
    """The one-line reason a failed stage gave: its `error: stage NAME: ...` line, else the last line of its log."""
    try:
        lines = [ln.strip() for ln in log.read_text(errors="replace").splitlines()[-200:] if ln.strip()]
    except OSError:
        return ""
    prefix = f"error: stage {stage}: "
    line = next((ln[len(prefix):] for ln in reversed(lines) if ln.startswith(prefix)),
                lines[-1] if lines and not lines[-1].startswith("$ ") else "")
    return line if len(line) <= MAX_REASON_CHARS else line[:MAX_REASON_CHARS] + " ... (cut)"
