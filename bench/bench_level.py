"""Levelling a panorama taken off level: gravity from its vertical lines (geometry/verticals.py) and the depth stage's
decision (depth/level.py), on real captures and on synthetic panoramas tilted by known rotations.

    python bench/bench_level.py [--real DIR] [--tilts 2 5 20 30] [--json F]

Real (DIR, default ../shared/data/real): every panorama found (ZInD homes' panoramas/ with depths/, the ZInD garage,
the Realsee pair, the RGB-only samples): the tilt its lines read, their count and share, the tilt its depth's floor
shows (where it has depth) and what the depth stage decides. Synthetic: the panoramas of a synthetic home (ci-tiny,
seed 7, 3 panoramas at 384 rows) with their layout depth, each tilted by every --tilts angle about a random
horizontal axis: the error of the gravity read from the lines, of the depth stage's levelling, and whether a level
depth under the tilted photo is refused."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2
import numpy as np

from panoworld.depth.level import level_panorama
from panoworld.geometry.level import angle_deg, floor_down, levelled
from panoworld.geometry.verticals import gravity_from_image
from panoworld.io.depth import read_panorama

UP = np.array([0.0, 1.0, 0.0])
DATA = next((p / "shared" / "data" / "real" for p in REPO.parents if (p / "shared" / "data" / "real").is_dir()),
            REPO.parent / "shared" / "data" / "real")
"""The shared real captures: ../shared/data/real beside the repository (or beside a folder above it)."""


def real_captures(root: Path) -> list[tuple[str, Path, Path | None]]:
    """(label, panorama, depth .npy or None) of the shared real captures under root."""
    out = []
    for home in sorted(root.glob("*/*/panoramas")):
        for p in sorted(home.glob("*.jpg")) + sorted(home.glob("*.png")):
            d = home.parent / "depths" / f"{p.stem}.npy"
            out.append((f"{home.parent.parent.name}/{home.parent.name}/{p.stem}", p, d if d.is_file() else None))
    garage = root / "zind_garage"
    if (garage / "panorama.jpg").is_file():
        out.append(("zind_garage", garage / "panorama.jpg", garage / "layout_depth_m.npy"))
    rs = root / "realsee3d_assets"
    for kind, depth in (("real", "depth_real_raw_units_float32.npy"), ("synthesis", "depth_synthetic_raw_units_float32.npy")):
        if (rs / f"panoImage_{kind}.jpg").is_file():
            out.append((f"realsee/{kind}", rs / f"panoImage_{kind}.jpg", rs / depth))
    for p in sorted((root / "rgb_only").glob("*.png")) + sorted((root / "rgb_only").glob("*.jpg")):
        out.append((f"rgb_only/{p.stem}", p, None))
    return out


def tilt_from_level(deg: float, azimuth: float) -> np.ndarray:
    """(3, 3) a camera turned by deg about the horizontal axis at azimuth."""
    return cv2.Rodrigues(np.array([np.sin(azimuth), 0.0, np.cos(azimuth)]) * np.radians(deg))[0]


def real_rows(root: Path) -> list[dict]:
    rows = []
    for label, pano, depth_file in real_captures(root):
        rgb = read_panorama(pano)
        t0 = time.perf_counter()
        g = gravity_from_image(rgb)
        row = {"panorama": label, "rows": rgb.shape[0], "image_tilt_deg": None if g is None else round(g.tilt_deg, 3),
               "verticals": None if g is None else g.verticals, "share": None if g is None else round(g.share, 3),
               "s": round(time.perf_counter() - t0, 3)}
        if depth_file is not None:
            depth = np.load(depth_file).astype(np.float32)
            depth = cv2.resize(depth, rgb.shape[1::-1], interpolation=cv2.INTER_NEAREST)
            valid = np.isfinite(depth) & (depth > 0)
            f = floor_down(np.where(valid, depth, 0.0).astype(np.float32))
            row["floor_tilt_deg"] = None if f is None else round(angle_deg(f, UP), 3)
            lev = level_panorama(rgb, depth, valid)
            row["levelled_deg"] = None if lev.level_from_cam is None else lev.info["tilt_deg"]
        rows.append(row)
    return rows


def synthetic_rows(tilts: list[float], seed: int = 0) -> list[dict]:
    from dataclasses import replace

    from panoworld.tools.synth.home import floor_plan, generate_home, home_params, layout_depth

    params = home_params("ci-tiny")
    params = replace(params, render=replace(params.render, pano_height=384))
    home = generate_home(7, 3, "ci-tiny", params=params)
    plan = floor_plan(home.scene)
    rng = np.random.default_rng(seed)
    rows = []
    for k, (pose, room) in enumerate(zip(home.world_from_cam, home.rooms)):
        rgb = home.scene.render(pose, 384, 768)[0]
        depth = layout_depth(plan, room, pose, 384, 768).astype(np.float32)
        for deg in [0.0, *tilts]:
            X = tilt_from_level(deg, rng.uniform(0, 2 * np.pi))
            trgb, tdepth = levelled(rgb, X), levelled(depth, X, nearest=True)
            g = gravity_from_image(trgb)
            lev = level_panorama(trgb, tdepth, tdepth > 0)
            photo_only = level_panorama(trgb, depth, depth > 0) if deg else None
            R = lev.level_from_cam
            rows.append({"panorama": k, "tilt_deg": deg,
                         "gravity_err_deg": None if g is None else round(angle_deg(g.down_cam, X @ UP), 3),
                         "levelled_err_deg": None if R is None else round(angle_deg(R.T @ UP, X @ UP), 3),
                         "levelled": R is not None,
                         "photo_over_level_depth_levelled": None if photo_only is None else
                         photo_only.level_from_cam is not None})
    return rows


def fmt(v) -> str:
    return "-" if v is None else str(v)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--real", type=Path, default=DATA)
    ap.add_argument("--tilts", type=float, nargs="+", default=[2.0, 5.0, 20.0, 30.0])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    real = real_rows(args.real) if args.real.is_dir() else []
    print("| panorama | rows | lines read ° | verticals | share | depth floor ° | depth stage levels ° | s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in real:
        print(f"| {r['panorama']} | {r['rows']} | {fmt(r['image_tilt_deg'])} | {fmt(r['verticals'])} | {fmt(r['share'])} | "
              f"{fmt(r.get('floor_tilt_deg'))} | {fmt(r.get('levelled_deg'))} | {r['s']} |")
    synth = synthetic_rows(args.tilts)
    print("\n| synthetic panorama | tilt ° | gravity error ° | levelled | levelling error ° | photo over level depth levelled |")
    print("|---|---|---|---|---|---|")
    for r in synth:
        print(f"| {r['panorama']} | {r['tilt_deg']} | {fmt(r['gravity_err_deg'])} | {r['levelled']} | "
              f"{fmt(r['levelled_err_deg'])} | {fmt(r['photo_over_level_depth_levelled'])} |")
    if args.json:
        args.json.write_text(json.dumps({"real": real, "synthetic": synth}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
