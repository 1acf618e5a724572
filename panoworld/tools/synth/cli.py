"""Command line: `synth OUT_DIR --seed N [--preset P] [--frames F] [--rig tripod | --panoramas K]` or `synth DATASET_DIR --seed N --scenes K`."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from panoworld.io.safe_write import check_output_dir
from panoworld.tools.synth.generate import SceneGenerationError, derive_seed, generate_scene
from panoworld.tools.synth.home import (
    DEPTH_KINDS,
    MAX_PANORAMAS,
    generate_home,
    home_params,
    tour_rooms,
    write_home,
)
from panoworld.tools.synth.params import Preset, params_for
from panoworld.tools.synth.rig import RigKind
from panoworld.tools.synth.write import write_scene


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="synth",
        description="Generate procedural indoor scene directories (panorama.png, depth.npy, gt/) with exact ground truth.",
    )
    ap.add_argument("out_dir", type=Path, help="scene directory, or dataset directory when --scenes is given")
    ap.add_argument("--seed", type=int, required=True, help="non-negative integer seed")
    ap.add_argument("--preset", choices=[p.value for p in Preset], default=Preset.DEFAULT.value)
    ap.add_argument("--frames", type=int, default=None, help="frames per track (overrides the preset)")
    ap.add_argument("--rig", choices=[k.value for k in RigKind], default=RigKind.NONE.value,
                    help="a capture rig under the panorama camera (gt/panorama_clean.png keeps the rig-free truth)")
    ap.add_argument("--scenes", type=int, default=None,
                    help="write this many scenes DATASET_DIR/scene_0000 ... with seeds derived from --seed")
    ap.add_argument("--panoramas", type=int, default=None,
                    help="a home of >= 3 rooms captured by this many panoramas (2-32; more rooms beyond 8): panoramas/, "
                    "depths/, gt/poses.json")
    ap.add_argument("--depth", choices=DEPTH_KINDS, default=None,
                    help="with --panoramas: depths/ holds the rendered scene's depth (scene, the default) or each "
                    "capture room's layout alone (layout: walls with the doorways closed, floor, flat ceiling)")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Run the synth CLI; returns a process exit code (0 ok, 1 generation failed, 2 bad arguments)."""
    ap = build_parser()
    args = ap.parse_args(argv)
    if args.seed < 0:
        ap.error(f"--seed {args.seed} but expected a non-negative integer")
    if args.frames is not None and args.frames < 1:
        ap.error(f"--frames {args.frames} but expected >= 1")
    if args.scenes is not None and args.scenes < 1:
        ap.error(f"--scenes {args.scenes} but expected >= 1")
    if args.panoramas is not None and not 2 <= args.panoramas <= MAX_PANORAMAS:
        ap.error(f"--panoramas {args.panoramas} but expected 2..{MAX_PANORAMAS}")
    if args.panoramas is not None and (args.scenes is not None or args.frames is not None or args.rig != "none"):
        ap.error("--panoramas cannot be combined with --scenes, --frames or --rig")
    if args.depth is not None and args.panoramas is None:
        ap.error("--depth needs --panoramas")
    params = params_for(args.preset, frames=args.frames)
    params = replace(params, render=replace(params.render, rig=args.rig))
    try:
        check_output_dir(args.out_dir)
        if args.panoramas is not None:
            if args.out_dir.exists() and (not args.out_dir.is_dir() or any(args.out_dir.iterdir())):
                ap.error(f"{args.out_dir} already exists and is not empty")
            hp = home_params(args.preset, tour_rooms(args.panoramas))
            home = generate_home(args.seed, args.panoramas, args.preset, params=hp)
            write_home(home, args.out_dir, hp, depth=args.depth or "scene")
            print(f"wrote {args.out_dir} (seed {args.seed}, {args.panoramas} panoramas in rooms {home.rooms} of "
                  f"{home.scene.meta['n_rooms']})")
            return 0
        if args.scenes is None:
            if args.out_dir.exists() and (not args.out_dir.is_dir() or any(args.out_dir.iterdir())):
                ap.error(f"{args.out_dir} already exists and is not empty")
            scene = generate_scene(args.seed, args.preset, params=params)
            write_scene(scene, args.out_dir, params)
            print(f"wrote {args.out_dir} (seed {args.seed}, preset {args.preset}, {len(scene.faces)} triangles)")
            return 0
        args.out_dir.mkdir(parents=True, exist_ok=True)
        for k in tqdm(range(args.scenes), desc="scenes"):
            out = args.out_dir / f"scene_{k:04d}"
            # Scene directories appear atomically, so an existing one is complete: resume after it.
            if (out / "gt" / "gt.json").is_file():
                continue
            scene = generate_scene(derive_seed(args.seed, 1, k), args.preset, params=params)
            write_scene(scene, out, params, progress=False)
        print(f"wrote {args.scenes} scenes into {args.out_dir}")
        return 0
    except SceneGenerationError as e:
        print(f"synth: error: {e}", file=sys.stderr)
        return 1
