"""Benchmark of the synthetic scene generator: scene generation time and seconds per rendered ERP frame."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from panoworld.tools.synth import Preset, generate_scene, params_for


def bench(preset: Preset, seed: int, n_frames: int, supersample: int) -> dict:
    """Generate one scene of preset and render n_frames of track 0 at the preset's frame height."""
    t0 = time.perf_counter()
    scene = generate_scene(seed, preset)
    t_gen = time.perf_counter() - t0
    height = params_for(preset).render.frame_height
    track = scene.tracks[0].world_from_cam
    scene.render(track[0], height, 2 * height)  # builds the BVH
    times, cpu = [], []
    for i in np.linspace(0, len(track) - 1, n_frames).astype(int):
        t0, c0 = time.perf_counter(), time.process_time()
        scene.render(track[i], height, 2 * height, supersample=supersample)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {"preset": str(preset), "resolution": f"{height}x{2 * height}", "supersample": supersample,
            "triangles": len(scene.faces), "lights": len(scene.lights), "generate_s": t_gen,
            "s_per_frame": float(np.median(times)), "cpu_s_per_frame": float(np.median(cpu))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=5, help="frames rendered per configuration")
    args = ap.parse_args()
    for preset, ss in ((Preset.CI_TINY, 1), (Preset.DEFAULT, 1), (Preset.DEFAULT, 2)):
        r = bench(preset, args.seed, args.frames, ss)
        print(f"{r['preset']:>8} {r['resolution']:>9} ss={r['supersample']}: {r['s_per_frame']:.3f} s/frame "
              f"(CPU {r['cpu_s_per_frame']:.3f} s) "
              f"(generate {r['generate_s']:.2f} s, {r['triangles']} triangles, {r['lights']} lights)")


if __name__ == "__main__":
    main()
