"""Prints precompute throughput (frames/s) for 20 synthetic scenes x 4 clips at 480x960: 1 and 2 local workers, Ray."""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.tools.precompute.run import PrecomputeParams, precompute
from panoworld.tools.synth import generate_scene, write_scene
from panoworld.tools.synth.generate import derive_seed
from panoworld.tools.synth.params import Preset, params_for


def make_dataset(root: Path, scenes: int, frames: int, height: int) -> None:
    """ci-tiny rooms with one track whose frames are rendered at the benchmark's height."""
    base = params_for(Preset.CI_TINY, frames=frames)
    params = replace(base, tracks=replace(base.tracks, n_tracks=1),
                     render=replace(base.render, pano_height=height, frame_height=height))
    for k in range(scenes):
        scene = generate_scene(derive_seed(0, 1, k), Preset.CI_TINY, params=params)
        write_scene(scene, root / f"scene_{k:04d}", params, progress=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--clips", type=int, default=4)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--track-frames", type=int, default=24)
    ap.add_argument("--no-ray", action="store_true")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        t0 = time.perf_counter()
        make_dataset(data, a.scenes, a.track_frames, a.height)
        print(f"dataset: {a.scenes} scenes, {a.track_frames} frames at {a.height}x{2 * a.height} "
              f"({time.perf_counter() - t0:.0f} s to generate)")
        params = PrecomputeParams(clips_per_scene=a.clips, strides=(1, 2), frames=a.track_frames // 2, min_frames=5,
                                  height=a.height)
        runs = [("local", 1), ("local", 2)] + ([] if a.no_ray else [("ray", 2)])
        fps = {}
        for executor, workers in runs:
            out = Path(tmp) / f"out_{executor}_{workers}"
            s = precompute(data, out, params, executor=executor, workers=workers, progress=False)
            assert s["failed"] == 0 and s["rendered"] == a.scenes * a.clips, s
            fps[(executor, workers)] = s["frames_per_s"]
            print(f"{executor:<5} workers={workers}: {s['frames_rendered']} frames in {s['seconds']:.1f} s "
                  f"= {s['frames_per_s']:.1f} frames/s")
            shutil.rmtree(out)
        print(f"speed-up 2 vs 1 local workers: {fps[('local', 2)] / fps[('local', 1)]:.2f}x (target >= 1.7x)")
        if ("ray", 2) in fps:
            print(f"ray vs local at 2 workers: {fps[('ray', 2)] / fps[('local', 2)]:.2f} (target within 20%)")


if __name__ == "__main__":
    sys.exit(main())
