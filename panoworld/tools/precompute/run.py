"""Offline precomputation of trajectory-conditioned training clips for whole datasets, on a local pool or on Ray."""

from __future__ import annotations

import argparse
import enum
import hashlib
import json
import multiprocessing
import os
import sys
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from panoworld.core.errors import InputError
from panoworld.framework.stage import execute_stage, input_digest, load_stage, stage_key
from panoworld.framework.stage_params import params_to_dict
from panoworld.io import manifest as art
from panoworld.io.jsonio import write_json
from panoworld.io.jsonl import write_jsonl
from panoworld.io.safe_write import check_output_dir
from panoworld.tools.precompute import clip as clip_mod

INDEX = "index.jsonl"
FAILURES = "failures.jsonl"
SUMMARY = "summary.json"


class ClipSampling(enum.StrEnum):
    TRAVERSAL = "traversal"
    """The paper: every clip has `frames` frames; the traversal scale (track frames between clip frames) is uniform."""
    LENGTH = "length"
    """Legacy: the frame count is uniform over [min_frames, frames] at a uniform stride (long clips are rare)."""


@dataclass(kw_only=True)
class PrecomputeParams:
    clips_per_scene: int = 4
    """Clips sampled per scene (clip j of a scene never changes when K grows)."""
    strides: tuple[int, ...] = (1, 2, 4)
    """Traversal scales (strides r, track frames between clip frames) to sample uniformly from."""
    frames: int = 81
    """traversal: frames per clip; length: the longest clip."""
    min_frames: int = 5
    """length sampling only: shortest clip, in frames."""
    sampling: ClipSampling = ClipSampling.TRAVERSAL
    """traversal (the paper: fixed frame count, uniform traversal scale) or length (legacy: uniform frame count)."""
    continuous_scale: bool = False
    """traversal: draw the scale uniformly from [min(strides), max(strides)] (frame k = start + round(s k))
    instead of from the stride set."""
    height: int = 480
    """Output ERP height; width is 2 x height."""
    seed: int = 0
    """Sampling seed."""
    write_depth: bool = True
    """Write warped depth next to warped RGB and mask."""
    write_targets: bool = True
    """Write the ground-truth target frames of every clip."""


@dataclass(frozen=True)
class ClipSpec:
    scene: str
    clip: int
    track: int
    start: int
    length: int
    stride: float
    """Traversal scale: track frames between consecutive clip frames (an integer unless continuous_scale)."""

    @property
    def clip_id(self) -> str:
        return f"clip_{self.clip:04d}"


def _scene_hash(name: str) -> int:
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "little")


def clip_span(length: int, stride: float) -> int:
    """Track frames covered by a clip of `length` frames at traversal scale `stride` (frame k = start + round(s k))."""
    return int(round(stride * (length - 1))) + 1


def sample_clips(scene: str, track_lengths: list[int], params: PrecomputeParams) -> list[ClipSpec]:
    """Clip j of a scene (docs/precompute.md).

    traversal (the paper): scale s ~ U(strides) (or U[min, max] with continuous_scale), `frames` frames, track ~ U
    over the tracks long enough for that span, start ~ U over the valid starts; a scene none of whose tracks fits a
    drawn scale is a ValueError (it goes to failures.jsonl) rather than a biased scale distribution.
    length (legacy): track ~ U{tracks}, stride ~ U(strides), length ~ U{min_frames..frames} capped by the track
    (a clip of L frames at stride r spans (L - 1) r + 1 track frames), start ~ U over the valid starts.

    Each clip draws from its own generator seeded by (seed, scene name, j), so clips are stable under
    adding scenes or raising clips_per_scene.
    """
    if params.sampling == ClipSampling.TRAVERSAL:
        return [_sample_traversal(scene, track_lengths, params, j) for j in range(params.clips_per_scene)]
    out = []
    for j in range(params.clips_per_scene):
        rng = np.random.default_rng([params.seed, _scene_hash(scene), j])
        track = int(rng.integers(len(track_lengths)))
        n = track_lengths[track]
        stride = int(rng.choice(params.strides))
        max_len = min(params.frames, (n - 1) // stride + 1)
        if max_len < params.min_frames:
            # Shorter tracks than asked for: take the longest clip the track allows at this stride.
            length = max_len
        else:
            length = int(rng.integers(params.min_frames, max_len + 1))
        start = int(rng.integers(0, n - (length - 1) * stride))
        out.append(ClipSpec(scene, j, track, start, length, stride))
    return out


def _sample_traversal(scene: str, track_lengths: list[int], params: PrecomputeParams, j: int) -> ClipSpec:
    rng = np.random.default_rng([params.seed, _scene_hash(scene), j])
    if params.continuous_scale:
        stride: float = float(rng.uniform(min(params.strides), max(params.strides)))
    else:
        stride = int(rng.choice(params.strides))
    span = clip_span(params.frames, stride)
    fits = [t for t, n in enumerate(track_lengths) if n >= span]
    if not fits:
        raise ValueError(
            f"scene {scene}: tracks of {max(track_lengths)} frames are too short for {params.frames} frames at "
            f"traversal scale {stride:g} ({span} track frames); use longer tracks (runner.py synth --frames "
            f"{clip_span(params.frames, max(params.strides))}), fewer --frames or --sampling length"
        )
    track = fits[int(rng.integers(len(fits)))]
    start = int(rng.integers(0, track_lengths[track] - span + 1))
    return ClipSpec(scene, j, track, start, params.frames, stride)


# ---------------------------------------------------------------- executors


class LocalExecutor:
    """A process pool (one single-threaded worker per core by default).

    Workers are spawned, not forked: forking a process whose numba/OpenMP thread pools are running deadlocks.
    """

    def __init__(self, workers: int):
        self.workers = workers

    def imap_unordered(self, fn: Callable, tasks: list) -> Iterator:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=_worker_init) as pool:
            pending = {pool.submit(fn, t) for t in tasks}
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    yield f.result()


class RayExecutor:
    """Ray Core tasks (`num_cpus=1` each); connects to `address` or starts a local instance with `workers` CPUs."""

    def __init__(self, workers: int, address: str | None):
        try:
            import ray
        except ImportError:
            raise RuntimeError("the ray executor needs Ray: pip install '.[ray]'") from None
        self.ray = ray
        if not ray.is_initialized():
            kw: dict[str, Any] = {"address": address} if address else {"num_cpus": workers, "include_dashboard": False}
            ray.init(log_to_driver=False, runtime_env={"env_vars": thread_env(1)}, **kw)
        self.workers = workers

    def imap_unordered(self, fn: Callable, tasks: list) -> Iterator:
        remote = self.ray.remote(num_cpus=1, max_retries=0)(_ray_call)
        pending = [remote.remote(fn, t) for t in tasks]
        while pending:
            done, pending = self.ray.wait(pending, num_returns=1)
            for ref in done:
                yield self.ray.get(ref)


def _ray_call(fn, task):
    _worker_init()
    return fn(task)


THREAD_VARS = ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def thread_env(threads: int = 1) -> dict[str, str]:
    """Environment variables that cap a worker process's native thread pools at `threads`."""
    return {k: str(max(1, int(threads))) for k in THREAD_VARS}


def _worker_init() -> None:
    os.environ.update(thread_env(1))
    try:
        import numba

        numba.set_num_threads(1)
    except (ImportError, ValueError):
        pass
    import cv2

    cv2.setNumThreads(1)


def make_executor(kind: str, workers: int, address: str | None = None):
    if kind == "local":
        return LocalExecutor(workers)
    if kind == "ray":
        return RayExecutor(workers, address)
    raise ValueError(f"--executor {kind}: expected local or ray")


# ---------------------------------------------------------------- tasks


@dataclass(frozen=True)
class ClipTask:
    spec: ClipSpec
    scene_root: str
    out_dir: str
    params: dict


def _clip_inputs(scene_root: Path, spec: ClipSpec) -> dict[str, Path | None]:
    from panoworld.tools.dataset import DatasetScene

    ds = DatasetScene(scene_root)
    files = ds.frame_files(spec.track, spec.start)
    glb = ds.gt_dir / ds.index.get("glb", "scene.glb")
    return {
        "gt_index": ds.gt_dir / "gt.json",
        "source_rgb": files[0] if files else None,
        "source_depth": files[1] if files else None,
        "scene_glb": glb if files is None and glb.is_file() else None,
    }


def _clip_params(spec: ClipSpec, p: PrecomputeParams) -> clip_mod.Params:
    return clip_mod.Params(
        track=spec.track, start=spec.start, length=spec.length, stride=spec.stride, height=p.height,
        write_depth=p.write_depth, write_targets=p.write_targets,
    )


def run_clip(task: ClipTask) -> dict:
    """Render one clip unless its cached artifact is up to date; never raises (errors are returned)."""
    spec = task.spec
    row: dict[str, Any] = {**asdict(spec), "clip": spec.clip_id}
    t0 = time.perf_counter()
    try:
        stage = load_stage(clip_mod)
        params = clip_mod.Params(**task.params)
        inputs = _clip_inputs(Path(task.scene_root), spec)
        digests = {n: input_digest(n, stage.inputs[n], p) for n, p in inputs.items()}
        key = stage_key(stage, params, digests)
        out = Path(task.out_dir)
        try:
            manifest = art.read_manifest(out, stage.artifact)
            cached = manifest["key"] == key and art.verify_files(out, manifest) is None
        except art.ArtifactError:
            cached = False
        if not cached:
            manifest = execute_stage(stage, inputs, params, out, input_digests=digests)
        row.update(status="cached" if cached else "rendered", digest=manifest["digest"], seconds=time.perf_counter() - t0)
    except Exception as e:  # one bad clip or scene must not stop the others
        row.update(status="failed", error=f"{type(e).__name__}: {e}", seconds=time.perf_counter() - t0)
    return row


# ---------------------------------------------------------------- driver


def precompute(
    dataset_dir: Path, out_dir: Path, params: PrecomputeParams, *, executor: str = "local", workers: int = 1,
    ray_address: str | None = None, progress: bool = True,
) -> dict:
    """Sample and render every clip of every scene; write index.jsonl, failures.jsonl and summary.json."""
    from tqdm import tqdm

    from panoworld.register.inputs import is_multi_scene
    from panoworld.tools.dataset import DatasetError, DatasetScene

    dataset_dir, out_dir = Path(dataset_dir), Path(out_dir)
    if not dataset_dir.is_dir():
        raise InputError(f"{dataset_dir}: dataset directory not found")
    scene_dirs = sorted(p for p in dataset_dir.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not scene_dirs:
        raise InputError(f"{dataset_dir}: no scene directories inside")
    failures: list[dict] = []
    tasks: list[ClipTask] = []
    for sd in scene_dirs:
        try:
            if is_multi_scene(sd):
                raise DatasetError(f"{sd}: a home of several panoramas, whose ground-truth track holds only its capture "
                                   "poses; training clips come from single-panorama scenes with trajectory tracks "
                                   "(runner.py synth OUT --scenes K --frames N)")
            ds = DatasetScene(sd)
            specs = sample_clips(sd.name, [ds.n_frames(t) for t in range(ds.n_tracks)], params)
        except (DatasetError, KeyError, TypeError, ValueError) as e:
            failures.append({"scene": sd.name, "clip": None, "error": f"{type(e).__name__}: {e}"})
            continue
        for spec in specs:
            p = params_to_dict(_clip_params(spec, params))
            tasks.append(ClipTask(spec, str(sd), str(out_dir / sd.name / spec.clip_id), p))
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows: list[dict] = []
    frames_rendered = 0
    ex = make_executor(executor, workers, ray_address)
    bar = tqdm(total=len(tasks), desc="clips", unit="clip", disable=not progress)
    for row in ex.imap_unordered(run_clip, tasks) if tasks else []:
        rows.append(row)
        if row["status"] == "rendered":
            frames_rendered += row["length"]
        elif row["status"] == "failed":
            failures.append({"scene": row["scene"], "clip": row["clip"], "error": row["error"]})
        bar.update()
        bar.set_postfix(fps=f"{frames_rendered / max(time.perf_counter() - t0, 1e-9):.1f}")
    bar.close()
    wall = time.perf_counter() - t0
    ok = sorted((r for r in rows if r["status"] != "failed"), key=lambda r: (r["scene"], r["clip"]))
    _write_index(out_dir, ok, params)
    write_jsonl(out_dir / FAILURES, sorted(failures, key=lambda f: (f["scene"], f["clip"] or "")))
    summary = {
        "clips": len(tasks),
        "rendered": sum(r["status"] == "rendered" for r in rows),
        "cached": sum(r["status"] == "cached" for r in rows),
        "failed": len(failures),
        "failed_scenes": sorted({f["scene"] for f in failures}),
        "frames_rendered": frames_rendered,
        "seconds": wall,
        "frames_per_s": frames_rendered / wall if wall > 0 else 0.0,
        "executor": executor,
        "workers": workers,
    }
    write_json(out_dir / SUMMARY, summary, indent=2)
    return summary


def _write_index(out_dir: Path, rows: list[dict], params: PrecomputeParams) -> None:
    lines = []
    for r in rows:
        clip_dir = Path(r["scene"]) / r["clip"]
        lines.append(
            {
                "scene": r["scene"], "clip": r["clip"], "track": r["track"], "start": r["start"], "length": r["length"],
                "stride": r["stride"], "height": params.height, "width": 2 * params.height,
                "path": clip_dir.as_posix(), "clip_json": (clip_dir / "clip.json").as_posix(),
                "conditions": (clip_dir / "cond" / "conditions.json").as_posix(), "digest": r["digest"],
            }
        )
    write_jsonl(out_dir / INDEX, lines)



def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python runner.py precompute", description=__doc__)
    ap.add_argument("dataset", type=Path, help="directory of scene directories, each with gt/gt.json (docs/precompute.md)")
    ap.add_argument("--out", type=Path, required=True, help="output directory (index.jsonl, failures.jsonl, clips)")
    ap.add_argument("--clips-per-scene", type=int, default=PrecomputeParams.clips_per_scene)
    ap.add_argument("--strides", default="1,2,4", help="comma-separated strides to sample from")
    ap.add_argument("--frames", type=int, default=PrecomputeParams.frames,
                    help="frames per clip (traversal sampling) or the longest clip (length sampling)")
    ap.add_argument("--min-frames", type=int, default=PrecomputeParams.min_frames,
                    help="shortest clip in frames (length sampling only)")
    ap.add_argument("--sampling", choices=[c.value for c in ClipSampling], default=ClipSampling.TRAVERSAL.value,
                    help="traversal (the paper: fixed frame count, uniform traversal scale) or length (legacy)")
    ap.add_argument("--continuous-scale", action="store_true",
                    help="traversal: scale ~ U[min(strides), max(strides)] instead of the stride set")
    ap.add_argument("--height", type=int, default=PrecomputeParams.height)
    ap.add_argument("--width", type=int, default=None, help="must be 2 x height (ERP)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-depth", action="store_true", help="do not write warped depth")
    ap.add_argument("--no-targets", action="store_true", help="do not write ground-truth target frames")
    ap.add_argument("--executor", choices=["local", "ray"], default="local")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--ray-address", default=None, help="Ray cluster address (default: start a local instance)")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON")
    a = ap.parse_args(argv)
    try:
        check_output_dir(a.out)
        if a.width is not None and a.width != 2 * a.height:
            raise InputError(f"--width {a.width} with --height {a.height}: ERP frames must be 2:1")
        strides = tuple(int(s) for s in a.strides.split(",") if s.strip())
        if not strides or min(strides) < 1:
            raise InputError(f"--strides {a.strides}: expected positive integers like 1,2,4")
        if not 1 <= a.min_frames <= a.frames:
            raise InputError(f"--min-frames {a.min_frames} / --frames {a.frames}: need 1 <= min <= frames")
        params = PrecomputeParams(
            clips_per_scene=a.clips_per_scene, strides=strides, frames=a.frames, min_frames=a.min_frames, height=a.height,
            seed=a.seed, write_depth=not a.no_depth, write_targets=not a.no_targets,
            sampling=ClipSampling(a.sampling), continuous_scale=a.continuous_scale,
        )
        summary = precompute(a.dataset, a.out, params, executor=a.executor, workers=a.workers, ray_address=a.ray_address,
                             progress=not a.json)
    except (InputError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(summary, indent=2))
    else:
        print(
            f"clips: {summary['clips']}  rendered: {summary['rendered']}  cached: {summary['cached']}  "
            f"failed: {summary['failed']}  frames/s: {summary['frames_per_s']:.1f}  ({summary['seconds']:.1f} s)"
        )
        for s in summary["failed_scenes"]:
            print(f"failed scene: {s} (see {a.out / FAILURES})", file=sys.stderr)
    return 1 if summary["failed"] else 0
