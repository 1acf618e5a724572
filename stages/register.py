"""Poses of the panoramas of a multi-panorama scene (SCENE/panoramas/): SCENE/poses.json validated, or estimated."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from panoworld.register.options import RegisterOptions
from panoworld.stage import Input, stage_main

NAME = "register"
VERSION = "1"
ARTIFACT = "register"
INPUTS = {"scene": Input("dir", help="scene directory with panoramas/NAME.png|jpg, depths/NAME.npy|exr|png, "
                                    "optional poses.json")}


@dataclass(kw_only=True)
class Params(RegisterOptions):
    """RegisterOptions (panoworld/register/solve.py) are this stage's params."""


def run(inputs: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
    from panoworld.register.artifact import register_scene

    t0 = time.perf_counter()
    info = register_scene(inputs["scene"], params, out_dir)
    return {**info, "register_s": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    return stage_main(__name__, argv)


if __name__ == "__main__":
    sys.exit(main())
