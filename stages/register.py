"""Poses of the panoramas of a multi-panorama scene (SCENE/panoramas/): SCENE/poses.json validated, or estimated."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from panoworld.framework.stage import Input, StageInputError
from panoworld.framework.stage_cli import stage_main
from panoworld.register.options import RegisterOptions

NAME = "register"
VERSION = "1"
ARTIFACT = "register"
INPUTS = {
    "depth": Input("depth", optional=True, help="depth artifact of the scene (the pipeline's input: a home's cleaned "
                   "panoramas and depths; one panorama is one capture point at the identity)"),
    "poses": Input("file", optional=True, help="with --depth: the scene's poses.json {NAME: 4x4 world_from_cam}"),
    "scene": Input("dir", optional=True, help="instead of --depth: scene directory with panoramas/NAME.png|jpg, "
                   "depths/NAME.npy|exr|png, optional poses.json"),
}


@dataclass(kw_only=True)
class Params(RegisterOptions):
    """RegisterOptions (panoworld/register/solve.py) are this stage's params."""


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    t0 = time.perf_counter()
    if inputs.get("scene") is not None:
        from panoworld.register.artifact import register_scene

        info = register_scene(inputs["scene"], params, out_dir)
    elif inputs.get("depth") is not None:
        from panoworld.io.home import home_depth_dirs, levelled_panoramas
        from panoworld.register.artifact import register_depth_dirs

        info = register_depth_dirs(home_depth_dirs(inputs["depth"]), inputs.get("poses"), params, out_dir,
                                   levelled=levelled_panoramas(inputs["depth"]))
    else:
        raise StageInputError("give --depth DIR (a depth artifact) or --scene DIR (a scene with panoramas/)")
    return {**info, "register_s": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
