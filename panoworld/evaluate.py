"""Evaluate a scene's artifacts against its synthetic ground truth, stage by stage (`python runner.py eval SCENE`)."""

from __future__ import annotations

import argparse
import dataclasses
import enum
import json
import math
import sys
import typing
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from panoworld.artifacts import MANIFEST
from panoworld.conventions import invert_pose, points_from_depth, transform_points
from panoworld.metrics import psnr, ssim, ws_psnr
from panoworld.pipeline import ARTIFACTS_DIRNAME

GT_DIRNAME = "gt"
NO_GT_MESSAGE = "{scene} has no gt/ (ground truth); eval needs a synthetic scene from `runner.py synth`"


class EvalInputError(ValueError):
    """The scene or an option cannot be evaluated at all (no ground truth, unusable weights): exit code 2."""


class LpipsNet(enum.StrEnum):
    ALEX = "alex"
    """AlexNet features (the LPIPS default)."""
    VGG = "vgg"
    """VGG16 features."""


@dataclass(kw_only=True)
class EvalParams:
    """What `runner.py eval` measures and at which sizes."""

    max_frames: int = 16
    """Frames evaluated per sequence (conditions, video), uniformly spaced over frames 1..N-1; 0 = all of them."""
    views: int = 4
    """N of the N@N protocol for Gaussians: N context views and N novel views are rendered."""
    video_height: int = 0
    """ERP height at which video frames are compared (frames resized with INTER_AREA, ground truth rendered at that
    size; the paper compares at 720 and at 480); 0 = the video's own size."""
    gs_height: int = 128
    """ERP height of the Gaussian renders and of their ground truth (width = 2 x height)."""
    disocclusion_tol: float = 0.015
    """Relative tolerance of the true-disocclusion test: a point counts as seen from the source camera when
    nothing lies nearer than (1 - tol) times its distance along the source ray."""
    surface_samples: int = 20000
    """Mesh vertices (uniformly sampled) whose distance to the ground-truth surface is measured."""
    navmesh_samples: int = 2000
    """Points sampled on the NavMesh to check that the agent's column there is really free."""
    seed: int = 0
    """Seed of the NavMesh and mesh-vertex sampling."""
    lpips_weights: str | None = None
    """LPIPS backbone weights: a torchvision AlexNet/VGG16 state dict (.pth); needs --lpips-lin-weights too."""
    lpips_lin_weights: str | None = None
    """LPIPS v0.1 linear-head weights for --lpips-net (alex.pth or vgg.pth of the official lpips package)."""
    lpips_net: LpipsNet = LpipsNet.ALEX
    """Backbone architecture of --lpips-weights."""


# ---------------------------------------------------------------- results and targets


def unavailable(reason: str) -> dict:
    """The value of a metric (or a whole stage) that could not be computed, with the reason why."""
    return {"available": False, "reason": reason}


def is_unavailable(value: Any) -> bool:
    return isinstance(value, dict) and value.get("available") is False


@dataclass(frozen=True)
class Target:
    """A pass mark: value op bound (issue #6's targets, and collision-freeness for trajectories)."""

    op: str
    """'>=' or '<='."""
    bound: float
    unit: str = ""

    def met(self, value: Any) -> bool | None:
        if not isinstance(value, (int, float)) or isinstance(value, bool) or math.isnan(value):
            return None
        return value >= self.bound if self.op == ">=" else value <= self.bound

    def text(self) -> str:
        return f"{self.op} {self.bound:g}{self.unit}"


TARGETS: dict[str, dict[str, Target]] = {
    "trajectory": {"clear_fraction": Target(">=", 1.0), "path_collisions": Target("<=", 0)},
    "conditions": {"psnr_valid": Target(">=", 28.0, " dB"), "mask_iou": Target(">=", 0.75)},
    "poses": {"rte": Target("<=", 0.005)},
    "gaussians": {"context_psnr": Target(">=", 26.0, " dB"), "novel_psnr": Target(">=", 22.0, " dB")},
}


# ---------------------------------------------------------------- ground truth


class GroundTruth:
    """The synthetic scene of SCENE/gt/ seen in the pipeline's canonical frame (camera 0 of track 0 = identity).

    Every pose argument is canonical world_from_cam; renders are exact (SynthScene.render) and cached per pose and size.
    """

    def __init__(self, gt_dir: Path):
        self.dir = Path(gt_dir)
        self.index = json.loads((self.dir / "gt.json").read_text())
        self.world_from_canonical = np.asarray(self.index["world_from_canonical"], np.float64)
        self.supersample = int((self.index.get("panorama") or {}).get("supersample", 1))
        self._renders: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    @cached_property
    def scene(self):
        from panoworld.synth import SynthScene

        return SynthScene.load(self.dir)

    @cached_property
    def vertices(self) -> np.ndarray:
        """(V, 3) float64 ground-truth vertices in the canonical frame (gt/scene.glb via world_from_canonical)."""
        return transform_points(invert_pose(self.world_from_canonical), self.scene.vertices.astype(np.float64))

    @property
    def faces(self) -> np.ndarray:
        return self.scene.faces

    def _world(self, pose: np.ndarray) -> np.ndarray:
        return self.world_from_canonical @ np.asarray(pose, np.float64)

    def render(self, pose: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """(rgb (H, W, 3) uint8, depth (H, W) float32 metres, inf = no surface) at a canonical pose (4, 4)."""
        key = (np.asarray(pose, np.float64).tobytes(), height, width)
        if key not in self._renders:
            self._renders[key] = self.scene.render(self._world(pose), height, width, supersample=self.supersample)
        return self._renders[key]

    def depth(self, pose: np.ndarray, height: int, width: int) -> np.ndarray:
        """Exact ray distance (H, W) float32 at a canonical pose, without shading."""
        return self.scene.raycaster.render_erp(self._world(pose), height, width).distance

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance (N,) along canonical unit rays origins (N | 1, 3) + t dirs (N, 3) to the first surface (inf = none)."""
        R, t = self.world_from_canonical[:3, :3], self.world_from_canonical[:3, 3]
        return self.scene.raycaster.cast(np.asarray(origins, np.float64) @ R.T + t, np.asarray(dirs, np.float64) @ R.T).distance

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Exact distance (N,) from canonical points (N, 3) to the ground-truth surface."""
        from panoworld.trajectory import mesh_clearance

        return mesh_clearance(self.vertices, self.faces, points)


# ---------------------------------------------------------------- per-metric helpers


def depth_errors(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """AbsRel = mean |p - g| / g, RMSE (metres), delta1 = share with max(p/g, g/p) < 1.25, and the median of g / p,
    over pixels where mask (H, W) is set, p > 0 and g are finite and positive; pred, gt (H, W) metres."""
    if pred.shape != gt.shape:
        raise ValueError(f"{pred.shape=} but expected {gt.shape} (the ground truth's (H, W))")
    sel = np.isfinite(pred) & np.isfinite(gt) & (pred > 0) & (gt > 0)
    if mask is not None:
        sel &= mask.astype(bool)
    if not sel.any():
        return {"abs_rel": float("nan"), "rmse_m": float("nan"), "delta1": float("nan"), "scale_median": float("nan")}
    p, g = pred[sel].astype(np.float64), gt[sel].astype(np.float64)
    return {
        "abs_rel": float(np.mean(np.abs(p - g) / g)),
        "rmse_m": float(np.sqrt(np.mean((p - g) ** 2))),
        "delta1": float(np.mean(np.maximum(p / g, g / p) < 1.25)),
        "scale_median": float(np.median(g / p)),
    }


def true_disocclusion(gt: GroundTruth, source_pose: np.ndarray, pose: np.ndarray, height: int, width: int,
                      tol: float) -> np.ndarray:
    """(H, W) bool: pixels of the view at `pose` whose ground-truth surface point the camera at `source_pose` does not
    see (something lies nearer than (1 - tol) x its distance along the source ray), or where there is no surface.

    This is the projection test 'project the point into the source ERP, compare with the source depth' with the
    source depth taken exactly along the point's own ray (a ray cast), so it has no source-resolution error.
    """
    depth = gt.depth(pose, height, width)
    hole = ~np.isfinite(depth)
    pts = points_from_depth(np.where(hole, 1.0, depth), np.asarray(pose, np.float64))[~hole]
    centre = np.asarray(source_pose, np.float64)[:3, 3]
    ray = pts - centre
    dist = np.linalg.norm(ray, axis=1)
    seen = gt.cast(centre[None], ray / np.maximum(dist, 1e-12)[:, None]) >= (1.0 - tol) * dist
    out = hole.copy()
    out[~hole] = ~seen
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks; nan when both are empty."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else float("nan")


def interpolate_pose(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """Pose (4, 4) at fraction t from a to b: linear camera centre, slerp rotation."""
    from scipy.spatial.transform import Rotation, Slerp

    out = np.eye(4)
    out[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))(t).as_matrix()
    out[:3, 3] = (1.0 - t) * a[:3, 3] + t * b[:3, 3]
    return out


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


class Lpips:
    """LPIPS on uint8 images when weights were passed, else the reason it is unavailable."""

    def __init__(self, params: EvalParams):
        self.params = params

    @cached_property
    def model(self):
        from panoworld.models.lpips import LPIPS

        return LPIPS.from_files(self.params.lpips_weights, self.params.lpips_lin_weights, net=self.params.lpips_net)

    @property
    def enabled(self) -> bool:
        return bool(self.params.lpips_weights or self.params.lpips_lin_weights)

    def reason(self) -> dict:
        return unavailable("pass --lpips-weights BACKBONE.pth and --lpips-lin-weights LIN.pth (torchvision "
                           f"{'AlexNet' if self.params.lpips_net == LpipsNet.ALEX else 'VGG16'} state dict and the "
                           "official lpips v0.1 linear weights)")

    def distance(self, a: np.ndarray, b: np.ndarray) -> float:
        return self.model.distance_uint8(a, b)


def _fid_fvd() -> dict[str, dict]:
    return {
        "fid": unavailable("not implemented: FID needs an InceptionV3 backbone and hundreds of frames; one scene is "
                           "too few for a meaningful score"),
        "fvd": unavailable("not implemented: FVD needs an I3D backbone and many videos; one scene is too few"),
    }


# ---------------------------------------------------------------- artifact readers


def _read_gray(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2:
        raise ValueError(f"{path}: missing or not a single-channel PNG")
    return img


# ---------------------------------------------------------------- the evaluation


class Evaluation:
    """Evaluates every stage artifact of one scene; each stage gives {metric: value | unavailable(reason)}."""

    def __init__(self, scene_dir: Path, params: EvalParams | None = None, *, progress: bool = True):
        self.scene_dir = Path(scene_dir)
        self.params = params or EvalParams()
        self.progress = progress
        self.gt = GroundTruth(self.scene_dir / GT_DIRNAME)
        self.lpips = Lpips(self.params)

    # -- helpers

    def artifact(self, stage: str) -> Path | None:
        """The artifact directory of a stage that has run (its manifest.json is written last), else None."""
        d = self.scene_dir / ARTIFACTS_DIRNAME / stage
        return d if (d / MANIFEST).is_file() else None

    def manifest(self, stage: str) -> dict:
        return json.loads((self.scene_dir / ARTIFACTS_DIRNAME / stage / MANIFEST).read_text())

    def _need(self, stage: str) -> Path:
        d = self.artifact(stage)
        if d is None:
            raise _NotRun(stage)
        return d

    @cached_property
    def trajectory_poses(self) -> np.ndarray:
        from panoworld.trajectory import load_trajectory

        return load_trajectory(self._need("trajectory"))

    @cached_property
    def video(self):
        """The video artifact's description (frame and depth paths, poses); frames are read when evaluated."""
        from panoworld.poses import read_video_frames

        return read_video_frames(self._need("video"))

    @cached_property
    def conditions(self):
        from panoworld.conditions import load_conditions

        return load_conditions(self._need("conditions"))

    def reference_poses(self) -> tuple[np.ndarray, str]:
        """The poses the video was generated along (the ground truth for recovered poses): video.json, else the trajectory."""
        if self.artifact("video") is not None and self.video.poses is not None:
            return self.video.poses, "video.json poses"
        return self.trajectory_poses, "trajectory.json poses"

    def _frames(self, n: int) -> list[int]:
        from panoworld.gaussians import uniform_subset

        return uniform_subset(range(1, n), self.params.max_frames)

    def _bar(self, items, desc: str):
        return tqdm(items, desc=desc, leave=False, disable=not self.progress, file=sys.stderr)

    # -- stages

    def depth(self) -> dict:
        d = self._need("depth")
        pred = np.load(d / "depth.npy")
        if pred.ndim != 2:
            raise ValueError(f"{d / 'depth.npy'}: {pred.shape=} but expected (H, W)")
        valid = _read_gray(d / "valid.png") > 0
        gt = self.gt.depth(np.eye(4), *pred.shape)
        return {**depth_errors(pred, gt, valid), "valid_fraction": float(valid.mean()),
                "resolution": f"{pred.shape[0]}x{pred.shape[1]}"}

    def mesh(self) -> dict:
        from panoworld.mesh import load_erp_mesh
        from panoworld.poses import load_frames
        from panoworld.raycast import Raycaster

        mesh = load_erp_mesh(self._need("mesh"))
        pano = load_frames([self.scene_dir / "panorama.png"])[0]
        H, W = pano.shape[:2]
        rc = Raycaster(mesh.vertices, mesh.faces)
        hits = rc.render_erp(np.eye(4), H, W)
        seen = hits.face >= 0
        valid = seen & mesh.face_valid[np.where(seen, hits.face, 0)]
        rgb = np.clip(np.rint(rc.interpolate(hits, mesh.colors.astype(np.float64))), 0, 255).astype(np.uint8)
        used = np.unique(mesh.faces[mesh.face_valid])
        rng = np.random.default_rng(self.params.seed)
        sample = rng.choice(used, min(len(used), self.params.surface_samples), replace=False)
        surf = self.gt.clearance(mesh.vertices[sample].astype(np.float64))
        return {
            "psnr_pose0": psnr(rgb, pano, valid),
            "coverage_pose0": float(valid.mean()),
            "surface_error_median_m": float(np.median(surf)),
            "surface_error_p90_m": float(np.percentile(surf, 90)),
            "num_faces": int(len(mesh.faces)),
        }

    def navmesh(self) -> dict:
        from panoworld.navmesh import load_navmesh

        nav = load_navmesh(self._need("navmesh"))
        radius = float(nav.agent.get("agent_radius_m", 0.25))
        floor_gt = float(self.gt.index["floor_y_canonical"])
        bottom = max(float(nav.agent.get("step_height_m", 0.0)), radius)
        top = float(nav.agent.get("band_top_m", bottom))
        heights = np.linspace(bottom, max(top, bottom), 4)
        xz = nav.sample_points(self.params.navmesh_samples, self.params.seed)
        pts = np.stack([np.repeat(xz[:, 0], len(heights)), np.tile(floor_gt - heights, len(xz)),
                        np.repeat(xz[:, 1], len(heights))], 1)
        clear = self.gt.clearance(pts).reshape(len(xz), len(heights)).min(axis=1)
        return {
            "floor_height_error_m": abs(float(nav.floor_y) - floor_gt),
            "area_m2": nav.area,
            "free_fraction": float(np.mean(clear >= radius)),
            "agent_radius_m": radius,
        }

    def trajectory(self) -> dict:
        from panoworld.navmesh import NavMeshParams
        from panoworld.trajectory import step_lengths

        poses = self.trajectory_poses
        centres = poses[:, :3, 3]
        clearance = self.gt.clearance(centres)
        radius, radius_src = NavMeshParams().agent_radius_m, "NavMeshParams default (navmesh not run)"
        if self.artifact("navmesh") is not None:
            doc = json.loads((self.artifact("navmesh") / "navmesh.json").read_text())
            radius, radius_src = float(doc["agent"]["agent_radius_m"]), "navmesh.json"
        seg = np.diff(centres, axis=0)
        length = np.linalg.norm(seg, axis=1)
        moving = length > 1e-9
        free = self.gt.cast(centres[:-1][moving], seg[moving] / length[moving, None])
        steps = step_lengths(poses)
        out = {
            "num_poses": int(len(poses)),
            "min_clearance_m": float(clearance.min()),
            "mean_clearance_m": float(clearance.mean()),
            "clear_fraction": float(np.mean(clearance >= radius)),
            "agent_radius_m": radius,
            "agent_radius_source": radius_src,
            "path_collisions": int(np.sum(free < length[moving])),
            "path_length_m": float(length.sum()),
            "loop_closure_m": float(np.linalg.norm(centres[-1] - centres[0])),
            "step_cv": float(steps.std() / steps.mean()) if len(steps) and steps.mean() > 0 else float("nan"),
        }
        return out

    def conditions_stage(self) -> dict:
        cond = self.conditions
        idx = self._frames(len(cond))
        if not idx:
            return unavailable("conditions hold only frame 0 (the source view); nothing to evaluate")
        ps, ious, dabs, hole_fraction = [], [], [], []
        inter = union = 0
        H, W = cond.height, cond.width
        for i in self._bar(idx, "eval conditions"):
            frame = cond.frame(i)
            gt_rgb, gt_depth = self.gt.render(cond.poses[i], H, W)
            if frame.mask.any():
                ps.append(psnr(frame.rgb, gt_rgb, frame.mask))
            hole_true = true_disocclusion(self.gt, np.eye(4), cond.poses[i], H, W, self.params.disocclusion_tol)
            hole = ~frame.mask
            hole_fraction.append(float(hole.mean()))
            inter += int(np.logical_and(hole, hole_true).sum())
            union += int(np.logical_or(hole, hole_true).sum())
            if not math.isnan(v := iou(hole, hole_true)):
                ious.append(v)
            if cond.depth is not None:
                dabs.append(depth_errors(frame.depth, gt_depth, frame.mask)["abs_rel"])
        return {
            "frames_evaluated": len(idx),
            "psnr_valid": _mean(ps),
            "mask_iou": inter / union if union else float("nan"),
            "mask_iou_frame_mean": _mean(ious),
            "hole_fraction": _mean(hole_fraction),
            "depth_abs_rel": _mean(dabs) if dabs else unavailable("the conditions have no depth maps"),
        }

    def video_stage(self) -> dict:
        import cv2

        from panoworld.poses import load_frames, read_depth_png

        video = self.video
        poses, _ = self.reference_poses()
        T = video.num_frames
        if len(poses) != T:
            raise ValueError(f"the video has {T} frames but {len(poses)} poses")
        idx = self._frames(T)
        if not idx:
            return unavailable("the video holds only frame 0 (the input panorama); nothing to evaluate")
        H = self.params.video_height or video.height
        W = 2 * H
        holes = None
        holes_reason = "conditions not run: the disoccluded pixels are the conditions' mask = 0"
        if self.artifact("conditions") is not None:
            if len(self.conditions) == T:
                holes = self.conditions.mask
            else:
                holes_reason = f"conditions have {len(self.conditions)} frames but the video {T}"
        acc: dict[str, list[float]] = {k: [] for k in ("psnr", "ssim", "ws_psnr", "psnr_dis", "ssim_dis",
                                                        "ws_psnr_dis", "lpips", "depth")}
        for i in self._bar(idx, "eval video"):
            gt_rgb, gt_depth = self.gt.render(poses[i], H, W)
            f = load_frames([video.rgb[i]], H)[0]
            acc["psnr"].append(psnr(f, gt_rgb))
            acc["ssim"].append(ssim(f, gt_rgb))
            acc["ws_psnr"].append(ws_psnr(f, gt_rgb))
            if holes is not None:
                m = cv2.resize((~holes[i]).astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST).astype(bool)
                if m.any():
                    acc["psnr_dis"].append(psnr(f, gt_rgb, m))
                    acc["ssim_dis"].append(ssim(f, gt_rgb, m))
                    acc["ws_psnr_dis"].append(ws_psnr(f, gt_rgb, m))
            if self.lpips.enabled:
                acc["lpips"].append(self.lpips.distance(f, gt_rgb))
            if video.has_depth:
                d = cv2.resize(read_depth_png(video.depth[i], video.depth_scale), (W, H), interpolation=cv2.INTER_NEAREST)
                acc["depth"].append(depth_errors(d, gt_depth)["abs_rel"])

        def dis(key: str):
            if holes is None:
                return unavailable(holes_reason)
            return _mean(acc[key]) if acc[key] else unavailable("no disoccluded pixel in the evaluated frames")

        return {
            "frames_evaluated": len(idx),
            "psnr": _mean(acc["psnr"]),
            "ssim": _mean(acc["ssim"]),
            "ws_psnr": _mean(acc["ws_psnr"]),
            "psnr_disoccluded": dis("psnr_dis"),
            "ssim_disoccluded": dis("ssim_dis"),
            "ws_psnr_disoccluded": dis("ws_psnr_dis"),
            "lpips": _mean(acc["lpips"]) if self.lpips.enabled else self.lpips.reason(),
            "depth_abs_rel": _mean(acc["depth"]) if video.has_depth else unavailable("the video has no depth"),
            "resolution": f"{H}x{W}",
            **_fid_fvd(),
        }

    def poses(self) -> dict:
        from panoworld.align import trajectory_metrics
        from panoworld.poses import load_poses

        est = load_poses(self._need("poses"))
        gt, source = self.reference_poses()
        if est.world_from_cam.shape != gt.shape:
            raise ValueError(f"poses.json has {len(est.world_from_cam)} poses but the {source} {len(gt)}")
        reg = est.registered
        out: dict[str, Any] = {"num_frames": int(len(reg)), "registered_fraction": float(reg.mean()),
                               "ground_truth": source}
        if reg.sum() < 2:
            reason = f"only {int(reg.sum())} registered frame(s); Sim(3) alignment needs at least 2"
            return {**out, **{k: unavailable(reason) for k in ("ate", "ate_rmse", "rpe_t", "rpe_r", "rre", "rte")}}
        m = trajectory_metrics(est.world_from_cam[reg], gt[reg])
        return {**out, **{k: m[k] for k in ("ate", "ate_rmse", "rpe_t", "rpe_r", "rre", "rte", "scale")}}

    def gaussians(self) -> dict:
        from panoworld.gaussians import uniform_subset
        from panoworld.render_gs import render_erp
        from panoworld.splat_ply import read_gaussians_ply

        d = self._need("gaussians")
        g = read_gaussians_ply(d / "gaussians.ply")
        poses, source = self.reference_poses()
        used = self.manifest("gaussians").get("info", {}).get("frames") or list(range(len(poses)))
        used = [int(i) for i in used if 0 <= int(i) < len(poses)]
        N = self.params.views
        context = uniform_subset(used, N)
        held_out = uniform_subset(sorted(set(range(len(poses))) - set(used)), N)
        if held_out:
            novel = [poses[i] for i in held_out]
            protocol = f"held-out frames of the {source}: {held_out}"
        else:
            pick = uniform_subset(range(len(used) - 1), N)
            novel = [interpolate_pose(poses[used[k]], poses[used[k + 1]], 0.5) for k in pick]
            protocol = (f"every frame is context, so novel views are midpoints between consecutive context frames "
                        f"{[(used[k], used[k + 1]) for k in pick]} of the {source}")
        H = self.params.gs_height
        out: dict[str, Any] = {"setting": f"{len(context)}@{len(novel)}", "context_frames": context,
                               "novel_protocol": protocol, "render_height": H}
        for name, views in (("context", [poses[i] for i in context]), ("novel", novel)):
            acc: dict[str, list[float]] = {"psnr": [], "ssim": [], "ws_psnr": [], "lpips": [], "coverage": []}
            for pose in self._bar(views, f"eval gaussians {name}"):
                r = render_erp(g, pose, H, 2 * H)
                img = (r.rgb.clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)
                ref, _ = self.gt.render(pose, H, 2 * H)
                acc["psnr"].append(psnr(img, ref))
                acc["ssim"].append(ssim(img, ref))
                acc["ws_psnr"].append(ws_psnr(img, ref))
                acc["coverage"].append(float(r.alpha.mean()))
                if self.lpips.enabled:
                    acc["lpips"].append(self.lpips.distance(img, ref))
            if not views:
                out.update({f"{name}_{k}": unavailable(f"no {name} view") for k in ("psnr", "ssim", "ws_psnr")})
                continue
            for k in ("psnr", "ssim", "ws_psnr", "coverage"):
                out[f"{name}_{k}"] = _mean(acc[k])
            out[f"{name}_lpips"] = _mean(acc["lpips"]) if self.lpips.enabled else self.lpips.reason()
        return out

    STAGES: dict[str, str] = {
        "depth": "depth", "mesh": "mesh", "navmesh": "navmesh", "trajectory": "trajectory",
        "conditions": "conditions_stage", "video": "video_stage", "poses": "poses", "gaussians": "gaussians",
    }

    def run(self, stages: list[str] | None = None) -> tuple[dict[str, dict], list[str]]:
        """({stage: metrics or unavailable(reason)}, [stages whose existing artifact could not be evaluated])."""
        results, errors = {}, []
        for stage in stages or list(self.STAGES):
            if self.artifact(stage) is None:
                results[stage] = unavailable(f"not run: no {ARTIFACTS_DIRNAME}/{stage}/{MANIFEST}; "
                                             f"`python runner.py run SCENE --until {stage}` makes it")
                continue
            try:
                results[stage] = getattr(self, self.STAGES[stage])()
            except _NotRun as e:
                results[stage] = unavailable(f"needs the {e.stage} artifact, which is not run")
            except Exception as e:  # a corrupt or foreign artifact must not stop the other stages
                results[stage] = unavailable(f"error: {type(e).__name__}: {e}")
                errors.append(stage)
        return results, errors


class _NotRun(Exception):
    def __init__(self, stage: str):
        super().__init__(stage)
        self.stage = stage


# ---------------------------------------------------------------- report


def target_report(stages: dict[str, dict]) -> dict[str, dict]:
    """{stage: {metric: {"target": text, "met": bool | None}}} for every metric with a target."""
    out: dict[str, dict] = {}
    for stage, targets in TARGETS.items():
        if stage not in stages:
            continue
        metrics = stages[stage]
        for name, t in targets.items():
            value = metrics.get(name) if not is_unavailable(metrics) else None
            out.setdefault(stage, {})[name] = {"target": t.text(), "met": t.met(value)}
    return out


def jsonable(obj: Any) -> Any:
    """obj with numpy scalars as Python numbers and non-finite floats as the strings 'inf', '-inf', 'nan'."""
    if isinstance(obj, dict):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    return obj


def _fmt(value: Any) -> str:
    if is_unavailable(value):
        return f"n/a ({value['reason']})"
    if isinstance(value, bool) or isinstance(value, (int, np.integer)):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        a = abs(value)
        return f"{value:.1f}" if a >= 1000 else f"{value:.3f}" if a >= 1 else f"{value:.4g}"
    return str(value)


def format_table(report: dict) -> str:
    """The report as a text table grouped by stage: metric, value, target, ok."""
    lines = [f"scene: {report['scene']}", ""]
    rows = [("stage", "metric", "value", "target", "ok")]
    for stage, metrics in report["stages"].items():
        if is_unavailable(metrics):
            rows.append((stage, "-", _fmt(metrics), "", ""))
            continue
        targets = report["targets"].get(stage, {})
        for k, (name, value) in enumerate(metrics.items()):
            t = targets.get(name)
            ok = "" if t is None or t["met"] is None else ("yes" if t["met"] else "NO")
            rows.append((stage if k == 0 else "", name, _fmt(value), t["target"] if t else "", ok))
    widths = [max(len(r[c]) for r in rows if len(r[c]) < 40) for c in range(4)]
    for r in rows:
        lines.append("  ".join(r[c].ljust(widths[c]) for c in range(4)) + "  " + r[4])
    return "\n".join(line.rstrip() for line in lines)


def evaluate(scene_dir: Path, params: EvalParams | None = None, *, stages: list[str] | None = None,
             progress: bool = False) -> tuple[dict, list[str]]:
    """The full report {"scene", "params", "stages", "targets"} of a synthetic scene and the stages that errored.

    Raises EvalInputError when scene_dir has no gt/gt.json or LPIPS weights were passed but cannot be loaded.
    """
    from panoworld.stage import params_to_dict

    scene_dir = Path(scene_dir)
    if not (scene_dir / GT_DIRNAME / "gt.json").is_file():
        raise EvalInputError(NO_GT_MESSAGE.format(scene=scene_dir))
    params = params or EvalParams()
    ev = Evaluation(scene_dir, params, progress=progress)
    if ev.lpips.enabled:
        try:
            ev.lpips.model
        except (OSError, ValueError, KeyError, RuntimeError) as e:
            raise EvalInputError(f"LPIPS weights: {e}") from None
    results, errors = ev.run(stages)
    report = {
        "scene": str(scene_dir),
        "params": params_to_dict(params),
        "stages": results,
        "targets": target_report(results),
    }
    return jsonable(report), errors


# ---------------------------------------------------------------- CLI


def build_parser() -> argparse.ArgumentParser:
    from panoworld.stage import field_docs

    ap = argparse.ArgumentParser(prog="python runner.py eval", description=__doc__)
    ap.add_argument("scene", type=Path, help="scene directory with gt/ (from `runner.py synth`) and artifacts/")
    ap.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")
    ap.add_argument("--out", type=Path, help="also write the JSON report to this file (the scene is never modified)")
    ap.add_argument("--only", action="append", default=[], choices=list(Evaluation.STAGES), metavar="STAGE",
                    help=f"evaluate only this stage (repeatable; one of {', '.join(Evaluation.STAGES)})")
    docs = field_docs(EvalParams)
    hints = typing.get_type_hints(EvalParams)
    for f in dataclasses.fields(EvalParams):
        tp = hints[f.name]
        choices = [m.value for m in tp] if isinstance(tp, type) and issubclass(tp, enum.Enum) else None
        default = f.default.value if isinstance(f.default, enum.Enum) else f.default
        ap.add_argument(f"--{f.name.replace('_', '-')}", dest=f"p_{f.name}", default=None, choices=choices,
                        metavar=None if choices else getattr(tp, "__name__", "path").upper(),
                        help=f"{docs.get(f.name, '')} (default: {default})")
    return ap


def main(argv: list[str] | None = None) -> int:
    from panoworld.stage import params_from_dict

    args = build_parser().parse_args(argv)
    values = {f.name: getattr(args, f"p_{f.name}") for f in dataclasses.fields(EvalParams)}
    try:
        params = params_from_dict(EvalParams, {k: v for k, v in values.items() if v is not None}, where="eval")
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if bool(params.lpips_weights) != bool(params.lpips_lin_weights):
        print("error: LPIPS needs both --lpips-weights (backbone) and --lpips-lin-weights (linear heads)", file=sys.stderr)
        return 2
    if not args.scene.is_dir():
        print(f"error: {args.scene}: scene directory not found", file=sys.stderr)
        return 2
    try:
        report, errors = evaluate(args.scene, params, stages=args.only or None, progress=sys.stderr.isatty())
    except EvalInputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    text = json.dumps(report, indent=2)
    if args.out:
        args.out.write_text(text + "\n")
    print(text if args.json else format_table(report))
    for stage in errors:
        print(f"error: stage {stage} could not be evaluated: {report['stages'][stage]['reason']}", file=sys.stderr)
    return 1 if errors else 0
