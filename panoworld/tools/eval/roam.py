"""The roam protocol: the Gaussian scene rendered at random upright poses on the NavMesh, bucketed by distance."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from panoworld.tools.eval.common import Lpips, _mean, unavailable


@dataclass(frozen=True)
class Bucket:
    """Poses whose horizontal distance from the capture point lies in [lo, hi) metres."""

    key: str
    lo: float
    hi: float


BUCKETS = (Bucket("d0", 0.0, 0.0), Bucket("d0.5", 0.25, 0.75), Bucket("d1", 0.75, 1.5), Bucket("d2", 1.5, 2.5))
"""Fixed buckets: the capture point itself, ~0.5 m, ~1 m, ~2 m (edges in metres)."""
FAR_KEY = "far"
FAR_FRACTION = 0.85
"""The 'farthest reachable' bucket: NavMesh points at least this fraction of the farthest one's distance away."""
CANDIDATES = 20000
"""NavMesh points drawn (uniformly over its area) to pick the roam poses from."""
SEEN_TOL = (0.01, 0.01)
"""source_seen's tolerance (relative, metres): a surface point counts as seen by the capture point when the capture
point's ray towards it hits nothing nearer than its distance * (1 - relative) - metres."""
MIN_PART = 1e-3
"""A view's seen / unseen part is scored only when it holds at least this fraction of the view's pixels."""


@dataclass
class RoamPoses:
    """The roam poses of one scene: per bucket key its poses (K, 4, 4) and distances (K,), or why there are none."""

    poses: dict[str, np.ndarray] = field(default_factory=dict)
    distances: dict[str, np.ndarray] = field(default_factory=dict)
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)
    missing_range: dict[str, str] = field(default_factory=dict)
    farthest_m: float = 0.0


def sample_roam_poses(nav, views: int, seed: int = 0, camera_y: float = 0.0) -> RoamPoses:
    """Seeded upright poses (camera at camera_y, random yaw) on the NavMesh `nav` (x, z of the canonical frame), `views`
    per bucket. The d0 bucket is the capture point itself, its first pose the identity (the input panorama's view)."""
    from panoworld.trajectory import poses_from_positions

    rng = np.random.default_rng(seed)
    cand = np.concatenate([nav.sample_points(CANDIDATES, rng), nav.vertices[nav.contains(nav.vertices)]])
    dist = np.linalg.norm(cand, axis=1)
    out = RoamPoses(farthest_m=float(dist.max()) if len(dist) else 0.0)
    yaw0 = rng.uniform(0.0, 2 * math.pi, views)
    yaw0[0] = 0.0
    out.poses["d0"] = poses_from_positions(np.zeros((views, 2)), yaw0, camera_y)
    out.distances["d0"] = np.zeros(views)
    out.ranges["d0"] = (0.0, 0.0)
    far = Bucket(FAR_KEY, FAR_FRACTION * out.farthest_m, out.farthest_m + 1e-9)
    for b in (*BUCKETS[1:], far):
        out.ranges[b.key] = (b.lo, min(b.hi, out.farthest_m))
        sel = np.flatnonzero((dist >= b.lo) & (dist < b.hi))
        if not len(sel):
            out.missing_range[b.key] = f"{b.lo:.2f}-{b.hi:.2f}"
            out.missing[b.key] = (f"the NavMesh does not reach {b.lo:g}-{b.hi:g} m from the capture point (its "
                                  f"farthest point is {out.farthest_m:.2f} m away)")
            continue
        pick = rng.choice(sel, min(views, len(sel)), replace=False)
        out.poses[b.key] = poses_from_positions(cand[pick], rng.uniform(0.0, 2 * math.pi, len(pick)), camera_y)
        out.distances[b.key] = dist[pick]
    return out


def source_seen(gt, pose: np.ndarray, height: int, width: int, tol: tuple[float, float] = SEEN_TOL) -> np.ndarray:
    """(H, W) bool of an ERP view at canonical `pose`: the pixels whose ground-truth surface (one exact ray per pixel
    centre) the capture point (the identity pose) sees, i.e. what the source panorama observed; False where the
    surface is hidden from it (disoccluded: only other frames, or nothing, can have it). Pixels without a surface
    count as seen."""
    from panoworld.core.conventions import erp_dirs

    pose = np.asarray(pose, np.float64)
    depth = gt.depth(pose, height, width).astype(np.float64).reshape(-1)
    hit = np.isfinite(depth)
    dirs = erp_dirs(height, width, np.float64).reshape(-1, 3)[hit] @ pose[:3, :3].T
    pts = pose[:3, 3] + dirs * depth[hit, None]
    dist = np.linalg.norm(pts, axis=1)
    first = gt.cast(np.zeros((1, 3)), pts / np.maximum(dist, 1e-12)[:, None])
    seen = np.ones(height * width, bool)
    seen[hit] = first >= dist * (1.0 - tol[0]) - tol[1]
    return seen.reshape(height, width)


def split_scores(img: np.ndarray, ref: np.ndarray, seen: np.ndarray, alpha: np.ndarray) -> dict[str, float]:
    """One view's error split by source visibility (seen (H, W) bool): PSNR of the seen and the unseen part (only
    parts of at least MIN_PART of the pixels), the unseen fraction, the unseen part's share of the squared error, and
    the coverage (alpha > 0.5) of each part."""
    from panoworld.render.metrics import psnr

    err2 = ((img.astype(np.float64) - ref.astype(np.float64)) ** 2).sum(-1)
    frac = float(1.0 - seen.mean())
    out = {"erp_unseen_fraction": frac,
           "erp_unseen_error_share": float(err2[~seen].sum() / max(err2.sum(), 1e-12))}
    for name, part in (("seen", seen), ("unseen", ~seen)):
        if part.mean() >= MIN_PART:
            out[f"erp_psnr_{name}"] = psnr(img, ref, part)
            out[f"erp_coverage_{name}"] = float((alpha[part] > 0.5).mean())
    return out


def pinhole_intrinsics(size: int, fov_deg: float) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a square pinhole view `size` pixels wide with a horizontal field of view fov_deg."""
    f = 0.5 * size / math.tan(math.radians(fov_deg) / 2)
    return f, f, 0.5 * size, 0.5 * size


def _uint8(t) -> np.ndarray:
    return (t.clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)


@dataclass
class RoamSettings:
    """Sizes and counts of one roam evaluation (EvalParams with the preset's defaults resolved)."""

    views: int
    height: int
    pinhole: int
    fov_deg: float
    seed: int


def evaluate_roam(gaussians, nav, gt, settings: RoamSettings, lpips: Lpips, *, panorama: np.ndarray | None = None,
                  on_view: Callable[[str, int, dict], None] | None = None, bar=lambda it, desc: it) -> dict[str, Any]:
    """Roam metrics {bucket}_{metric} of a Gaussian scene; gt: the scene's reference (GroundTruth renders; a scene
    without a mesh raises NoReference and gets coverage only); panorama (H, W, 3) uint8: the input, scored against
    the identity view of the d0 bucket. on_view(bucket, k, images) receives the renders (report pictures). With a
    mesh, each ERP view's error is also split into what the capture point sees and what it does not (split_scores)."""
    import cv2

    from panoworld.render.erp import render_erp
    from panoworld.render.metrics import psnr, ssim, ws_psnr
    from panoworld.render.splats import render_perspective

    H = settings.height
    roam = sample_roam_poses(nav, settings.views, settings.seed)
    pin = pinhole_intrinsics(settings.pinhole, settings.fov_deg) if settings.pinhole > 0 else None
    has_gt = gt.kind == "synthetic"  # a frames + poses reference has no views off its tracks
    out: dict[str, Any] = {
        "reference": (gt.describe(H) if has_gt else f"none at roam poses ({gt.kind} reference): coverage only, and "
                      "the d0 identity view against the input panorama"),
        "erp_size": f"{H}x{2 * H}",
        "pinhole": f"{settings.pinhole}x{settings.pinhole}, {settings.fov_deg:g} deg" if pin else "off",
        "views_per_bucket": settings.views,
        "farthest_m": roam.farthest_m,
    }
    pano = None
    if panorama is not None:
        pano = cv2.resize(panorama, (2 * H, H), interpolation=cv2.INTER_AREA)
    for key in (*[b.key for b in BUCKETS], FAR_KEY):
        lo, hi = roam.ranges[key]
        if key in roam.missing:
            out[f"{key}_range_m"] = roam.missing_range[key]
            out[f"{key}_count"] = 0
            out[f"{key}_erp_psnr"] = unavailable(roam.missing[key])
            continue
        out[f"{key}_range_m"] = f"{lo:.2f}-{hi:.2f}"
        acc: dict[str, list[float]] = {}
        for k, pose in enumerate(bar(roam.poses[key], f"eval roam {key}")):
            r = render_erp(gaussians, pose, H, 2 * H)
            img = _uint8(r.rgb)
            acc.setdefault("erp_coverage", []).append(float((r.alpha > 0.5).float().mean()))
            images = {"erp": img}
            if key == "d0" and k == 0 and pano is not None:
                acc.setdefault("erp_psnr_vs_input", []).append(psnr(img, pano))
            if has_gt:
                images["erp_ref"] = ref = gt.render(pose, H, 2 * H)[0]
                acc.setdefault("erp_psnr", []).append(psnr(img, ref))
                acc.setdefault("erp_ssim", []).append(ssim(img, ref))
                acc.setdefault("erp_ws_psnr", []).append(ws_psnr(img, ref))
                for name, v in split_scores(img, ref, source_seen(gt, pose, H, 2 * H), r.alpha.numpy()).items():
                    acc.setdefault(name, []).append(v)
                if lpips.enabled:
                    acc.setdefault("erp_lpips", []).append(lpips.distance(img, ref))
            if pin is not None:
                P = settings.pinhole
                rp = render_perspective(gaussians, pose, *pin, P, P)
                pimg = _uint8(rp.rgb)
                images["pinhole"] = pimg
                acc.setdefault("pinhole_coverage", []).append(float((rp.alpha > 0.5).float().mean()))
                if has_gt:
                    pref = gt.render_pinhole(pose, *pin, P, P)[0]
                    images["pinhole_ref"] = pref
                    acc.setdefault("pinhole_psnr", []).append(psnr(pimg, pref))
                    acc.setdefault("pinhole_ssim", []).append(ssim(pimg, pref))
                    if lpips.enabled:
                        acc.setdefault("pinhole_lpips", []).append(lpips.distance(pimg, pref))
            if on_view is not None:
                on_view(key, k, images)
        out[f"{key}_count"] = len(roam.poses[key])
        out[f"{key}_distance_m"] = float(np.mean(roam.distances[key]))
        for metric, values in acc.items():
            out[f"{key}_{metric}"] = _mean(values)
        if not has_gt:
            out[f"{key}_erp_psnr"] = unavailable("no ground-truth mesh: coverage only (and d0 against the input)")
    if not lpips.enabled:
        out["lpips"] = lpips.reason()
    return out


def save_view(out_dir, bucket: str, k: int, images: dict[str, np.ndarray]) -> None:
    """Save the first view of a bucket as OUT_DIR/{bucket}_{kind}.png (kinds: erp, erp_ref, pinhole, pinhole_ref)."""
    from pathlib import Path

    import cv2

    if k:
        return
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for kind, img in images.items():
        cv2.imwrite(str(out_dir / f"{bucket}_{kind}.png"), np.ascontiguousarray(img[..., ::-1]))


def sector_reachable(nav, n_sectors: int = 8, start_within_m: float = 0.5) -> np.ndarray:
    """(n_sectors,) distance (m) walkable from the capture point (x, z = 0) straight along each sector's centre
    direction (sector k at lon = k 2 pi / n, lon 0 = +z) to the NavMesh boundary. A capture point off the NavMesh (the
    rig's blind spot) starts at the first inside point within start_within_m (searched in 1 cm steps)."""
    lon = 2 * math.pi * np.arange(n_sectors) / n_sectors
    dirs = np.stack([np.sin(lon), np.cos(lon)], 1)
    ts = np.arange(0.0, start_within_m + 1e-9, 0.01)
    out = np.zeros(n_sectors)
    for k in range(n_sectors):
        first = np.flatnonzero(nav.contains(ts[:, None] * dirs[k]))
        if len(first):
            t0 = ts[first[0]]
            out[k] = t0 + float(nav.ray_reach(t0 * dirs[k], dirs[k][None])[0])
    return out


def trajectory_reach(nav, poses: np.ndarray, n_sectors: int = 8) -> dict[str, Any]:
    """How far the planned camera centres (N, 4, 4) get from the capture point: the farthest (m), and per sector the
    farthest pose in it against the sector's straight walkable distance (sector_reachable)."""
    from panoworld.trajectory.sectors import MIN_SECTOR_DIST_M, sector_of

    xz = np.asarray(poses, np.float64).reshape(-1, 4, 4)[:, :3, 3][:, [0, 2]]
    dist = np.linalg.norm(xz, axis=1)
    sec = sector_of(xz, np.zeros(2), n_sectors)
    reached = np.array([dist[(sec == k) & (dist >= MIN_SECTOR_DIST_M)].max(initial=0.0) for k in range(n_sectors)])
    reachable = sector_reachable(nav, n_sectors)
    open_ = reachable >= MIN_SECTOR_DIST_M
    frac = np.minimum(reached[open_] / reachable[open_], 1.0)
    return {"reach_max_m": float(dist.max(initial=0.0)), "sector_reached_m": reached.round(3).tolist(),
            "sector_reachable_m": reachable.round(3).tolist(),
            "sector_reach_fraction_min": float(frac.min()) if len(frac) else float("nan")}


UNSEEN_PARTS = ("floor", "walls", "ceiling", "object side", "object top", "object underside")
"""unseen_parts' surface classes: architecture by the ground-truth node kind, furniture by its face normal."""


def unseen_parts(gt, pose: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) int8 index into UNSEEN_PARTS of the ground-truth surface at each pixel centre of an ERP view at canonical
    `pose` (-1 = no surface): floor / walls / ceiling by node kind; any other node (furniture, lights, pictures) by its
    face normal against canonical up (-y): side (|cos| < 0.5), top, underside."""
    pose = np.asarray(pose, np.float64)
    hits = gt.scene.raycaster.render_erp(gt.world_from_canonical @ pose, height, width)
    face = hits.face.reshape(-1)
    out = np.full(face.shape, -1, np.int8)
    hit = face >= 0
    kind = np.array([n.kind for n in gt.scene.nodes])[gt.scene.face_node[face[hit]]]
    up = -(gt.world_from_canonical[:3, :3] @ np.array([0.0, 1.0, 0.0]))  # canonical -y in the world frame
    cos = gt.scene.face_normals[face[hit]] @ up
    part = np.where(cos > 0.5, 4, np.where(cos < -0.5, 5, 3))
    for k, name in enumerate(UNSEEN_PARTS[:3]):
        part = np.where(kind == name, k, part)
    out[hit] = part
    return out.reshape(height, width)
