"""The report's Gaussian section: the stage's preview and ERP renders from context and novel poses beside video frames."""

from __future__ import annotations

import html
import time

import numpy as np

from panoworld.tools.report import encode as enc
from panoworld.tools.report.page import Section, figure, fmt, missing, table
from panoworld.tools.report.scene_data import ReportParams, SceneData


def render_poses(poses: np.ndarray, context: list[int], k: int) -> list[tuple[str, int, np.ndarray]]:
    """Up to k (label, nearest video frame, world_from_cam): the middle context frame, then midpoints between
    consecutive frames spread along the path (novel poses: no frame was generated exactly there)."""
    from panoworld.tools.eval.cli import interpolate_pose

    out: list[tuple[str, int, np.ndarray]] = []
    if k <= 0 or len(poses) == 0:
        return out
    ctx = [i for i in context if 0 <= i < len(poses)] or [0]
    c = ctx[len(ctx) // 2]
    out.append((f"context pose (frame {c})", c, poses[c]))
    if len(poses) >= 2:
        for a in np.linspace(0, len(poses) - 2, max(k - 1, 0) + 2)[1:-1].round().astype(int):
            out.append((f"novel pose (midway frames {a}-{a + 1})", int(a), interpolate_pose(poses[a], poses[a + 1], 0.5)))
    return out[:k]


def pinhole_from_erp(erp: np.ndarray, size: int, fov_deg: float) -> np.ndarray:
    """The forward (+z) pinhole view (size, size) with fov_deg horizontal field of view resampled from an ERP image."""
    import cv2

    from panoworld.core.conventions import erp_pixel_from_dir

    f = size / 2 / np.tan(np.deg2rad(fov_deg) / 2)
    jj, ii = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    d = np.stack([(jj - size / 2) / f, (ii - size / 2) / f, np.ones_like(jj)], -1)
    u, v = erp_pixel_from_dir(d, erp.shape[0], erp.shape[1])
    return cv2.remap(erp, (u - 0.5).astype(np.float32), (v - 0.5).astype(np.float32), cv2.INTER_AREA
                     if erp.shape[0] > 2 * size else cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def _renders(scene: SceneData, d, info: dict, poses: np.ndarray, vframes: list, params: ReportParams):
    """Forward pinhole renders of the Gaussians (one cube face: about a quarter of an ERP render's CPU time) at a context pose and
    novel poses, each beside the same view cut out of the nearest video frame (from that frame's own pose)."""
    import torch

    from panoworld.io.splat_ply import read_gaussians_ply
    from panoworld.render.splats import render_perspective

    pairs, notes = [], []
    size, fov = params.gs_height, 90.0
    f = size / 2 / np.tan(np.deg2rad(fov) / 2)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # multi-threaded CPU torch was up to 10x slower on a shared 2-core machine
    t0 = time.perf_counter()
    try:
        g = read_gaussians_ply(d / "gaussians.ply")
    except (OSError, ValueError, KeyError) as e:
        torch.set_num_threads(threads)
        return pairs, [f"gaussians.ply unreadable: {e}"]
    views = render_poses(poses, [int(i) for i in info.get("frames", [])], params.gs_views)
    done = 0
    try:
        for label, near, pose in views:
            if done and time.perf_counter() - t0 > params.gs_budget_s:
                break
            out = render_perspective(g, pose, f, f, size / 2, size / 2, size, size, background=(0.0, 0.0, 0.0))
            img = (out.rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
            cov = float((out.alpha.numpy() > 0.5).mean())
            fig = figure(enc.data_uri(img), f"Gaussians: {label}, forward {fov:.0f} deg view, coverage {100 * cov:.1f} %",
                         small=True)
            frame = enc.read_rgb(vframes[near]) if 0 <= near < len(vframes) else None
            if frame is not None:
                fig += figure(enc.data_uri(pinhole_from_erp(frame, size, fov)), f"video frame {near}, same view from its own pose",
                              small=True)
            pairs.append(fig)
            done += 1
    finally:
        torch.set_num_threads(threads)
    notes.append(f"{done} of {len(views)} renders ({size}x{size}, {len(g.means)} Gaussians) in "
                 f"{time.perf_counter() - t0:.1f} s with panoworld.render.splats on the CPU (reading the .ply included; "
                 f"budget {params.gs_budget_s:.0f} s: --gs-views, --gs-height, --gs-budget-s)")
    return pairs, notes


def section_gaussians(scene: SceneData, params: ReportParams) -> Section:
    title = "Gaussians: renders beside video frames"
    if not scene.has("gaussians"):
        return missing("gaussians", title, "the gaussians stage has not run yet")
    d = scene.dir("gaussians")
    info = scene.info("gaussians")
    video = scene.video()
    vframes = [] if video is None else video.rgb
    w = params.image_width

    def video_frame(i: int) -> str:
        if 0 <= i < len(vframes):
            img = enc.read_rgb(vframes[i], w)
            if img is not None:
                return figure(enc.data_uri(img), f"video frame {i}")
        return '<p class="note">video frame unavailable</p>'

    pairs = []
    notes = []
    evals = info.get("eval") or []
    prev = enc.read_rgb(d / "preview.png", w)
    if prev is not None:
        f0 = int(evals[0]["frame"]) if evals else int((info.get("frames") or [0])[0])
        psnr = f", PSNR {evals[0]['psnr']:.2f} dB" if evals and isinstance(evals[0].get("psnr"), (int, float)) else ""
        pairs.append(figure(enc.data_uri(prev), f"stage preview.png: context frame {f0} re-rendered{psnr}") + video_frame(f0))
    pa = scene.poses_artifact()
    poses = scene.video_poses() if pa is None else pa.world_from_cam
    if params.gs_views > 0 and poses is not None:
        r_pairs, r_notes = _renders(scene, d, info, poses, vframes, params)
        pairs += r_pairs
        notes += r_notes
    rows = [[k, fmt(info.get(k))] for k in ("backend", "num_gaussians", "voxel_size", "context_psnr", "context_psnr_covered", "depth_source") if k in info]
    if info.get("frames"):
        rows.append(["context frames", ", ".join(map(str, info["frames"]))[:200]])
    rows += [["warning", w_] for w_ in info.get("warnings", [])]
    body = ("".join(f'<div class="row">{p}</div>' for p in pairs)
            + "".join(f'<p class="note">{html.escape(n)}</p>' for n in notes) + table(["gaussians", "value"], rows))
    return Section("gaussians", title, body)
