"""The numba kernels a pipeline run calls, each with the one signature its stage calls it with, compiled into numba's
on-disk cache ahead of the stages (`runner.py warmup`, or a background process the runner starts on a cold cache)."""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from panoworld.io.manifest import REPO_ROOT

KERNEL_MODULES = (
    "panoworld.geometry.floor_view", "panoworld.render.raster_kernels", "panoworld.video.background_layer",
    "panoworld.gaussians.fusion_kernels", "panoworld.gaussians.eig3", "panoworld.gaussians.pixel",
    "panoworld.render.splat_weights", "panoworld.gaussians.capture_fit", "panoworld.render.erp_operator",
    "panoworld.render.cull_kernels",
)
"""The modules of the kernels below, in the order of the stages that first call them."""
STAMP = "panoworld-kernels.json"
"""Written into the cache directory once every kernel is compiled there: its content is cache_key()."""
LOCK = "panoworld-kernels.lock"
"""Held by the process compiling the kernels (one at a time per cache directory)."""
PROGRESS = "panoworld-kernels.progress"
"""The background compilation appends a stage's name here once that stage's kernels are in the cache."""
KERNEL_STAGES = ("conditions", "video", "gaussians")
"""The pipeline stages that wait for the background compilation of their kernels, in the order they are compiled (the
register stage's one kernel compiles in under a second and only a home calls it, so a one-panorama scene's register
stage does not wait for it)."""
HOME_ONLY = ("capture_fit", "culling")
"""kernel_specs() groups only a home's run calls (the pruning of its capture fit's operators, the occlusion culling of
a mesh of millions of faces): the runner's background compilation of a one-panorama scene leaves them out."""
DISABLE_ENV = "PANOWORLD_PRECOMPILE"
"""Set to 0: the runner starts no background compilation (the stages compile what they call, as numba does)."""


def kernel_specs() -> list[tuple[str, str, str, tuple]]:
    """(stage, module, function, argument types) of every kernel, in pipeline order (imports numba)."""
    from numba import types as t

    def a(dtype, ndim, readonly=False):
        return t.Array(dtype, ndim, "C", readonly=readonly)

    f4, f8, i4, i8, u1, u8, b1 = t.float32, t.float64, t.int32, t.int64, t.uint8, t.uint64, t.boolean
    raster, fusion, splat = "panoworld.render.raster_kernels", "panoworld.gaussians.fusion_kernels", "panoworld.render.splat_weights"
    cull = "panoworld.render.cull_kernels"
    return [
        ("register", "panoworld.geometry.floor_view", "nearest_both_ways", (a(f4, 2),)),
        ("conditions", raster, "_vertex_pass", (a(f4, 2), a(f8, 2), i8, i8, f8, a(f4, 2))),
        ("conditions", raster, "_raster_pass", (a(i4, 2), a(f4, 2), i8, i8, a(f8, 1), a(f8, 1), a(f8, 1), a(f8, 1), f8,
                                                a(i8, 1), a(u8, 2), a(f4, 3))),
        ("conditions", raster, "_resolve_shaded", (a(u8, 2), a(f4, 3), a(i4, 2), a(u1, 2), a(b1, 1), i8, a(u1, 3),
                                                   a(f4, 2), a(b1, 2))),
        ("video", "panoworld.video.background_layer", "_stretch_kernel", (a(f8, 2), a(f8, 2), a(f8, 1), a(i8, 2),
                                                                          a(f4, 1))),
        ("gaussians", fusion, "_frame_points", (a(f4, 2), a(f8, 3, True), a(f8, 2), f8, a(f8, 3), a(i8, 1), a(f8, 2))),
        ("gaussians", fusion, "_footprints", (a(f8, 3), a(i8, 1), a(f8, 3, True), a(f8, 2), a(f8, 2), a(f8, 1),
                                              a(f8, 1))),
        ("gaussians", "panoworld.gaussians.eig3", "_eig3", (a(f8, 3), a(f8, 2), a(f8, 3))),
        ("gaussians", "panoworld.gaussians.pixel", "_source_lookup", (a(f8, 2), a(f8, 2), a(f8, 2), a(f8, 1), a(f8, 1))),
        ("gaussians", fusion, "_keys", (a(f8, 2), f8, a(i8, 1), a(i8, 2))),
        ("gaussians", fusion, "_frame_sums", (a(i8, 1), a(i8, 1), a(i8, 2), a(f8, 2), a(f8, 2), a(f8, 3), a(f8, 1), f8,
                                              a(i8, 1), a(f8, 1), a(f8, 2), a(i8, 1))),
        ("gaussians", fusion, "_merge", (t.Tuple((a(i8, 1), a(f8, 1), a(f8, 2), a(i8, 1))), a(i8, 1), a(f8, 1),
                                         a(f8, 2), a(i8, 1), a(i8, 1), a(i8, 1), a(f8, 1), a(f8, 2), a(i8, 1))),
        ("gaussians", splat, "view_candidate_indices", (a(f4, 2), a(f4, 1), a(f4, 1), a(f8, 2), f8, f8, f8, f8, i8, i8,
                                                        f8, f8, f8, f8)),
        ("gaussians", splat, "_tile_ranges", (a(f4, 2), a(f4, 2), i8, i8, i8, a(i8, 2))),
        ("gaussians", splat, "_bin", (a(i8, 2), a(i8, 1), i8, i8)),
        ("gaussians", splat, "tile_weights", (a(f4, 2), a(f4, 2), a(f4, 1), a(i8, 1), a(i8, 1), a(i8, 1), i8, i8, i8, i8,
                                              i8, a(b1, 1))),
        ("gaussians", "panoworld.gaussians.capture_fit", "_view_colors", (a(f4, 2), a(i8, 1), a(f4, 2))),
        ("gaussians", "panoworld.gaussians.capture_fit", "_add_view_grad", (a(f4, 2), a(i8, 1), a(f4, 2), a(f4, 2))),
        ("gaussians", "panoworld.render.erp_operator", "_csr_times", (a(i4, 1), a(i4, 1), a(f4, 1), a(f4, 2), a(f4, 2))),
        ("gaussians", "panoworld.render.erp_operator", "_csr_times_t", (a(i4, 1), a(i4, 1), a(f4, 1), a(f4, 2),
                                                                        a(f4, 2))),
        # HOME_ONLY groups, compiled last, no stage waits for them. "capture_fit": the pruning of the home's capture-fit
        # operators (its gaussians stage); "culling": ErpRasterizer's occlusion culling, for meshes of CULL_MIN_FACES
        # (6 M) faces and more (a home of about ten panoramas and more, in its conditions stage)
        ("capture_fit", "panoworld.render.erp_operator", "_prune_rows", (a(i4, 1), a(f4, 1), f8, a(b1, 1), a(i4, 1))),
        ("culling", cull, "_morton_keys", (a(f4, 2), a(f8, 1), f8)),
        ("culling", cull, "_cluster_vertices", (a(i4, 2), a(i8, 1), a(i8, 1), i8)),
        ("culling", cull, "_cluster_spheres", (a(f4, 2), a(i8, 1), a(i4, 1), a(f8, 2), a(f8, 1))),
        ("culling", cull, "_tile_far", (a(u8, 2), i8, i8, a(f4, 2))),
        ("culling", cull, "_may_show", (a(i8, 1), a(f8, 2), a(f8, 1), a(f8, 2), a(f4, 2), i8, i8, i8, a(b1, 1))),
        ("culling", cull, "_seen_clusters", (a(u8, 2), a(i4, 1), a(b1, 1))),
        ("culling", raster, "_vertex_pass_clusters", (a(f4, 2), a(f8, 2), i8, i8, f8, a(f4, 2), a(i8, 1), a(i4, 1),
                                                      a(i8, 1))),
        ("culling", raster, "_raster_clusters", (a(i4, 2), a(i8, 1), a(i8, 1), a(i8, 1), a(f4, 2), i8, i8, a(f8, 1),
                                                 a(f8, 1), a(f8, 1), a(f8, 1), f8, a(u8, 2), a(f4, 3))),
        ("eval", splat, "weighted_sums", (a(i4, 1), a(i4, 1), a(f4, 1), a(f4, 2), i8)),
        ("eval", raster, "_resolve_hits", (a(u8, 2), a(f4, 3), i8, a(f4, 2), a(i8, 2), a(f4, 3))),
    ]


def specs_to_compile(home: bool) -> list[tuple[str, str, str, tuple]]:
    """kernel_specs(), without home the HOME_ONLY groups left out."""
    return [spec for spec in kernel_specs() if home or spec[0] not in HOME_ONLY]


def compile_kernels(progress=None, *, home: bool = True) -> list[dict]:
    """Compile every kernel of kernel_specs() (or load it from numba's cache; without home, not the HOME_ONLY groups)
    -> rows {stage, kernel, seconds (CPU), cached (True: loaded from the on-disk cache, nothing compiled), error (None,
    or why it did not compile: its stage then compiles it as numba does)}; progress(row) after each."""
    import importlib

    rows = []
    for stage, module, name, sig in specs_to_compile(home):
        c0 = time.process_time()
        hits, error = 0, None
        try:
            fn = getattr(importlib.import_module(module), name)
            hits = sum(fn.stats.cache_hits.values())
            fn.compile(sig)
            hits = sum(fn.stats.cache_hits.values()) - hits
        except Exception as e:  # a kernel that does not compile here is compiled by its stage
            error = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
        row = {"stage": stage, "kernel": f"{module.rsplit('.', 1)[1]}.{name}", "seconds": time.process_time() - c0,
               "cached": hits > 0, "error": error}
        rows.append(row)
        if progress:
            progress(row)
    return rows


def cache_dir() -> Path:
    """Where numba caches the kernels: $NUMBA_CACHE_DIR, else beside the sources (the package's __pycache__)."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    return Path(env) if env else REPO_ROOT / "panoworld" / "__pycache__"


def cache_key() -> str:
    """Digest of what numba's cache of these kernels depends on: Python's version and the kernel sources' size and
    modification time (numba's own invalidation)."""
    parts = [sys.version]
    for m in KERNEL_MODULES:
        p = REPO_ROOT / (m.replace(".", "/") + ".py")
        try:
            st = p.stat()
            parts.append(f"{m}:{st.st_size}:{st.st_mtime_ns}")
        except OSError:
            parts.append(f"{m}:missing")
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def is_compiled(where: Path | None = None, *, home: bool = True) -> bool:
    """Whether every kernel (without home, but the HOME_ONLY groups) was compiled into the cache directory for the
    current sources."""
    try:
        stamp = json.loads(((where or cache_dir()) / STAMP).read_text())
        return stamp.get("key") == cache_key() and (stamp.get("home", True) or not home)
    except (OSError, ValueError, AttributeError):
        return False


def start_background_compile(*, home: bool = False) -> subprocess.Popen | None:
    """Start compiling the kernels in a background process, unless they are compiled already, another
    process is compiling them, or PANOWORLD_PRECOMPILE=0 -> the process (None when none was started). The lock it holds
    is released when it exits; stages that call a kernel before it is done compile it themselves, as numba does."""
    if os.environ.get(DISABLE_ENV) == "0" or is_compiled(home=home):
        return None
    where = cache_dir()
    try:
        where.mkdir(parents=True, exist_ok=True)
        fd = os.open(where / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return None  # another process is compiling them
        (where / PROGRESS).unlink(missing_ok=True)
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        return subprocess.Popen([sys.executable, "-m", "panoworld.framework.kernels", "--locked"] + (["--home"] if home else []),
                                cwd=REPO_ROOT, env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                pass_fds=(fd,))
    except OSError:
        return None
    finally:
        os.close(fd)  # the child's copy keeps the lock


def wait_for_stage(process: subprocess.Popen | None, stage: str, poll_s: float = 0.1, max_s: float = 300.0) -> float:
    """Before `stage` runs: while the background compilation `process` is still compiling that stage's kernels, wait
    (the stage would otherwise compile the same kernels again beside it), at most max_s -> seconds waited."""
    if process is None or stage not in KERNEL_STAGES:
        return 0.0
    t0 = time.perf_counter()
    progress = cache_dir() / PROGRESS
    while _running(process) and time.perf_counter() - t0 < max_s:
        try:
            if stage in progress.read_text().split():
                break
        except OSError:
            pass
        time.sleep(poll_s)
    return time.perf_counter() - t0


def _running(process: subprocess.Popen) -> bool:
    """Whether process has not exited, without reaping it (its CPU time stays for whoever waits for it)."""
    if process.returncode is not None:
        return False
    try:
        return os.waitid(os.P_PID, process.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is None
    except ChildProcessError:
        return False


def compile_and_stamp(progress=None, *, home: bool = True) -> list[dict]:
    """compile_kernels(), then the stamp that tells later runs the cache holds them all (without home: all but the
    HOME_ONLY groups)."""
    key = cache_key()
    rows = compile_kernels(progress, home=home)
    try:
        (cache_dir() / STAMP).write_text(json.dumps({"key": key, "home": home}))
    except OSError:
        pass
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m panoworld.framework.kernels", description=__doc__)
    ap.add_argument("--locked", action="store_true", help="started by the runner, which passed the held lock")
    ap.add_argument("--home", action="store_true", help="with --locked: the HOME_ONLY groups too (a home's run)")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    a = ap.parse_args(argv)
    if a.locked:
        specs = specs_to_compile(a.home)
        last = {stage: i for i, (stage, *_rest) in enumerate(specs)}
        done = iter(range(len(specs)))

        def stage_done(row: dict) -> None:
            if next(done) == last[row["stage"]]:
                with open(cache_dir() / PROGRESS, "a") as f:
                    f.write(row["stage"] + "\n")

        compile_and_stamp(stage_done, home=a.home)
        return 0
    rows = compile_and_stamp()
    print(json.dumps(rows, indent=2) if a.json else "\n".join(row_line(r) for r in rows))
    return 1 if any(r["error"] for r in rows) else 0


def row_line(r: dict) -> str:
    state = "FAILED" if r["error"] else "cached" if r["cached"] else "compiled"
    return f"{r['stage']:<11} {r['kernel']:<34} {state:<9} {r['seconds']:6.2f} s CPU" + (f"  {r['error']}" if r["error"] else "")


if __name__ == "__main__":
    sys.exit(main())
