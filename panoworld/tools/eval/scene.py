"""Evaluation of one scene's artifacts against its reference: synthetic ground truth, ground-truth frames + poses,
or the plan alone (RealSee3D-like scenes); each stage gives {metric: value | unavailable(reason)}."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from panoworld.conditions.warp import true_disocclusion
from panoworld.io.manifest import ARTIFACTS_DIRNAME, MANIFEST
from panoworld.render.metrics import psnr, ssim, ws_psnr
from panoworld.tools.eval.common import (
    _mean,
    _read_gray,
    depth_errors,
    fid_fvd_per_scene,
    interpolate_pose,
    iou,
    unavailable,
)
from panoworld.tools.eval.groundtruth import NoReference
from panoworld.tools.eval.inputs import NotRun, SceneInputs

POSE_METRICS = ("ate", "ate_rmse", "rpe_t", "rpe_r", "rre", "rte", "ate_over_path", "rot_error_abs")


class Evaluation(SceneInputs):
    """Evaluates every stage artifact of one scene; each stage gives {metric: value | unavailable(reason)}.

    The reference (self.gt, see open_ground_truth) decides what can be scored: a synthetic scene everything, a frames
    + poses scene what lies on its ground-truth tracks, a plan-only scene poses against the plan and ring loops.
    """

    # -- stages

    def depth(self) -> dict:
        d = self._need("depth")
        pred = np.load(d / "depth.npy")
        if pred.ndim != 2:
            raise ValueError(f"{d / 'depth.npy'}: {pred.shape=} but expected (H, W)")
        valid = _read_gray(d / "valid.png") > 0
        gt = self.gt.depth(self.pose0, *pred.shape)
        return {**depth_errors(pred, gt, valid), "valid_fraction": float(valid.mean()),
                "resolution": f"{pred.shape[0]}x{pred.shape[1]}"}

    def register(self) -> dict:
        from panoworld.register.inputs import is_multi_scene
        from panoworld.tools.eval.home import registration_metrics

        if not is_multi_scene(self.scene_dir):
            raise NoReference("one panorama: nothing to register")
        return registration_metrics(self._need("register"), self.scene_dir)

    def _first_capture(self) -> tuple[Path, np.ndarray, str]:
        """(input panorama, world_from_cam, name) of the scene's panorama at the identity, or of a home's first
        registered panorama (by name) at its registered pose."""
        from panoworld.io.home import capture_poses
        from panoworld.register.inputs import PANORAMAS_DIR, find_multi_scene, is_multi_scene

        if not is_multi_scene(self.scene_dir):
            for e in ("png", "jpg", "jpeg"):
                if (self.scene_dir / f"panorama.{e}").is_file():
                    return self.scene_dir / f"panorama.{e}", np.eye(4), "panorama"
            raise NoReference(f"{self.scene_dir}: no panorama.png|jpg to score the mesh against")
        captures = capture_poses(self._need("register"))
        name = sorted(captures)[0]
        path = find_multi_scene(self.scene_dir).panoramas.get(name)
        if path is None:
            raise NoReference(f"{self.scene_dir / PANORAMAS_DIR}: no panorama of the capture point {name}")
        return path, captures[name], name

    def mesh(self) -> dict:
        from panoworld.geometry.erp_mesh import load_erp_mesh
        from panoworld.geometry.raycast import Raycaster
        from panoworld.io.video import load_frames

        mesh = load_erp_mesh(self._need("mesh"))
        path, world_from_cam, name = self._first_capture()
        pano = load_frames([path])[0]
        H, W = pano.shape[:2]
        rc = Raycaster(mesh.vertices, mesh.faces)
        hits = rc.render_erp(world_from_cam, H, W)
        seen = hits.face >= 0
        valid = seen & mesh.face_valid[np.where(seen, hits.face, 0)]
        rgb = np.clip(np.rint(rc.interpolate(hits, mesh.colors.astype(np.float64))), 0, 255).astype(np.uint8)
        used = np.unique(mesh.faces[mesh.face_valid])
        rng = np.random.default_rng(self.params.seed)
        sample = rng.choice(used, min(len(used), self.params.surface_samples), replace=False)
        out: dict[str, Any] = {"psnr_pose0": psnr(rgb, pano, valid), "coverage_pose0": float(valid.mean())}
        try:
            surf = self.gt.clearance(mesh.vertices[sample].astype(np.float64))
            out.update(surface_error_median_m=float(np.median(surf)), surface_error_p90_m=float(np.percentile(surf, 90)))
        except NoReference as e:
            out.update(surface_error_median_m=unavailable(str(e)), surface_error_p90_m=unavailable(str(e)))
        return {**out, "num_faces": int(len(mesh.faces)), **({"pose0_at": name} if name != "panorama" else {})}

    def navmesh(self) -> dict:
        from panoworld.geometry.navmesh import load_navmesh

        nav = load_navmesh(self._need("navmesh"))
        if self.gt.kind != "synthetic":
            self.gt.clearance(np.zeros((1, 3)))  # raises NoReference: the NavMesh is checked against the GT surface
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
        from panoworld.io.trajectory import load_clips
        from panoworld.navmesh import NavMeshParams

        poses = self.trajectory_poses
        centres = poses[:, :3, 3]
        clips = load_clips(self._need("trajectory"), len(poses))
        # the walked segments: consecutive poses of each path (a jump between paths is not walked)
        a, b = (np.concatenate([np.asarray(c[k:len(c) - 1 + k], dtype=np.int64) for c in clips]) for k in (0, 1))
        seg = centres[b] - centres[a]
        steps = np.linalg.norm(seg, axis=1)
        plan = {
            "num_poses": int(len(poses)),
            "num_paths": len(clips),
            "path_length_m": float(steps.sum()),
            "loop_closure_m": float(np.linalg.norm(centres[-1] - centres[0])),
            "step_cv": float(steps.std() / steps.mean()) if len(steps) and steps.mean() > 0 else float("nan"),
        }
        if self.artifact("trajectory") is not None:  # sector exploration as the trajectory stage measured it
            info = self.manifest("trajectory").get("info") or {}
            plan.update({k: info[k] for k in ("sectors_covered", "sectors_reachable") if k in info})
        if self.artifact("navmesh") is not None:  # how far the plan gets from the capture point (roam protocol)
            from panoworld.geometry.navmesh import load_navmesh
            from panoworld.tools.eval.roam import trajectory_reach

            plan.update(trajectory_reach(load_navmesh(self.artifact("navmesh")), poses))
        try:
            clearance = self.gt.clearance(centres)
        except NoReference as e:
            why = unavailable(str(e))
            return {**plan, **{k: why for k in ("min_clearance_m", "mean_clearance_m", "clear_fraction", "path_collisions")}}
        radius, radius_src = NavMeshParams().agent_radius_m, "NavMeshParams default (navmesh not run)"
        if self.artifact("navmesh") is not None:
            doc = json.loads((self.artifact("navmesh") / "navmesh.json").read_text())
            radius, radius_src = float(doc["agent"]["agent_radius_m"]), "navmesh.json"
        moving = steps > 1e-9
        free = self.gt.cast(centres[a][moving], seg[moving] / steps[moving, None])
        return {
            **plan,
            "min_clearance_m": float(clearance.min()),
            "mean_clearance_m": float(clearance.mean()),
            "clear_fraction": float(np.mean(clearance >= radius)),
            "agent_radius_m": radius,
            "agent_radius_source": radius_src,
            "path_collisions": int(np.sum(free < steps[moving])),
        }

    def conditions_stage(self) -> dict:
        cond = self.conditions
        idx = self._frames(len(cond))
        if not idx:
            return unavailable("conditions hold only frame 0 (the source view); nothing to evaluate")
        ps, ious, dabs, hole_fraction = [], [], [], []
        inter = union = 0
        no_mesh: dict | None = None
        H, W = cond.height, cond.width
        for i in self._bar(idx, "eval conditions"):
            frame = cond.frame(i)
            gt_rgb, gt_depth = self.gt.render(cond.poses[i], H, W)
            if frame.mask.any():
                ps.append(psnr(frame.rgb, gt_rgb, frame.mask))
            hole = ~frame.mask
            hole_fraction.append(float(hole.mean()))
            if no_mesh is not None:
                continue
            try:
                hole_true = true_disocclusion(self.gt, np.eye(4), cond.poses[i], H, W, self.params.disocclusion_tol)
            except NoReference as e:
                no_mesh = unavailable(f"true disocclusion {e}")
                continue
            inter += int(np.logical_and(hole, hole_true).sum())
            union += int(np.logical_or(hole, hole_true).sum())
            if not math.isnan(v := iou(hole, hole_true)):
                ious.append(v)
            if cond.depth is not None and np.isfinite(gt_depth).any():
                dabs.append(depth_errors(frame.depth, gt_depth, frame.mask)["abs_rel"])
        return {
            "frames_evaluated": len(idx),
            "psnr_valid": _mean(ps),
            "mask_iou": no_mesh or (inter / union if union else float("nan")),
            "mask_iou_frame_mean": no_mesh or _mean(ious),
            "hole_fraction": _mean(hole_fraction),
            "depth_abs_rel": _mean(dabs) if dabs else unavailable("the conditions or the ground truth have no depth"),
        }

    def video_stage(self) -> dict:
        import cv2

        from panoworld.io.depth_png import read_depth_png
        from panoworld.io.video import load_frames

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
            if video.has_depth and np.isfinite(gt_depth).any():
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
            "depth_abs_rel": _mean(acc["depth"]) if acc["depth"] else unavailable("the video or the ground truth has no depth"),
            "resolution": f"{H}x{W}",
            **fid_fvd_per_scene(),
        }

    def poses(self) -> dict:
        from panoworld.geometry.align import trajectory_metrics
        from panoworld.poses.estimate import load_poses

        est = load_poses(self._need("poses"))
        gt, source = self.reference_poses()
        if est.world_from_cam.shape != gt.shape:
            raise ValueError(f"poses.json has {len(est.world_from_cam)} poses but the {source} {len(gt)}")
        reg = est.registered
        out: dict[str, Any] = {"num_frames": int(len(reg)), "registered_fraction": float(reg.mean()),
                               "ground_truth": source}
        if reg.sum() < 2:
            reason = f"only {int(reg.sum())} registered frame(s); Sim(3) alignment needs at least 2"
            return {**out, **{k: unavailable(reason) for k in POSE_METRICS}}
        m = trajectory_metrics(est.world_from_cam[reg], gt[reg])
        return {**out, **{k: m[k] for k in (*POSE_METRICS, "scale")}}

    def gaussians(self) -> dict:
        from panoworld.gaussians.fusion import uniform_subset
        from panoworld.io.splat_ply import read_gaussians_ply
        from panoworld.render.erp import render_erp

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
            if self.gt.kind == "frames":
                novel, protocol = self._track_novel_views(novel, [poses[i] for i in used])
        H = self.params.gs_height
        out: dict[str, Any] = {"setting": f"{len(context)}@{len(novel)}", "context_frames": context,
                               "novel_protocol": protocol, "render_height": H}
        for name, views in (("context", [poses[i] for i in context]), ("novel", novel)):
            acc: dict[str, list[float]] = {"psnr": [], "ssim": [], "ws_psnr": [], "lpips": [], "coverage": []}
            try:
                refs = [self.gt.render(pose, H, 2 * H)[0] for pose in views]
            except NoReference as e:
                out.update({f"{name}_{k}": unavailable(str(e)) for k in ("psnr", "ssim", "ws_psnr", "lpips")})
                continue
            for pose, ref in zip(self._bar(views, f"eval gaussians {name}"), refs):
                r = render_erp(g, pose, H, 2 * H)
                img = (r.rgb.clamp(0, 1).numpy() * 255.0).round().astype(np.uint8)
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
        return {**out, **self._capture_scores(d / "gaussians.ply", H)}

    def _capture_scores(self, ply: Path, height: int) -> dict:
        """A home: the Gaussians at every registered capture pose against that panorama as the depth stage cleaned
        it (the capture rig removed, as the scene holds it; capture_psnr, at height rows): the lowest, its panorama
        and the median; {} for one panorama."""
        from panoworld.gaussians.quality import capture_psnr
        from panoworld.io.depth import read_panorama
        from panoworld.io.home import capture_poses, home_depth_dirs

        if self.artifact("register") is None or self.artifact("depth") is None:
            return {}
        dirs = home_depth_dirs(self.artifact("depth")) or {}
        captures = {n: T for n, T in capture_poses(self.artifact("register")).items() if n in dirs}
        if len(captures) < 2:
            return {}
        scores = capture_psnr(ply, captures, {n: read_panorama(dirs[n] / "panorama.png") for n in captures},
                              height=height)
        worst = min(scores, key=scores.get)
        return {"capture_psnr_min": scores[worst], "capture_worst": worst,
                "capture_psnr_median": float(np.median(list(scores.values())))}

    def _track_novel_views(self, midpoints: list[np.ndarray], used: list[np.ndarray]) -> tuple[list[np.ndarray], str]:
        """Frames + poses scenes: for each midpoint the nearest ground-truth track frame that no fused frame sits on."""
        cands = [(t, i, p) for t, track in enumerate(self.gt.tracks) for i, p in enumerate(track)
                 if min(np.linalg.norm(p[:3, 3] - u[:3, 3]) for u in used) > self.params.pose_tol_m]
        picked: list[tuple[int, int, np.ndarray]] = []
        for m in midpoints:
            free = [c for c in cands if all(c[:2] != q[:2] for q in picked)]
            if free:
                picked.append(min(free, key=lambda c: np.linalg.norm(c[2][:3, 3] - m[:3, 3])))
        return [c[2] for c in picked], (f"ground-truth track frames not fused, nearest to midpoints between context "
                                        f"frames: (track, frame) {[c[:2] for c in picked]}")

    def roam_settings(self):
        """The roam protocol's sizes: EvalParams where set, else 2 views, 256 rows, 256 px pinhole (ci-tiny: 1, 64, 64)."""
        from panoworld.tools.eval.roam import RoamSettings

        p, tiny = self.params, self.preset == "ci-tiny"
        return RoamSettings(views=p.roam_views or (1 if tiny else 2), height=p.roam_height or (64 if tiny else 256),
                            pinhole=p.roam_pinhole or (64 if tiny else 256), fov_deg=p.roam_fov_deg, seed=p.seed)

    def roam(self) -> dict:
        """The roam protocol (panoworld/tools/eval/roam.py) on the gaussians and navmesh artifacts."""
        from panoworld.geometry.navmesh import load_navmesh
        from panoworld.io.splat_ply import read_gaussians_ply
        from panoworld.io.video import load_frames
        from panoworld.tools.eval.roam import evaluate_roam

        g = read_gaussians_ply(self._need("gaussians") / "gaussians.ply")
        nav = load_navmesh(self._need("navmesh"))
        pano_path = next((p for p in (self.scene_dir / f"panorama.{e}" for e in ("png", "jpg", "jpeg")) if p.is_file()),
                         None)
        pano = load_frames([pano_path])[0] if pano_path else None
        on_view = None
        if self.roam_images is not None:
            from functools import partial

            from panoworld.tools.eval.roam import save_view

            on_view = partial(save_view, self.roam_images)
        return evaluate_roam(g, nav, self.gt, self.roam_settings(), self.lpips, panorama=pano, on_view=on_view,
                             bar=self._bar)

    def loop(self) -> dict:
        """First/last-frame loop metrics of a closed trajectory (the paper's Loop and LPIPS-Loop on ring paths)."""
        from panoworld.io.video import load_frames
        from panoworld.render.metrics import loop_closure_flow_deg
        from panoworld.trajectory import step_lengths

        poses, source = self.reference_poses()
        steps = step_lengths(poses)
        gap = float(np.linalg.norm(poses[-1, :3, 3] - poses[0, :3, 3]))
        tol = 1.5 * float(np.median(steps)) if len(steps) else 0.0
        if len(poses) < 3 or gap > tol:
            return unavailable(f"not a closed path: the last camera of the {source} is {gap:.3f} m from the first "
                               f"(> 1.5 steps = {tol:.3f} m); loop metrics are for ring trajectories "
                               "(--set trajectory.kind=ring)")
        video = self.video
        first, last = load_frames([video.rgb[0], video.rgb[-1]])
        out: dict[str, Any] = {"loop_gap_m": gap, "loop_flow_deg": loop_closure_flow_deg(first, last),
                               "loop_psnr": psnr(first, last),
                               "lpips_loop": self.lpips.distance(first, last) if self.lpips.enabled else self.lpips.reason()}
        try:  # the same score between the true views at the two ends: what a perfect video would get
            H, W = first.shape[:2]
            out["loop_flow_deg_reference"] = loop_closure_flow_deg(self.gt.render(poses[0], H, W)[0],
                                                                   self.gt.render(poses[-1], H, W)[0])
        except NoReference as e:
            out["loop_flow_deg_reference"] = unavailable(str(e))
        return out

    STAGES: dict[str, str] = {
        "depth": "depth", "register": "register", "mesh": "mesh", "navmesh": "navmesh", "trajectory": "trajectory",
        "conditions": "conditions_stage", "video": "video_stage", "loop": "loop", "poses": "poses",
        "gaussians": "gaussians", "roam": "roam",
    }
    ARTIFACT = {"loop": "video", "roam": "gaussians"}
    """Report sections that are not stage names: the artifact they read."""

    def run(self, stages: list[str] | None = None) -> tuple[dict[str, dict], list[str]]:
        """({stage: metrics or unavailable(reason)}, [stages whose existing artifact could not be evaluated])."""
        results, errors = {}, []
        for stage in stages or list(self.STAGES):
            art = self.ARTIFACT.get(stage, stage)
            if self.artifact(art) is None:
                results[stage] = unavailable(f"not run: no {ARTIFACTS_DIRNAME}/{art}/{MANIFEST}; "
                                             f"`python runner.py run SCENE --until {art}` makes it")
                continue
            try:
                results[stage] = getattr(self, self.STAGES[stage])()
            except NotRun as e:
                results[stage] = unavailable(f"needs the {e.stage} artifact, which is not run")
            except NoReference as e:
                results[stage] = unavailable(str(e))
            except Exception as e:  # a corrupt or foreign artifact must not stop the other stages
                results[stage] = unavailable(f"error: {type(e).__name__}: {e}")
                errors.append(stage)
        return results, errors
