"""Shared implementation of the toy stages (each toy module only names itself and its inputs)."""

from __future__ import annotations

import hashlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from panoworld.core.errors import InputError
from panoworld.core.params import param
from panoworld.framework.stage import Input
from panoworld.framework.stage_cli import stage_main


@dataclass(kw_only=True)
class Params:
    n: int = param(1, ge=0, le=100)
    """A number written into the output."""
    sleep: float = param(0.0, ge=0)
    """Seconds to sleep after writing a partial file (lets a test kill the stage mid-write)."""
    fail: bool = False
    """Raise an error instead of finishing."""
    refuse: bool = False
    """Refuse the input (InputError: exit code 2) after writing a partial file."""


def make_stage(name: str, inputs: dict[str, Input]) -> dict:
    """Module globals of a toy stage following the stage contract."""

    def run(inp: dict[str, Path | None], params: Params, out_dir: Path) -> dict:
        parts = [name, str(params.n)]
        for _, p in sorted(inp.items()):
            if p is not None:
                parts.append((p / "out.txt").read_text() if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()[:8])
        (out_dir / "partial.txt").write_text("partial")
        if params.sleep:
            print(f"toy {name}: sleeping", flush=True)
            time.sleep(params.sleep)
        if params.refuse:
            raise InputError(f"toy stage {name} refuses its input on purpose; unset {name}.refuse")
        if params.fail:
            raise RuntimeError(f"toy stage {name} failed on purpose")
        (out_dir / "out.txt").write_text("|".join(parts))
        return {"n": params.n}

    return {"NAME": name, "VERSION": "1", "ARTIFACT": "toy", "INPUTS": inputs, "Params": Params, "run": run}


def main_of(module_name: str):
    return lambda argv=None: stage_main(module_name, argv)


def entry(module_name: str) -> None:
    sys.exit(stage_main(module_name))


def use_toy_schemas(monkeypatch) -> None:
    """Validate manifests against the toy schemas (tests/toy/schemas) for the rest of the test."""
    from panoworld.io import manifest as art

    monkeypatch.setenv("PANOWORLD_SCHEMA_PATH", str(Path(__file__).parent / "schemas"))
    art.load_schema.cache_clear()
    art._validator.cache_clear()


def toy_scene(tmp_path: Path) -> Path:
    """A scene directory with a random 16x8 panorama."""
    import numpy as np
    from PIL import Image

    d = tmp_path / "scene"
    d.mkdir()
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (8, 16, 3), dtype=np.uint8)).save(d / "panorama.png")
    return d
