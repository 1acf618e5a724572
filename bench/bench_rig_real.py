"""Capture-rig detection and removal on the shared real panoramas against hand-drawn rig labels.

    python bench/bench_rig_real.py [--split dev|test|all] [--json F] [--save DIR] [--sectors] [--turn SEED] [--rows N]

Runs what the depth stage runs at default settings (no flags): the panorama at the working size, the provided depth
(ZInD layout depth), `clean_depth` with the default rig detector. Per panorama with a tripod (ZInD east, west and the
garage; labels in bench/rig_labels/zind_real.json, drawn by hand on a 90 deg downward view):

- iou: the detected rig mask against the label, solid-angle weighted on the ERP (0 when nothing was found);
- legs: the share of the label's tripod legs (its lines outside its polygons) the detected mask covers;
- fill / seen floor: the mean luminance of the cleaned panorama under the label within CAP_DEG over that of the
  floor the input shows in the cap (1: the fill is lit like the floor under the camera, whatever the ring's light);
- gap before / after: |1 - cap / ring| of the mean luminance (Rec. 601 luma, solid-angle weighted) of the cap within
  CAP_DEG of the nadir and of the floor ring RING_DEG (20-35 deg) around it on the working panorama; the ring keeps
  only pixels on the floor plane by the scene's depth (camera height from the depth stage) and outside the label,
  so walls of a narrow room and the rig itself never stand in for the floor; `ring_floor` its share of the ring;
- seconds: clean_depth up to the rig (metric scale, rig detection and removal; completion is left out) on this machine.

--scenes DIR: single-panorama scenes DIR/<side>_<pano> (panorama + depth, built by `runner.py run`, no flags):
their Gaussians rendered at the capture point (camera 0 = identity, 512 rows), the same gap on the render against
the ring of the render (gap_gaussians; `runner.py run` must have been run on them first).

Controls with no rig (must stay byte-identical: panorama and depth): the Realsee pair (real LiDAR and synthesis) and
the RGB-only samples (colour alone, no depth), less those whose nadir is a capture artefact (ARTEFACTS: the
Stanford 2D-3D-S sample's black hexagon where the capture has no pixels), which must be found as that kind and
removed. Split: east + garage = dev (where the method was tuned), west = test
(held out). --save DIR writes each panorama's nadir before/after with the detected mask's outline. --sectors prints
the floor the input shows (luma medians) per azimuth sector and angle from the nadir: whether the floor under the
camera is darker on every side (a shadow the capture added) or the room's light crosses some sectors. --turn SEED
turns each panorama, its depth and its label by its own random azimuth first (where the seam falls is arbitrary
in a capture); --rows N resizes each panorama and its depth to N rows first (another capture size).
"""

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

from panoworld.core.conventions import erp_pixel_solid_angle

DATA = next((p / "shared" / "data" / "real" for p in REPO.parents if (p / "shared" / "data" / "real").is_dir()),
            REPO.parent / "shared" / "data" / "real")
"""The shared real captures: ../shared/data/real beside the repository (or beside a folder above it)."""
LABELS = REPO / "bench" / "rig_labels" / "zind_real.json"
CAP_DEG = 15.0
RING_DEG = (20.0, 35.0)
SPLIT = {"east": "dev", "garage": "dev", "west": "test"}
ARTEFACTS = {"depthanywhere__sf3d_rgb1.png": "mask"}
"""RGB-only samples whose nadir is a capture artefact, not the room (the kind detection must find): sf3d's black
hexagon, pure black (0, 0, 0) with a jagged edge, is where the Stanford 2D-3D-S capture has no pixels."""


def label_mask(entry: dict, view: dict, H: int, W: int) -> np.ndarray:
    """A label (polygons and thick lines in the pixels of a downward view of fov_deg and size) -> (H, W) bool ERP."""
    from panoworld.depth.rig.face import face_to_erp_mask, nadir_view
    from panoworld.geometry.cube_views import PerspectiveView

    size = int(view["size"])
    m = np.zeros((size, size), np.uint8)
    for p in entry.get("polygons", []):
        cv2.fillPoly(m, [np.round(np.asarray(p, float) * 4).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=2)
    for x0, y0, x1, y1, w in entry.get("lines", []):
        cv2.line(m, (round(x0), round(y0)), (round(x1), round(y1)), 1, max(1, round(w)))
    pv = PerspectiveView(nadir_view(H).cam_from_view, float(view["fov_deg"]), size)
    return face_to_erp_mask(m > 0, pv, H, W)


def from_nadir(H: int, W: int) -> np.ndarray:
    return np.broadcast_to((180.0 - (np.arange(H) + 0.5) / H * 180.0)[:, None], (H, W))


def floor_gap(rgb: np.ndarray, depth: np.ndarray, valid: np.ndarray, floor_m: float | None,
              exclude: np.ndarray, cap_exclude: np.ndarray | None = None) -> tuple[float, float]:
    """(|1 - cap / ring| of the mean luma, the ring's floor share): cap within CAP_DEG of the nadir (less
    cap_exclude), ring RING_DEG on the floor plane by depth (within 5 % of floor_m below the camera) and outside
    exclude."""
    H, W = rgb.shape[:2]
    t = from_nadir(H, W)
    lum = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float64)
    w = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W))
    ring = (t >= RING_DEG[0]) & (t < RING_DEG[1])
    floor = ring & ~exclude
    if floor_m:
        drop = depth * np.cos(np.deg2rad(t))
        floor &= valid & (np.abs(drop - floor_m) < 0.05 * floor_m)
    share = float(w[floor].sum() / w[ring].sum())
    cap = (t < CAP_DEG) if cap_exclude is None else (t < CAP_DEG) & ~cap_exclude
    lc = float((lum * w)[cap].sum() / w[cap].sum())
    lr = float((lum * w)[floor].sum() / max(w[floor].sum(), 1e-12))
    return abs(1.0 - lc / max(lr, 1e-6)), share


def fill_over_seen(before: np.ndarray, after: np.ndarray, label: np.ndarray, around: np.ndarray) -> float:
    """Mean luma (solid-angle weighted) of the cleaned panorama under the label within CAP_DEG over that of the
    floor the input shows in the cap (the cap less around): 1 when the fill is lit like the floor under the camera."""
    H, W = before.shape[:2]
    cap = from_nadir(H, W) < CAP_DEG
    w = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W))

    def mean(img: np.ndarray, m: np.ndarray) -> float:
        return float((cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float64) * w)[m].sum() / max(w[m].sum(), 1e-12))

    return mean(after, cap & label) / max(mean(before, cap & ~around), 1e-6)


SECTOR_EDGES = (3, 6, 9, 12, 15, 18, 21, 24, 27, 30, 35, 40)


def sector_profile(rgb: np.ndarray, depth: np.ndarray, valid: np.ndarray, floor_m: float | None,
                   exclude: np.ndarray, sectors: int = 8) -> list[list[float | None]]:
    """Median luma of the floor the input shows (on the floor plane by depth, outside exclude) per azimuth sector
    (rows) and per band of SECTOR_EDGES degrees from the nadir (columns; None under 20 pixels): a shadow the capture
    adds darkens every sector towards the nadir, the room's light (a sun band) some sectors at every angle."""
    H, W = rgb.shape[:2]
    t = from_nadir(H, W)
    lum = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float64)
    phi = np.broadcast_to((np.arange(W) + 0.5) / W * sectors, (H, W)).astype(int)
    floor = valid & ~exclude
    if floor_m:
        floor &= np.abs(depth * np.cos(np.deg2rad(t)) - floor_m) < 0.05 * floor_m
    out = []
    for k in range(sectors):
        row = []
        for a, b in zip(SECTOR_EDGES[:-1], SECTOR_EDGES[1:]):
            m = floor & (phi == k) & (t >= a) & (t < b)
            row.append(float(np.median(lum[m])) if m.sum() >= 20 else None)
        out.append(row)
    return out


def print_sectors(name: str, prof: list[list[float | None]]) -> None:
    print(f"  {name}: floor luma by azimuth sector (rows) and degrees from the nadir (columns, band starts)")
    print("    deg" + "".join(f"{a:>5d}" for a in SECTOR_EDGES[:-1]))
    for k, row in enumerate(prof):
        print(f"    {k * 360 // len(prof):>3d}" + "".join(f"{v:5.0f}" if v is not None else "    -" for v in row))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    H, W = a.shape
    w = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W))
    return float(w[a & b].sum() / max(w[a | b].sum(), 1e-12))


def coverage(mask: np.ndarray, part: np.ndarray) -> float:
    """Solid-angle share of part (H, W) bool that mask covers (1 when part is empty)."""
    H, W = part.shape
    w = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W))
    return float(w[mask & part].sum() / w[part].sum()) if part.any() else 1.0


def stage_input(pano: Path, depth: Path | None):
    """(rgb at the working size, Job result) as the depth stage makes them at default settings."""
    from panoworld.core import registry as backends
    from panoworld.depth import depth_map as dep
    from panoworld.depth.backends import Job
    from panoworld.io.depth import read_panorama
    from stages.depth import NAME, Params

    params = Params()
    rgb = read_panorama(pano, [])
    H, _ = dep.working_size(rgb.shape[0], params.max_height)
    rgb = dep.resize_panorama(rgb, H)
    inputs = {"panorama": pano, "depth": depth}
    backend = backends.pick(NAME, params.backend, inputs)
    res = backend.impl(Job(rgb=rgb, depth_file=depth, panorama_file=pano, options=backend.options_of(params), notes=[]))
    return rgb, res, params


def clean(rgb: np.ndarray, res, params, source: Path):
    """clean_depth with the default rig backend, as the depth stage calls it, less the completion of poles and
    dropouts (after the rig's removal: the panorama is the same): (Cleaned, seconds)."""
    from panoworld.core import registry as backends
    from panoworld.depth.clean import clean_depth

    rig_backend = backends.get("rig", params.rig_detector).impl
    t0 = time.perf_counter()
    c = clean_depth(rgb, res.depth, res.valid, relative=res.relative, rescale=params.rescale,
                    camera_height=params.camera_height, min_depth_m=params.min_depth_m,
                    detect_rig=lambda *a: rig_backend(*a, params), rig_mask=None,
                    complete_poles=False, complete_dropouts=False, source=source)
    return c, time.perf_counter() - t0


def rig_panoramas() -> list[tuple[str, Path, Path]]:
    out = []
    for side in ("east", "west"):
        for p in sorted((DATA / "zind_home" / side / "panoramas").glob("*.jpg")):
            out.append((f"{side}/{p.stem}", p, DATA / "zind_home" / side / "depths" / f"{p.stem}.npy"))
    g = DATA / "zind_garage"
    if (g / "panorama.jpg").is_file():
        out.append(("garage/panorama", g / "panorama.jpg", g / "layout_depth_m.npy"))
    return out


def save_picture(out: Path, name: str, before: np.ndarray, after: np.ndarray, det_mask, label: np.ndarray) -> None:
    from panoworld.depth.rig.face import nadir_crop

    def outline(img, m, colour):
        if m is None or not m.any():
            return img
        face = nadir_crop(np.repeat(m.astype(np.uint8)[..., None] * 255, 3, 2), 384)[..., 0] > 127
        cnt, _ = cv2.findContours(face.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        return cv2.drawContours(img.copy(), cnt, -1, colour, 1)

    a = outline(nadir_crop(before, 384), label, (0, 255, 0))
    a = outline(a, det_mask, (255, 0, 255))
    b = nadir_crop(after, 384)
    out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out / f"{name.replace('/', '_')}.png"), cv2.cvtColor(np.concatenate([a, b], 1), cv2.COLOR_RGB2BGR))


def vary(rgb: np.ndarray, depth: np.ndarray, rng: np.random.Generator | None, rows: int | None, source: Path
         ) -> tuple[np.ndarray, np.ndarray, int]:
    """A panorama (H, W, 3) and its depth (h, w) resized to `rows` rows (area; the depth by the same factor, nearest)
    and/or turned about gravity by a random azimuth from rng (a whole number of depth columns, so both move exactly)
    -> (panorama, depth, the turn in depth columns). source names the panorama in the error."""
    if rows:
        f = rows / rgb.shape[0]
        rgb = cv2.resize(rgb, (2 * rows, rows), interpolation=cv2.INTER_AREA)
        depth = cv2.resize(depth, (max(2, round(depth.shape[1] * f)), max(1, round(depth.shape[0] * f))),
                           interpolation=cv2.INTER_NEAREST)
    k = int(rng.integers(0, depth.shape[1])) if rng is not None else 0
    if rgb.shape[1] % depth.shape[1]:
        raise SystemExit(f"{source}: width {rgb.shape[1]} is not a multiple of its depth's {depth.shape[1]}")
    return np.roll(rgb, k * rgb.shape[1] // depth.shape[1], axis=1), np.roll(depth, k, axis=1), k


def varied_input(pano: Path, depth: Path, out: Path, rng: np.random.Generator | None, rows: int | None
                 ) -> tuple[Path, Path, float]:
    """A copy of a panorama and its depth under out (PNG and .npy), varied as `vary` does -> (panorama, depth, the
    turn as a fraction of the width: the label turns with it)."""
    from panoworld.io.depth import read_panorama

    rgb, d, k = vary(read_panorama(pano), np.load(depth).astype(np.float32), rng, rows, pano)
    out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out / "panorama.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    np.save(out / "depth.npy", d)
    return out / "panorama.png", out / "depth.npy", k / d.shape[1]


def rig_rows(split: str, save: Path | None, sectors: bool = False, turn_seed: int | None = None,
             rows_px: int | None = None) -> list[dict]:
    """One row per labelled panorama of the split; turn_seed / rows_px: each panorama (and its depth and label) turned
    by its own random azimuth / resized to that many rows first (varied_input)."""
    import tempfile

    doc = json.loads(LABELS.read_text())
    rng = np.random.default_rng(turn_seed) if turn_seed is not None else None
    rows = []
    tmp = tempfile.TemporaryDirectory()
    for name, pano, depth in rig_panoramas():
        part = SPLIT[name.split("/")[0]]
        if split != "all" and part != split:
            continue
        shift = 0.0
        if rng is not None or rows_px:
            pano, depth, shift = varied_input(pano, depth, Path(tmp.name) / name.replace("/", "_"), rng, rows_px)
        rgb, res, params = stage_input(pano, depth)
        c, sec = clean(rgb, res, params, depth)
        H, W = rgb.shape[:2]
        entry = doc["labels"][name]
        label = np.roll(label_mask(entry, doc["view"], H, W), round(shift * W), axis=1)
        legs = np.roll(label_mask({"lines": entry.get("lines", [])}, doc["view"], H, W)
                       & ~label_mask({"polygons": entry.get("polygons", [])}, doc["view"], H, W), round(shift * W), axis=1)
        det = c.rig
        found = bool(det is not None and det.found)
        mask = det.mask if found else np.zeros_like(label)
        floor_m = c.info.get("camera_height_estimated_after")
        gb, share = floor_gap(rgb, res.depth, res.valid, floor_m, label)  # ZInD layout depth: metric as given
        ga, _ = floor_gap(c.rgb, res.depth, res.valid, floor_m, label)
        around = cv2.dilate(label.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
        gs, _ = floor_gap(rgb, res.depth, res.valid, floor_m, label, cap_exclude=around)
        rows.append({"panorama": name, "split": part, "found": found, "kind": det.kind if det else None,
                     "reason": det.reason if det else "", "iou": iou(mask, label),
                     "leg_recall": coverage(mask, legs), "gap_before": gb, "gap_after": ga, "gap_seen": gs,
                     "fill_over_seen": fill_over_seen(rgb, c.rgb, label, around),
                     "ring_floor": share, "seconds": sec, "floor_m": floor_m})
        if sectors:
            rows[-1]["sectors"] = sector_profile(rgb, res.depth, res.valid, floor_m, around)
            print_sectors(name, rows[-1]["sectors"])
        if save is not None:
            save_picture(save, name, rgb, c.rgb, mask, label)
        print(f"  {name}: found={found} iou={rows[-1]['iou']:.3f} gap {gb:.1%} -> {ga:.1%} (seen floor {gs:.1%})  ({sec:.1f} s)", flush=True)
    tmp.cleanup()
    return rows


def gaussian_gaps(rows: list[dict], scenes: Path, height: int = 512) -> None:
    """Adds gap_gaussians to each row whose scene (scenes/<side>_<pano>) holds Gaussians: the gap of their render at
    the capture point (floor ring by the provided depth, outside the label, as on the panorama)."""
    from panoworld.depth.rig.face import nadir_crop
    from panoworld.io.splat_ply import read_gaussians_ply
    from panoworld.render.erp import render_erp

    doc = json.loads(LABELS.read_text())
    paths = {name: (pano, depth) for name, pano, depth in rig_panoramas()}
    for r in rows:
        scene = scenes / r["panorama"].replace("/", "_")
        ply = scene / "artifacts" / "gaussians" / "gaussians.ply"
        if not ply.is_file():
            continue
        out = render_erp(read_gaussians_ply(ply), np.eye(4), height, 2 * height)
        img = np.clip(np.rint(np.asarray(out.rgb, np.float32) * 255), 0, 255).astype(np.uint8)
        depth = np.load(paths[r["panorama"]][1]).astype(np.float32)
        depth = cv2.resize(depth, (2 * height, height), interpolation=cv2.INTER_NEAREST)
        info = json.loads((scene / "artifacts" / "depth" / "manifest.json").read_text()).get("info", {})
        floor_m = info.get("camera_height_estimated_after") or r.get("floor_m")
        label = label_mask(doc["labels"][r["panorama"]], doc["view"], height, 2 * height)
        r["gap_gaussians"], _ = floor_gap(img, depth, np.isfinite(depth) & (depth > 0), floor_m, label)
        cv2.imwrite(str(scene / "nadir_gaussians.png"), cv2.cvtColor(nadir_crop(img, 384), cv2.COLOR_RGB2BGR))
        print(f"  {r['panorama']}: Gaussians at the capture point: gap {r['gap_gaussians']:.1%}", flush=True)


def control_rows() -> list[dict]:
    """The shared captures with no rig: panorama and depth must come out byte-identical (`expect` None); and the
    RGB-only captures of ARTEFACTS, whose artefact must be found as its kind (`expect`) and removed."""
    from panoworld.depth.rig.detect import detect_rig
    from panoworld.depth.rig.remove import remove_rig

    rows = []
    real = DATA / "realsee3d_assets"
    for name, pano, dep_file in (("realsee_real", real / "panoImage_real.jpg", real / "depth_image.png"),
                                 ("realsee_synthesis", real / "panoImage_synthesis.jpg", real / "depth_image_synthesis.png")):
        if not pano.is_file():
            continue
        rgb, res, params = stage_input(pano, dep_file)
        c, sec = clean(rgb, res, params, dep_file)
        found = bool(c.rig is not None and c.rig.found)
        rows.append({"control": name, "expect": None, "found": found, "kind": c.rig.kind if found else None,
                     "reason": c.rig.reason if c.rig else "", "identical": bool(np.array_equal(c.rgb, rgb)),
                     "seconds": sec})
    for pano in sorted((DATA / "rgb_only").glob("*")):
        if pano.suffix.lower() not in (".png", ".jpg", ".jpeg"):
            continue
        from panoworld.depth import depth_map as dep
        from panoworld.io.depth import read_panorama

        rgb = read_panorama(pano, [])
        rgb = dep.resize_panorama(rgb, dep.working_size(rgb.shape[0], 1024)[0])
        t0 = time.perf_counter()
        det = detect_rig(rgb)
        out = remove_rig(rgb, det) if det.found else rgb
        rows.append({"control": pano.name, "expect": ARTEFACTS.get(pano.name), "found": det.found,
                     "kind": det.kind if det.found else None, "reason": det.reason,
                     "identical": bool(np.array_equal(out, rgb)), "seconds": time.perf_counter() - t0})
    return rows


def table(rows: list[dict], controls: list[dict]) -> str:
    lines = ["| panorama | split | found | IoU | legs | gap before | gap after | seen floor gap | fill / seen floor | gap on Gaussians | ring floor | s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        gg = f"{r['gap_gaussians']:.1%}" if "gap_gaussians" in r else "-"
        lines.append(f"| {r['panorama']} | {r['split']} | {'yes' if r['found'] else 'no'} | {r['iou']:.3f} | "
                     f"{r['leg_recall']:.2f} | "
                     f"{r['gap_before']:.1%} | {r['gap_after']:.1%} | {r['gap_seen']:.1%} | {r['fill_over_seen']:.2f} | {gg} | {r['ring_floor']:.2f} | {r['seconds']:.1f} |")
    for part in ("dev", "test"):
        sub = [r for r in rows if r["split"] == part]
        if sub:
            ok = sum(r["iou"] >= 0.7 and r["gap_after"] <= 0.15 for r in sub)
            lines.append(f"| **{part}** ({len(sub)}) | | {sum(r['found'] for r in sub)} | "
                         f"{np.mean([r['iou'] for r in sub]):.3f} (min {min(r['iou'] for r in sub):.3f}) | "
                         f"{np.mean([r['leg_recall'] for r in sub]):.2f} | "
                         f"{np.mean([r['gap_before'] for r in sub]):.1%} | {np.mean([r['gap_after'] for r in sub]):.1%} "
                         f"(max {max(r['gap_after'] for r in sub):.1%}) | {np.mean([r['gap_seen'] for r in sub]):.1%} | | | | {ok}/{len(sub)} meet IoU >= 0.7 and gap <= 15 % |")
    lines += ["", "| control | expected | found | byte-identical | ok | s |", "|---|---|---|---|---|---|"]
    for c in controls:
        ok = (c["found"] and c["kind"] == c["expect"] and not c["identical"]) if c["expect"] else \
            (not c["found"] and c["identical"])
        lines.append(f"| {c['control']} | {c['expect'] or 'no rig, byte-identical'} | {c['kind'] or 'no'} | "
                     f"{'yes' if c['identical'] else 'no'} | {'yes' if ok else 'NO'} | {c['seconds']:.1f} |")
    return "\n".join(lines)


def labelled_parser(doc: str, save_help: str) -> argparse.ArgumentParser:
    """The arguments of a bench over the labelled panoramas: --split, --json F, --save DIR (save_help)."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("--split", choices=("dev", "test", "all"), default="all")
    ap.add_argument("--json", type=Path, default=None, help="write the rows as JSON to this file")
    ap.add_argument("--save", type=Path, default=None, help=save_help)
    return ap


def have_data() -> bool:
    """Whether the shared real panoramas are there (a line on stderr when not)."""
    if (DATA / "zind_home").is_dir():
        return True
    print(f"{DATA / 'zind_home'}: the shared real panoramas are not there; nothing to measure", file=sys.stderr)
    return False


def main(argv: list[str] | None = None) -> int:
    ap = labelled_parser(__doc__, "folder for nadir before/after pictures")
    ap.add_argument("--no-controls", action="store_true")
    ap.add_argument("--sectors", action="store_true",
                    help="also print each panorama's floor luma by azimuth sector and angle from the nadir (seen floor)")
    ap.add_argument("--scenes", type=Path, default=None,
                    help="folder of single-panorama scenes <side>_<pano> built by runner.py run: gap on their Gaussians")
    ap.add_argument("--turn", type=int, default=None, metavar="SEED",
                    help="turn each panorama, its depth and its label by its own random azimuth (this seed) first: "
                         "where the seam falls is arbitrary in a capture")
    ap.add_argument("--rows", type=int, default=None, help="resize each panorama (and its depth) to this many rows first")
    args = ap.parse_args(argv)
    if args.scenes is not None and (args.turn is not None or args.rows):
        ap.error("--scenes measures the scenes as built from the panoramas as given: not with --turn or --rows")
    if not have_data():
        return 2
    rows = rig_rows(args.split, args.save, args.sectors, args.turn, args.rows)
    if args.scenes is not None:
        gaussian_gaps(rows, args.scenes)
    controls = [] if args.no_controls else control_rows()
    print(table(rows, controls))
    if args.json:
        args.json.write_text(json.dumps({"rig": rows, "controls": controls}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
