"""Prints what caps the SEEN part of roam views (surfaces the capture point saw): per view and per kind of pixel, the
PSNR of an ORACLE (the generator's true geometry textured by projecting the source panorama, at the resolution the
pipeline was given, from the capture point; anti-aliased like the reference), of the scene's Gaussians, of its source
per-pixel Gaussians alone, and of the video frame nearest the roam pose (true geometry textured from that frame at
its planned pose), on scenes already run to `gaussians` (e.g. kept by `bench_roam.py --out DIR`).

Seen pixels are split by kind (first match wins): depth edges of the view (within 1 px of a > 5 % log-depth step),
floor / ceiling near the poles (the capture point's ray at |lat| > 60 deg), surfaces seen obliquely from the capture
point (|cos| < 0.5 between its ray and the face normal), textured (reference luma gradient > 4 levels / px) and flat.
Development diagnosis only (it reads the generator's truth): VALIDATION seeds, never the test seeds of bench_roam.

  python bench/bench_seen.py /tmp/roam/seed_6 --buckets d1 d2 --png /tmp/seen
  python bench/bench_seen.py SCENE --ply OTHER/gaussians.ply --json F
  python bench/bench_seen.py SCENE --variant fit_iters=10,fit_height=512 --variant source_scale=1.9,fit_iters=10

--variant adds the source per-pixel Gaussians built as bench_poles.py builds them (keys source_height, source_scale,
thin_poles, fit_iters, fit_height: cheap, no voxel fusion; the voxels barely touch the seen part).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np

ARTIFACTS = "artifacts"
KINDS = ("edge", "pole", "oblique", "textured", "flat")
"""Kinds of seen pixels, in the order they are assigned (a pixel gets the first that applies)."""
EDGE_LOG_STEP = 0.05
POLE_LAT_DEG = 60.0
OBLIQUE_COS = 0.5
TEXTURE_GRAD = 4.0


def to_linear(rgb: np.ndarray) -> np.ndarray:
    """uint8 sRGB-like (gamma 2.2, the generator's) -> linear float32."""
    return (rgb.astype(np.float32) / 255.0) ** 2.2


def to_srgb(linear: np.ndarray) -> np.ndarray:
    from panoworld.tools.synth.appearance import srgb_uint8

    return srgb_uint8(linear)


def surface_points(gt, pose: np.ndarray, height: int, width: int):
    """Canonical points (H W, 3) and world-frame face index (H W,) of an ERP view's pixel-centre rays (inf / -1 where
    nothing is hit)."""
    from panoworld.core.conventions import erp_dirs

    pose = np.asarray(pose, np.float64)
    hits = gt.scene.raycaster.render_erp(gt.world_from_canonical @ pose, height, width)
    dist = np.asarray(hits.distance, np.float64).reshape(-1)
    dirs = erp_dirs(height, width, np.float64).reshape(-1, 3) @ pose[:3, :3].T
    return pose[:3, 3] + dirs * dist[:, None], np.asarray(hits.face).reshape(-1)


def textured_view(gt, pose: np.ndarray, height: int, width: int, image: np.ndarray, image_pose: np.ndarray,
                  supersample: int) -> np.ndarray:
    """(H, W, 3) uint8: the true surface of an ERP view at canonical `pose`, each of s x s sub-rays per pixel coloured
    by projecting its point into the ERP `image` (uint8) taken at canonical `image_pose` (bilinear), averaged in
    linear light (as the reference is). Occlusion is ignored: a point hidden from image_pose takes its occluder's
    colour, which is what a depth-perfect reprojection of that image gives."""
    import cv2

    from panoworld.core.conventions import erp_pixel_from_dir

    s = supersample
    pts, face = surface_points(gt, pose, s * height, s * width)
    ip = np.asarray(image_pose, np.float64)
    local = (np.where(face[:, None] >= 0, pts, 1.0) - ip[:3, 3]) @ ip[:3, :3]
    h, w = image.shape[:2]
    u, v = erp_pixel_from_dir(local, h, w)
    pad = 2
    src = cv2.copyMakeBorder(to_linear(image), pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    src[:, :pad] = src[:, w:w + pad]  # wrap longitude
    src[:, w + pad:] = src[:, pad:2 * pad]
    mx = (u - 0.5 + pad).astype(np.float32).reshape(s * height, s * width)
    my = (v - 0.5 + pad).astype(np.float32).reshape(s * height, s * width)
    lin = cv2.remap(src, mx, my, cv2.INTER_LINEAR)
    lin[(face < 0).reshape(s * height, s * width)] = 0.0
    if s > 1:
        lin = cv2.resize(lin, (width, height), interpolation=cv2.INTER_AREA)
    return to_srgb(lin)


def pixel_kinds(gt, pose: np.ndarray, ref: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(H, W) int8 index into KINDS of each pixel of a view (see the module docstring)."""
    import cv2

    H, W = depth.shape
    pts, face = surface_points(gt, pose, H, W)
    logd = np.log(np.clip(np.where(np.isfinite(depth), depth, 1e3), 1e-3, None)).astype(np.float32)
    step = np.maximum(np.abs(np.diff(logd, axis=0, append=logd[-1:])), np.abs(np.diff(logd, axis=1, append=logd[:, -1:])))
    edge = cv2.dilate((step > EDGE_LOG_STEP).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    ray = pts / np.maximum(np.linalg.norm(pts, axis=1, keepdims=True), 1e-9)
    pole = (np.degrees(np.arcsin(np.clip(np.abs(ray[:, 1]), 0, 1))) > POLE_LAT_DEG).reshape(H, W)
    normal = gt.scene.face_normals[np.maximum(face, 0)] @ gt.world_from_canonical[:3, :3]  # canonical
    cos = np.abs((normal * ray).sum(1)).reshape(H, W)
    oblique = (cos < OBLIQUE_COS) & (face >= 0).reshape(H, W)
    luma = cv2.cvtColor(ref, cv2.COLOR_RGB2GRAY).astype(np.float32)
    grad = np.hypot(cv2.Sobel(luma, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(luma, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    textured = cv2.GaussianBlur(grad, (5, 5), 0) > TEXTURE_GRAD
    out = np.full((H, W), len(KINDS) - 1, np.int8)
    for k, m in reversed(list(enumerate((edge, pole, oblique, textured)))):
        out[m] = k
    return out


def nearest_frame(scene: Path, pose: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """(index, uint8 image, planned canonical pose) of the video frame whose planned centre is nearest `pose`'s."""
    from panoworld.io.video import load_frames, read_video_doc

    traj = json.loads((scene / ARTIFACTS / "trajectory" / "trajectory.json").read_text())
    poses = np.asarray(traj["poses"], np.float64)
    i = int(np.argmin(np.linalg.norm(poses[:, :3, 3] - np.asarray(pose)[:3, 3], axis=1)))
    frame = read_video_doc(scene / ARTIFACTS / "video").rgb[i]
    return i, load_frames([frame])[0], poses[i]


def scores(images: dict[str, np.ndarray], ref: np.ndarray, seen: np.ndarray, kinds: np.ndarray) -> dict:
    """Per image: seen-part PSNR, and per kind its PSNR and share of the seen part's squared error."""
    from panoworld.render.metrics import psnr

    out: dict = {"share": {k: float((seen & (kinds == i)).sum() / max(seen.sum(), 1)) for i, k in enumerate(KINDS)}}
    for name, img in images.items():
        err2 = ((img.astype(np.float64) - ref.astype(np.float64)) ** 2).sum(-1)
        row = {"seen": psnr(img, ref, seen)}
        total = max(err2[seen].sum(), 1e-12)
        for i, k in enumerate(KINDS):
            m = seen & (kinds == i)
            row[k] = psnr(img, ref, m) if m.mean() >= 1e-3 else None
            row[f"{k}_err"] = float(err2[m].sum() / total)
        out[name] = row
    return out


def save_png(path: Path, ref: np.ndarray, images: dict[str, np.ndarray], seen: np.ndarray, kinds: np.ndarray) -> None:
    """Reference and each image (top), their error x4 with unseen pixels blue (bottom), and the kinds map."""
    import cv2

    palette = np.array([[255, 0, 0], [0, 160, 255], [255, 200, 0], [0, 200, 0], [90, 90, 90]], np.uint8)
    tiles, errs = [ref], [palette[kinds]]
    for img in images.values():
        e = np.clip(np.abs(img.astype(np.int16) - ref.astype(np.int16)).max(-1) * 4, 0, 255).astype(np.uint8)
        e = np.repeat(e[..., None], 3, -1)
        e[~seen] = (0, 0, 128)
        tiles.append(img)
        errs.append(e)
    grid = np.concatenate([np.concatenate(tiles, 1), np.concatenate(errs, 1)], 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.ascontiguousarray(grid[..., ::-1]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", type=Path, nargs="+")
    ap.add_argument("--buckets", nargs="*", default=["d0", "d1", "d2"])
    ap.add_argument("--views", type=int, default=2, help="roam views per bucket (the roam protocol's seed 0 poses)")
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--supersample", type=int, default=4, help="the oracles' sub-rays per pixel side")
    ap.add_argument("--ply", type=Path, help="score these Gaussians instead of the scene's (one scene)")
    ap.add_argument("--variant", action="append", default=[], help="source per-pixel Gaussians, KEY=VALUE,... "
                    "(bench_poles.py's keys)")
    ap.add_argument("--only-variants", action="store_true", help="skip the scene's own Gaussians")
    ap.add_argument("--png", type=Path, help="write one picture per view here")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    import torch

    from panoworld.geometry.navmesh import load_navmesh
    from panoworld.io.manifest import read_manifest
    from panoworld.io.splat_ply import read_gaussians_ply
    from panoworld.io.video import load_frames
    from panoworld.render.erp import render_erp
    from panoworld.tools.eval.groundtruth import open_ground_truth
    from panoworld.tools.eval.roam import sample_roam_poses, source_seen

    torch.set_num_threads(1)
    H, W = a.height, 2 * a.height
    from bench_poles import parse_variant, source_gaussians

    names = ("oracle", "frame", "gaussians", "source_gs", *[f"var{i}" for i in range(len(a.variant))])
    rows = []
    print(f"{'scene':<8} {'view':<6} {'d m':>4} {'frm':>4} {'image':<10} {'seen':>6} "
          + " ".join(f"{k:>14}" for k in KINDS) + "   (kind: dB / share of seen px / share of seen err)")
    for scene in a.scenes:
        gt = open_ground_truth(scene)
        art = scene / ARTIFACTS / "gaussians"
        models = {}
        if not a.only_variants:
            g = read_gaussians_ply(a.ply or art / "gaussians.ply")
            models["gaussians"] = g
            if a.ply is None:
                models["source_gs"] = g.subset(np.arange(read_manifest(art)["info"]["num_source_gaussians"]))
        for i, v in enumerate(a.variant):
            models[f"var{i}"], _, info = source_gaussians(scene, parse_variant(v))
            print(f"{scene.name} var{i} = {v}: " + " ".join(f"{k}={x:.4g}" if isinstance(x, float) else f"{k}={x}"
                                                          for k, x in info.items()), flush=True)
        pano = load_frames([next(p for p in (scene / f"panorama.{e}" for e in ("png", "jpg", "jpeg")) if p.is_file())])[0]
        roam = sample_roam_poses(load_navmesh(scene / ARTIFACTS / "navmesh"), a.views, seed=0)
        for b in a.buckets:
            for k, pose in enumerate(roam.poses.get(b, [])):
                ref, depth = gt.render(pose, H, W)
                seen = source_seen(gt, pose, H, W)
                kinds = pixel_kinds(gt, pose, ref, depth)
                fi, frame, frame_pose = nearest_frame(scene, pose)
                images = {"oracle": textured_view(gt, pose, H, W, pano, np.eye(4), a.supersample),
                          "frame": textured_view(gt, pose, H, W, frame, frame_pose, a.supersample)}
                for name, gs in models.items():
                    images[name] = (render_erp(gs, pose, H, W).rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
                sc = scores(images, ref, seen, kinds)
                dist = float(roam.distances[b][k])
                rows.append({"scene": scene.name, "bucket": b, "view": k, "distance_m": dist, "frame": fi,
                             "seen_fraction": float(seen.mean()), **sc})
                for name in names:
                    if name not in sc:
                        continue
                    r = sc[name]

                    def f(v):
                        return "   -" if v is None else f"{v:5.2f}"

                    print(f"{scene.name:<8} {b + '/' + str(k):<6} {dist:4.2f} {fi:>4} {name:<10} {r['seen']:6.2f} "
                          + " ".join(f"{f(r[kd])}/{sc['share'][kd]:.2f}/{r[kd + '_err']:.2f}" for kd in KINDS), flush=True)
                if a.png:
                    save_png(a.png / f"{scene.name}_{b}_{k}.png", ref, images, seen, kinds)
    summary = {}
    for b in a.buckets:
        sel = [r for r in rows if r["bucket"] == b]
        if sel:
            summary[b] = {n: float(np.mean([r[n]["seen"] for r in sel])) for n in names if n in sel[0]}
    print("mean seen-part dB per bucket: " + "; ".join(
        f"{b}: " + ", ".join(f"{n} {v:.2f}" for n, v in s.items()) for b, s in summary.items()))
    if a.json:
        a.json.write_text(json.dumps({"variants": a.variant, "views": rows, "mean_seen_db": summary}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
