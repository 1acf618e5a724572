"""`runner.py split HOME`: each group of panoramas its registration left unplaced becomes a home (or scene) of its own."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

from panoworld.core.errors import InputError, PanoWorldError
from panoworld.io.manifest import ARTIFACTS_DIRNAME, SCENE_CONFIG
from panoworld.register.artifact import read_registration, unplaced_groups
from panoworld.register.inputs import (
    DEPTHS_DIR,
    PANORAMAS_DIR,
    REGISTRATION_JSON,
    RIG_MASKS_DIR,
    MultiScene,
    check_home,
    is_multi_scene,
)

REGISTER_DIR = Path(ARTIFACTS_DIRNAME) / "register"


def home_groups(scene: Path, names: list[str]) -> list[list[str]]:
    """The groups of panoramas (each sorted, the groups by their first name) that the register artifact of the home
    at scene, whose panoramas are names, left unplaced (register.artifact.unplaced_groups). InputError when the home
    has no register artifact or one of other panoramas (registered before the home changed)."""
    run = f"run `python runner.py run {scene} --until register` first"
    try:
        _, reg = read_registration(scene / REGISTER_DIR)
    except (OSError, ValueError):
        reg = None
    if not isinstance(reg, dict) or not isinstance(reg.get("panoramas"), dict):
        raise InputError(f"{scene / REGISTER_DIR / REGISTRATION_JSON}: no registration of this home; {run}")
    if sorted(reg["panoramas"]) != names:
        raise InputError(f"{scene / REGISTER_DIR / REGISTRATION_JSON}: registered other panoramas than "
                         f"{scene / PANORAMAS_DIR} holds now; {run}")
    return sorted(unplaced_groups(reg["panoramas"]))


def _link(src: Path, dst: Path) -> None:
    """dst as a hard link to src where the file system allows it, else a copy."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def write_group(home: MultiScene, group: list[str], out: Path, config: Path | None = None) -> None:
    """The group's panoramas, depths and rig masks as a home at out (two or more panoramas: panoramas/, depths/,
    rig_masks/) or as one panorama's scene (panorama.EXT, depth.EXT, rig_mask.png), with config (the home's
    scene.yaml: its preset and params) where given; files hard-linked where possible, written beside out and renamed to
    it when complete. poses.json is not carried: no panorama of an unplaced group has a given pose."""
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    tmp.mkdir(parents=True)
    try:
        if config is not None:
            _link(config, tmp / SCENE_CONFIG)
        for n in group:
            files = [(home.panoramas[n], PANORAMAS_DIR, "panorama"), (home.depths.get(n), DEPTHS_DIR, "depth"),
                     (home.rig_masks.get(n), RIG_MASKS_DIR, "rig_mask")]
            for src, folder, single in files:
                if src is not None:
                    _link(src, tmp / folder / src.name if len(group) > 1 else tmp / f"{single}{src.suffix.lower()}")
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python runner.py split",
        description="Each group of a home's panoramas that registration left unplaced (joined to each other but to no "
                    "registered panorama, docs/multi.md) becomes a home of its own, HOME-group2, HOME-group3, ... beside "
                    "HOME (a group of one panorama: a one-panorama scene) with HOME's scene.yaml, so `runner.py run` builds "
                    "it as HOME's settings say. The files are hard-linked where the file system allows (else copied); HOME is not changed. A pose in "
                    "HOME/poses.json for one panorama of a group places it in HOME instead.")
    ap.add_argument("home", type=Path, help="a home (panoramas/) whose register stage has run")
    ap.add_argument("--out", type=Path, help="directory for the new homes (default: HOME's parent)")
    args = ap.parse_args(argv)
    try:
        home = args.home.resolve()
        if not is_multi_scene(home):
            raise InputError(f"{args.home}: not a home (no {PANORAMAS_DIR}/); split applies to a home of several "
                             "panoramas (docs/multi.md)")
        files = check_home(home)
        groups = home_groups(home, files.names)
        out_dir = (args.out or home.parent).resolve()
        targets = [out_dir / f"{home.name}-group{k}" for k in range(2, len(groups) + 2)]
        for t in targets:
            if t.exists():
                raise InputError(f"{t}: already exists; remove it or give --out DIR")
        config = home / SCENE_CONFIG if (home / SCENE_CONFIG).is_file() else None
        for group, t in zip(groups, targets):
            write_group(files, group, t, config)
    except PanoWorldError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code
    if not groups:
        print(f"{args.home}: every panorama is registered; nothing to split")
        return 0
    rows = [("group", "panoramas", "directory", "build it with")]
    rows += [(str(k), ", ".join(g), str(t), f"python runner.py run {t}") for k, (g, t) in enumerate(zip(groups, targets), 2)]
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
    return 0
