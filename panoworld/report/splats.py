"""The report's Gaussian section: the stage's preview and ERP renders from context and novel poses beside video frames."""

from __future__ import annotations

import html
import time

import numpy as np

from panoworld.report import encode as enc
from panoworld.report.page import Section, figure, fmt, missing, table
from panoworld.report.scene import ReportParams, SceneData


def render_poses(poses: np.ndarray, context: list[int], k: int) -> list[tuple[str, int, np.ndarray]]:
    """Up to k (label, nearest video frame, world_from_cam): the middle context frame, then midpoints between
    consecutive frames spread along the path (novel poses: no frame was generated exactly there)."""
    from panoworld.evaluate import interpolate_pose

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


def section_gaussians(scene: SceneData, params: ReportParams) -> Section:
    title = "Gaussians: renders beside video frames"
    if not scene.has("gaussians"):
        return missing("gaussians", title, "the gaussians stage has not run yet")
    d = scene.dir("gaussians")
    info = scene.info("gaussians")
    vdoc = scene.json("video/video.json") or {}
    vframes = vdoc.get("frames", [])
    w = params.image_width

    def video_frame(i: int) -> str:
        if 0 <= i < len(vframes):
            img = enc.read_rgb(scene.dir("video") / vframes[i]["rgb"], w)
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
    poses = scene.poses("poses/poses.json")
    if poses is None:
        poses = scene.poses("video/video.json")
    if params.gs_views > 0 and poses is not None:
        from panoworld.render_gs import render_erp
        from panoworld.splat_ply import read_gaussians_ply

        import torch

        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # multi-threaded CPU torch is up to 10x slower on a shared 2-core machine
        t0 = time.perf_counter()
        try:
            g = read_gaussians_ply(d / "gaussians.ply")
        except (OSError, ValueError, KeyError) as e:
            g = None
            notes.append(f"gaussians.ply unreadable: {e}")
        views = render_poses(poses, [int(i) for i in info.get("frames", [])], params.gs_views) if g is not None else []
        done = 0
        for label, near, pose in views:
            if time.perf_counter() - t0 > params.gs_budget_s:
                break
            out = render_erp(g, pose, params.gs_height, 2 * params.gs_height, background=(0.0, 0.0, 0.0))
            img = (out.rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
            cov = float((out.alpha.numpy() > 0.5).mean())
            pairs.append(figure(enc.data_uri(img), f"render: {label}, {params.gs_height} rows, coverage {100 * cov:.1f} %")
                         + video_frame(near))
            done += 1
        torch.set_num_threads(threads)
        if views:
            notes.append(f"{done} of {len(views)} renders in {time.perf_counter() - t0:.1f} s "
                         f"(panoworld.render_gs.render_erp on the CPU; budget {params.gs_budget_s:.0f} s, --gs-views/--gs-budget)")
    rows = [[k, fmt(info.get(k))] for k in ("backend", "num_gaussians", "voxel_size", "context_psnr", "depth_source") if k in info]
    if info.get("frames"):
        rows.append(["context frames", ", ".join(map(str, info["frames"]))[:200]])
    rows += [["warning", w_] for w_ in info.get("warnings", [])]
    body = ("".join(f'<div class="row">{p}</div>' for p in pairs)
            + "".join(f'<p class="note">{html.escape(n)}</p>' for n in notes) + table(["gaussians", "value"], rows))
    return Section("gaussians", title, body)
