"""Prints where the Gaussians' disoccluded error lies at the roam poses of synthetic scenes already run to `gaussians`
(e.g. kept by `bench_roam.py --out DIR`), and each part's ceiling with the true content in the video's holes.

Per bucket, the pixels the capture point does not see (roam.source_seen) are split by ground-truth surface (floor,
walls, ceiling, object side / top / underside: roam.unseen_parts), by room (the capture point's room or another: the
next room through a doorway) and by geometry (the render's depth within 10 % of the true depth, or not): area (share
of the view), PSNR, share of the view's squared error, the mean render - reference and the mean render / reference
colours (RGB levels).
`--oracle rgb,depth`: the video's hole pixels (conditions mask 0) are replaced by the ground truth (one exact ray
per pixel centre) - `rgb`: colour only, `depth`: depth only, `rgb,depth`: both - and the Gaussians refused from that
video with the scene's poses: what a perfect fill of that kind would give. Tune on VALIDATION seeds (1 2 3) only.

  python bench/bench_disocc.py /tmp/roam/seed_1 --buckets d1 d2 --oracle rgb,depth --oracle rgb --oracle depth
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from panoworld.tools.eval.groundtruth import open_ground_truth
from panoworld.tools.eval.roam import UNSEEN_PARTS, sample_roam_poses, source_seen, unseen_parts

ARTIFACTS = "artifacts"
DEPTH_TOL = 0.10
"""A rendered pixel's geometry is right when its depth is within this fraction of the true depth."""


def oracle_video(scene: Path, kinds: set[str], out: Path) -> Path:
    """A copy of the scene's video artifact whose hole pixels hold the ground truth's colour and/or depth."""
    from panoworld.core.conventions import depth_to_mm, erp_dirs
    from panoworld.io.conditions import load_conditions
    from panoworld.io.png import decode_png, encode_png
    from panoworld.io.video import read_video_doc

    src = scene / ARTIFACTS / "video"
    shutil.copytree(src, out, ignore=shutil.ignore_patterns("*.mcap", "*.mp4", "upscaled"))
    gt = open_ground_truth(scene)
    cond = load_conditions(scene / ARTIFACTS / "conditions")
    doc = read_video_doc(out)
    for k in range(doc.num_frames):
        hole = ~np.asarray(cond.mask[k], bool)
        if not hole.any():
            continue
        H, W = hole.shape
        pose = gt.world_from_canonical @ np.asarray(doc.poses[k], np.float64)
        dirs = erp_dirs(H, W, np.float64)[hole][:, None]  # (N, 1, 3): one column for SynthScene._shade
        hits = gt.scene.raycaster.cast(pose[:3, 3][None], dirs.reshape(-1, 3) @ pose[:3, :3].T)
        if "rgb" in kinds:
            from panoworld.tools.synth.appearance import srgb_uint8

            lin = gt.scene._shade(pose, hits.distance[:, None], hits.face[:, None], dirs)
            rgb = decode_png(doc.rgb[k].read_bytes())
            rgb[hole] = srgb_uint8(lin)[:, 0]
            doc.rgb[k].write_bytes(encode_png(rgb))
        if "depth" in kinds and doc.depth[k] is not None:
            import cv2

            mm = cv2.imread(str(doc.depth[k]), cv2.IMREAD_UNCHANGED)
            mm[hole] = depth_to_mm(hits.distance[None].astype(np.float32))[0]
            doc.depth[k].write_bytes(encode_png(mm))
    return out


def oracle_poses(scene: Path, video: Path, out: Path) -> Path:
    """A copy of the scene's poses artifact whose depth maps are the (oracle) video's: the Gaussians stage fuses the
    poses artifact's depth, not the video's."""
    from panoworld.io.video import DEPTH_SCALE, read_video_doc
    from panoworld.poses.estimate import load_poses

    shutil.copytree(scene / ARTIFACTS / "poses", out, ignore=shutil.ignore_patterns("*.mcap"))
    vdoc = read_video_doc(video)
    if abs(float(vdoc.depth_scale) - DEPTH_SCALE) > 1e-12:
        raise SystemExit(f"{video}: depth scale differs from the poses artifact's; cannot put the oracle depth in")
    for k, path in enumerate(load_poses(out).depth or []):
        if vdoc.depth[k] is not None:
            shutil.copyfile(vdoc.depth[k], path)
    return out


def fuse(scene: Path, video: Path, out: Path, poses: Path | None = None) -> tuple[Path, float]:
    from panoworld.framework.stage_params import params_from_dict
    from stages.gaussians import Params, run

    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    run({"video": video, "poses": poses or scene / ARTIFACTS / "poses"},
        params_from_dict(Params, {"eval_views": 0}, "gaussians"), out)
    return out / "gaussians.ply", time.perf_counter() - t0


PART_BGR = np.array([[60, 160, 60], [200, 120, 40], [40, 200, 220], [40, 40, 230], [200, 60, 200], [120, 120, 120]],
                    np.uint8)
"""--png: colour of each UNSEEN_PARTS class (BGR): floor green, walls blue, ceiling yellow, object side red, top
magenta, underside grey."""


def save_png(path: Path, img: np.ndarray, ref: np.ndarray, seen: np.ndarray, part: np.ndarray,
             depth_ok: np.ndarray) -> None:
    """render | reference over unseen parts (depth wrong dimmed) | squared error (unseen only, 0..64^2)."""
    import cv2

    parts = np.zeros_like(img)
    unseen = ~seen & (part >= 0)
    parts[unseen] = PART_BGR[part[unseen]][:, ::-1]
    parts[unseen & ~depth_ok] //= 2
    err = np.sqrt(((img.astype(np.float64) - ref) ** 2).mean(-1))
    heat = cv2.applyColorMap(np.clip(err * 4, 0, 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1]
    heat[seen] //= 4
    grid = np.concatenate([np.concatenate([img, ref], 1), np.concatenate([parts, heat], 1)], 0)
    cv2.imwrite(str(path), np.ascontiguousarray(grid[..., ::-1]))


def pixel_rooms(gt, pose: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) int of the ground-truth surface's room at each pixel centre of an ERP view at canonical pose (-1: none)."""
    hits = gt.scene.raycaster.render_erp(gt.world_from_canonical @ np.asarray(pose, np.float64), height, width)
    face = hits.face.reshape(-1)
    room = np.array([n.room for n in gt.scene.nodes])
    return np.where(face >= 0, room[gt.scene.face_node[np.maximum(face, 0)]], -1).reshape(height, width)


def capture_room(gt) -> int:
    """The room of the floor under the capture point (the source view's bottom row)."""
    r = pixel_rooms(gt, np.eye(4), 16, 32)[-1]
    vals = r[r >= 0]
    return int(np.bincount(vals).argmax()) if len(vals) else -1


def diagnose(scene: Path, ply: Path, views: int, height: int, buckets: list[str], cache: dict,
             png: Path | None = None) -> dict:
    """Per bucket: PSNR of the view, of its seen and unseen parts, and per unseen part (surface class, geometry)."""
    from panoworld.geometry.navmesh import load_navmesh
    from panoworld.io.splat_ply import read_gaussians_ply
    from panoworld.render.erp import render_erp

    g = read_gaussians_ply(ply)
    gt = open_ground_truth(scene)
    roam = sample_roam_poses(load_navmesh(scene / ARTIFACTS / "navmesh"), views, seed=0)
    W = 2 * height
    home = capture_room(gt)
    rows = {}
    for key in buckets:
        acc: dict[str, list] = {}
        for k, pose in enumerate(roam.poses.get(key, [])):
            if (key, k) not in cache:
                ref, ref_d = gt.render(pose, height, W)
                cache[key, k] = (ref, ref_d, source_seen(gt, pose, height, W), unseen_parts(gt, pose, height, W),
                                 pixel_rooms(gt, pose, height, W))
            ref, ref_d, seen, part, room = cache[key, k]
            r = render_erp(g, pose, height, W)
            img = (r.rgb.clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)
            diff = img.astype(np.float64) - ref
            err = (diff**2).mean(-1)
            depth_ok = (r.alpha.numpy() > 0.5) & (np.abs(r.depth.numpy() / np.maximum(r.alpha.numpy(), 1e-6) - ref_d)
                                                   <= DEPTH_TOL * ref_d)
            if png is not None:
                png.mkdir(parents=True, exist_ok=True)
                save_png(png / f"{key}_{k}.png", img, ref, seen, part, depth_ok)
            groups = {"all": np.ones_like(seen), "seen": seen, "unseen": ~seen,
                      "unseen, depth right": ~seen & depth_ok, "unseen, depth wrong": ~seen & ~depth_ok}
            groups.update({f"unseen {name}": ~seen & (part == i) for i, name in enumerate(UNSEEN_PARTS)})
            for where, in_room in (("this room", room == home), ("next room", (room >= 0) & (room != home))):
                groups[f"unseen, {where}"] = ~seen & in_room
                groups.update({f"unseen, {where}: {name}": ~seen & in_room & (part == i)
                               for i, name in enumerate(UNSEEN_PARTS)})
            for name, m in groups.items():
                acc.setdefault(name, []).append((float(err[m].sum()), int(m.sum()), err.size, float(err.sum()),
                                                 diff[m].sum(0), ref[m].sum(0)))
        rows[key] = {}
        for name, vals in acc.items():
            se, n, npx, tot, dsum, rsum = (sum(v[i] for v in vals) for i in range(6))
            bias = dsum / max(n, 1)  # mean render - reference per channel (levels)
            flat = se - n * float((bias**2).mean())  # the same pixels with that constant offset removed
            rows[key][name] = {"area": n / npx, "error_share": se / max(tot, 1e-12),
                               "psnr": 10 * np.log10(255.0**2 / (se / n)) if n and se > 0 else None,
                               "bias": float(bias.mean()),
                               "render_rgb": [float(x) for x in (rsum + dsum) / max(n, 1)],
                               "ref_rgb": [float(x) for x in rsum / max(n, 1)],
                               "psnr_unbiased": 10 * np.log10(255.0**2 / (flat / n)) if n and flat > 0 else None}
    return rows


def print_rows(title: str, rows: dict) -> None:
    print(f"\n{title}")
    print("| bucket | part | area % | PSNR dB | error share % | render - ref (levels) | PSNR, offset removed | "
          "render / ref RGB |\n|---|---|---|---|---|---|---|---|")
    for key, parts in rows.items():
        for name, r in parts.items():
            if r["area"] < 1e-4 and name not in ("all", "seen", "unseen"):
                continue
            p = "n/a" if r["psnr"] is None else f"{r['psnr']:.2f}"
            pu = "n/a" if r["psnr_unbiased"] is None else f"{r['psnr_unbiased']:.2f}"
            print(f"| {key} | {name} | {100 * r['area']:.2f} | {p} | {100 * r['error_share']:.1f} | {r['bias']:+.1f} | "
                  f"{pu} | {'/'.join(f'{x:.0f}' for x in r['render_rgb'])} vs {'/'.join(f'{x:.0f}' for x in r['ref_rgb'])} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", type=Path, nargs="+")
    ap.add_argument("--buckets", nargs="*", default=["d1", "d2"])
    ap.add_argument("--views", type=int, default=2, help="roam views per bucket (seed 0, as bench_gs_variants)")
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--oracle", action="append", default=[], help="rgb | depth | rgb,depth (repeatable)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--png", type=Path, help="write render | reference / unseen parts | unseen error per view here")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    out = {}
    with tempfile.TemporaryDirectory(prefix="disocc-") as tmp:
        for scene in a.scenes:
            cache: dict = {}
            variants = ["artifact", *a.oracle]
            for vi, variant in enumerate(variants):
                fuse_s = 0.0
                ply = scene / ARTIFACTS / "gaussians" / "gaussians.ply"
                if variant != "artifact":
                    kinds = set(variant.split(","))
                    if not kinds <= {"rgb", "depth"}:
                        raise SystemExit(f"--oracle {variant}: expected rgb, depth or rgb,depth")
                    video = oracle_video(scene, kinds, Path(tmp) / f"{scene.name}_{vi}" / "video")
                    poses = oracle_poses(scene, video, Path(tmp) / f"{scene.name}_{vi}" / "poses") \
                        if "depth" in kinds else None
                    ply, fuse_s = fuse(scene, video, Path(tmp) / f"{scene.name}_{vi}" / "gaussians", poses)
                rows = diagnose(scene, ply, a.views, a.height, a.buckets, cache,
                                a.png / scene.name / variant.replace(",", "_") if a.png else None)
                title = f"{scene.name}: {'artifact' if variant == 'artifact' else 'oracle ' + variant} (fuse {fuse_s:.0f} s)"
                print_rows(title, rows)
                out[f"{scene.name} {variant}"] = rows
                sys.stdout.flush()
    if a.json:
        a.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
