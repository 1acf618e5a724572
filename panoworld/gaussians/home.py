"""One Gaussian scene over a home: every capture panorama as per-pixel Gaussians at its registered pose (each surface
from the panorama that sees it nearest), the video frames voxel-fused where no panorama sees."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from panoworld.core.conventions import erp_dirs64, invert_pose, transform_points
from panoworld.core.errors import InputError
from panoworld.core.memory import release_free_memory
from panoworld.core.parallel import cpu_threads, map_ahead
from panoworld.core.progress import bar as progress_bar
from panoworld.gaussians.capture_fit import fit_capture_colors
from panoworld.gaussians.fusion import ContextSource
from panoworld.gaussians.fusion_params import SourcePixelParams
from panoworld.gaussians.pixel import SourceVisibility, fuse_unseen, merge_gaussians, pixel_gaussians
from panoworld.geometry.panoramas import depth_along, erp_pixel_index, nearest_source
from panoworld.geometry.resize import rgbd_at_height
from panoworld.io.gaussian_set import FusionResult, Gaussians
from panoworld.room.plausible import NEAR_PLANE_M


class SourcesVisibility:
    """What any of several source panoramas sees (SourceVisibility of each, or-ed)."""

    def __init__(self, sources: list[SourceVisibility]):
        self.sources = sources
        self.centres = np.array([invert_pose(s.cam_from_world)[:3, 3] for s in sources])

    def explained(self, points: np.ndarray) -> np.ndarray:
        """(M,) bool: SourceVisibility.explained by any source. The sources are asked nearest to the points' mean
        first, each only about the points the nearer ones left (most of a frame is explained by one source)."""
        explained = np.zeros(len(points), bool)
        if not len(points):
            return explained
        rest = np.arange(len(points))
        for k in np.argsort(np.linalg.norm(self.centres - points.mean(0), axis=1)):
            e = self.sources[k].explained(points[rest])
            explained[rest[e]] = True
            rest = rest[~e]
            if not len(rest):
                break
        return explained

    def poking_through(self, g) -> np.ndarray:
        """(N,) bool: SourceVisibility.poking_through of any source."""
        return np.logical_or.reduce([s.poking_through(g) for s in self.sources])


def depth_from_others(k: int, names: list[str], depths: dict[str, np.ndarray], world_from_cam: dict[str, np.ndarray],
                      *, height: int = 128) -> np.ndarray:
    """(H, W) ray distance, from panorama names[k] (depths[names[k]] is (H, W)), of the nearest surface the other
    panoramas see (their depth (h, w), 0 = none, as points at their poses), 0 where none: a z-buffer at `height` rows
    (coarse, so the others' points leave no cracks between them; one-pixel gaps closed from the nearest neighbour),
    nearest-upsampled to (H, W)."""
    H, W = depths[names[k]].shape
    h = min(height, H)
    w = 2 * h
    zbuf = np.full(h * w, np.inf)
    cam_from_world = invert_pose(world_from_cam[names[k]])
    for j, other in enumerate(names):
        d = np.asarray(depths[other], np.float64)
        ok = np.isfinite(d) & (d > 0)
        if j == k or not ok.any():
            continue
        pts = erp_dirs64(*d.shape)[ok] * d[ok][:, None]
        p = transform_points(cam_from_world @ world_from_cam[other], pts)
        rows, cols = erp_pixel_index(p, h, w)
        np.minimum.at(zbuf, rows * w + cols, np.linalg.norm(p, axis=1))
    z = zbuf.reshape(h, w)
    hole = ~np.isfinite(z)
    if hole.any():
        from scipy import ndimage

        near = ndimage.minimum_filter(np.where(hole, np.inf, z), size=3, mode="wrap")
        z = np.where(hole, near, z)
    z = np.where(np.isfinite(z), z, 0.0)
    rows = np.minimum((np.arange(H) + 0.5) * h / H, h - 1).astype(int)
    cols = np.minimum((np.arange(W) + 0.5) * w / W, w - 1).astype(int)
    return z[rows][:, cols]


def complete_from_others(k: int, names: list[str], depths: dict[str, np.ndarray], world_from_cam: dict[str, np.ndarray]
                         ) -> np.ndarray:
    """depths[names[k]] (H, W) with its pixels without depth (0: implausible layout masked, doorway lines dropped)
    given the depth of the nearest surface the other panoramas see along their ray (depth_from_others at H / 4 rows),
    float32; the same array when it has no such pixel."""
    depth = depths[names[k]]
    hole = ~(np.isfinite(depth) & (depth > 0))
    if not hole.any():
        return depth
    fill = depth_from_others(k, names, depths, world_from_cam, height=max(8, depth.shape[0] // 4))
    return np.where(hole, fill, depth).astype(np.float32)


def seen_through(k: int, pts_world: np.ndarray, names: list[str], depths: dict[str, np.ndarray],
                 world_from_cam: dict[str, np.ndarray], *, tol: float) -> np.ndarray:
    """(M,) bool for surface points (M, 3) of panorama names[k]: another panorama saw through them, i.e. its depth
    along the point's ray, the nearest over the 3 x 3 pixels around it (no evidence where any is unknown), lies
    beyond the point by more than tol in log range. A surface standing in the space another capture saw empty (a
    layout annotation's doorway wall seen from the next room) is not there."""
    from scipy import ndimage

    out = np.zeros(len(pts_world), bool)
    for j, other in enumerate(names):
        d = np.asarray(depths[other], np.float64)
        d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
        if j == k or not d.any():
            continue
        near = ndimage.minimum_filter(d, size=3, mode="wrap")
        p = transform_points(invert_pose(world_from_cam[other]), pts_world)
        r = np.linalg.norm(p, axis=1)
        d_j = depth_along(near, p)
        out |= (d_j > 0) & (np.log(np.maximum(d_j, 1e-6) / np.maximum(r, 1e-6)) > tol)
    return out


def own_fill(k: int, names: list[str], depths: dict[str, np.ndarray], world_from_cam: dict[str, np.ndarray], scene,
             others: SourcesVisibility, *, height: int, tol: float) -> np.ndarray | None:
    """(h, w) depth (0 = none; h = `height` rows at most) for panorama names[k]'s pixels without depth (depths (0 =
    none)) but those next to one with depth: the nearest of what the scene (Gaussians) shows along the pixel's ray
    from the capture point (render_erp's depth where its alpha > 0.5, farther than NEAR_PLANE_M: nothing stands
    where the rig stood), the median of the panorama's own depth, and
    just in front of the nearest surface another panorama measured along the ray (depth_from_others, / (1 + 2 tol)),
    so the pixel's own Gaussian stands in front of whatever else its capture point sees there; kept only where no
    other panorama's depth explains that point (`others`: the other panoramas' SourcesVisibility at tolerance tol; on
    or in front of a surface another panorama measured, seen from there), so no other capture point sees it. None when it has no
    pixel without depth."""
    from scipy import ndimage

    from panoworld.geometry.resize import resize_depth
    from panoworld.render.erp import render_erp

    n = names[k]
    depth = depths[n]
    if depth.shape[0] > height:
        depth = np.nan_to_num(resize_depth(depth, height, 2 * height), nan=0.0, posinf=0.0)
    hole = ~(np.isfinite(depth) & (depth > 0))
    if not hole.any() or len(scene) == 0:
        return None
    h, w = depth.shape
    inner = ndimage.binary_erosion(np.pad(hole, ((1, 1), (0, 0)), mode="edge"), np.ones((3, 3)), border_value=1)
    fill = inner[1:-1]
    if not fill.any():
        return np.zeros((h, w), np.float32)
    out = render_erp(scene, world_from_cam[n], h, w, supersample=1, pixels=fill)  # only fill's pixels are read
    shown, alpha = np.asarray(out.depth, np.float64), np.asarray(out.alpha, np.float64)
    del out
    release_free_memory()  # the render's temporaries, before the next panorama's
    reach = float(np.median(depth[~hole])) if not hole.all() else np.inf
    d = np.where((alpha > 0.5) & np.isfinite(shown) & (shown > NEAR_PLANE_M), np.minimum(shown, reach), reach)
    nearer = depth_from_others(k, names, {**depths, n: depth}, world_from_cam, height=h)
    d = np.where(nearer > 0, np.minimum(d, nearer / (1.0 + 2.0 * tol)), d)
    fill &= np.isfinite(d)
    pts = transform_points(world_from_cam[n], erp_dirs64(h, w)[fill] * d[fill][:, None])
    fill[fill] = ~others.explained(pts)
    return np.where(fill, d, 0.0).astype(np.float32)


def add_own_fill(result: FusionResult, names: list[str], rgbs: dict[str, np.ndarray], depths: dict[str, np.ndarray],
                 world_from_cam: dict[str, np.ndarray], params: SourcePixelParams, *, progress: bool = False):
    """(result.gaussians (the sources' per-pixel Gaussians first, result.num_source of them, then the frames' voxel
    ones) with every source's own fill of its pixels without depth (rgbs, depths (0 = none), each pair at one size):
    per-pixel Gaussians at params.source_fill_height rows where own_fill places them, a surface two fills share kept
    by the source nearer it (nearest_source over the fills), none in front of another source's fill seen from that
    source's capture point (by more than params.source_tol), less those whose splat reaches through a surface another
    source saw (SourcesVisibility.poking_through); the voxel Gaussians a fill stands for (on it or in front of it from
    its capture point, params.source_tol) dropped. Second: {NAME: {"filled": its fill's Gaussians, "stood_for": the
    voxel Gaussians it dropped}} of the sources with pixels without depth.) progress: a bar per source (core.progress.bar)."""
    g = result.gaussians
    height = min(params.source_fill_height, min(d.shape[0] for d in depths.values()))
    vis = {n: SourceVisibility(depths[n], world_from_cam[n], params.source_tol, NEAR_PLANE_M) for n in names}
    others = {n: SourcesVisibility([vis[m] for m in names if m != n]) for n in names}
    bar = progress_bar(names, desc="own fill", unit="panorama", on=progress, leave=False)
    fills = {n: f for k, n in enumerate(bar) if (f := own_fill(k, names, depths, world_from_cam, g, others[n],
                                                                 height=height, tol=params.source_tol)) is not None}
    if not fills:
        return g, {}
    keep = np.ones(len(g), bool)
    at = np.arange(result.num_source, len(g))
    means = np.asarray(g.means, np.float64)[at]
    fill_names = list(fills)
    pix_params = replace(params, scale_factor=params.source_scale)
    parts, stats = [], {}
    for k, n in enumerate(fill_names):
        d = fills[n]
        h, w = d.shape
        stood_for = at[SourceVisibility(d, world_from_cam[n], params.source_tol).explained(means)]
        pts = transform_points(world_from_cam[n], erp_dirs64(h, w).reshape(-1, 3) * d.reshape(-1, 1))
        own = nearest_source(k, pts, fill_names, fills, world_from_cam, tol=params.source_tol)
        for m in fill_names:  # nor in front of another fill, seen from that one's capture point
            if m != n:
                p = transform_points(invert_pose(world_from_cam[m]), pts)
                d_m = depth_along(fills[m], p)
                own &= ~((d_m > 0) & (np.linalg.norm(p, axis=1) < d_m * (1.0 - params.source_tol)))
        own = own.reshape(h, w)
        rgb = rgbs[n] if rgbs[n].shape[0] == h else cv2.resize(rgbs[n], (w, h), interpolation=cv2.INTER_AREA)
        fill = pixel_gaussians(rgb, np.where(own, d, 0.0).astype(np.float32), world_from_cam[n], pix_params)
        parts.append(fill.subset(~others[n].poking_through(fill)))
        stats[n] = {"filled": len(parts[-1]), "stood_for": int(np.count_nonzero(keep[stood_for]))}
        keep[stood_for] = False
    return merge_gaussians([g.subset(keep)] + parts), stats


def home_anchored_fusion(frames: ContextSource | None, sources: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
                         params: SourcePixelParams, *, progress: bool = False) -> FusionResult:
    """Per-pixel Gaussians of every source {NAME: (rgb (H, W, 3), depth (H, W) metres (0 = unknown), world_from_cam)}
    at most params.source_height rows (0 = as given), a pixel kept only when no other source sees its surface from
    nearer (geometry.panoramas.nearest_source: no doubled surfaces) nor saw through it (seen_through, tolerance
    params.source_carve_tol; 0 = not checked), plus voxel fusion of what the frames see that no
    source does (SourceVisibility of each, tolerance params.source_tol; nor within NEAR_PLANE_M of a capture point,
    where the rig stood, whatever its depth there) in voxels of params.unseen_voxel_size (0 =
    params.voxel_size), less those poking through a surface a source saw: source_anchored_fusion of a single panorama,
    over several. params.source_complete: each source's pixels without depth first take the others'
    (complete_from_others). frames None: the panoramas' Gaussians alone (what the captures themselves show).
    params.source_fill: each source's pixels without depth then get its own per-pixel Gaussians where the scene shows
    a surface no other source sees (own_fill), and the frames' voxel Gaussians they stand for (on that fill or in front
    of it, within params.source_tol) are dropped (result.own_fill: add_own_fill's figures); which source keeps a
    surface is decided by the measured depths alone.
    params.capture_fit_iters > 0: the colours are then fitted at every capture pose to its panorama
    (fit_at_capture_points; result.color_fit: its figures, RMSE per panorama before and after)."""
    names = list(sources)
    if not names:
        raise InputError("home fusion: no panorama to build from; give at least one panorama with its depth and pose")
    tol = params.source_tol
    small = {n: rgbd_at_height(sources[n][0], sources[n][1], params.source_height) for n in names}
    depths = {n: small[n][1] for n in names}
    poses = {n: np.asarray(sources[n][2], np.float64) for n in names}
    observed = depths
    if params.source_complete:
        depths = {n: complete_from_others(k, names, depths, poses) for k, n in enumerate(names)}
    pix_params = replace(params, scale_factor=params.source_scale)

    def source_part(k: int) -> Gaussians:  # panorama k's pixel Gaussians of the surfaces no other sees from nearer
        n = names[k]
        rgb, depth = small[n][0], depths[n]
        h, w = depth.shape
        pts = transform_points(poses[n], erp_dirs64(h, w).reshape(-1, 3) * depth.reshape(-1, 1))
        keep = nearest_source(k, pts, names, depths, poses, tol=tol)
        if params.source_carve_tol > 0:
            keep &= ~seen_through(k, pts, names, observed, poses, tol=params.source_carve_tol)
        keep = keep.reshape(h, w)
        return pixel_gaussians(rgb, np.where(keep & (depth > 0), depth, 0.0).astype(np.float32), poses[n], pix_params)

    parts = list(progress_bar(map_ahead(source_part, range(len(names)), workers=cpu_threads(2)), total=len(names),
                              desc="panorama pixels", unit="panorama", on=progress, leave=False))
    pix = merge_gaussians(parts)
    if frames is None:
        result = fuse_unseen(pix, [], None, params)
    else:
        seen = SourcesVisibility([SourceVisibility(depths[n], poses[n], tol, NEAR_PLANE_M) for n in names])
        result = fuse_unseen(pix, frames, seen, params, unseen_voxel_size=params.unseen_voxel_size, progress=progress)
    del pix, parts
    release_free_memory()
    if params.source_fill:
        result.gaussians, result.own_fill = add_own_fill(result, names, {n: small[n][0] for n in names}, observed,
                                                         poses, params, progress=progress)
    if params.capture_fit_iters > 0:
        result.gaussians, result.color_fit = fit_at_capture_points(result.gaussians, names, sources, poses, params,
                                                                   progress=progress)
    return result


CAPTURE_FIT_MIN_HEIGHT = 64
"""The lowest ERP height the capture fit falls back to when its render operators exceed capture_fit_max_gb."""


def fit_at_capture_points(g, names: list[str], sources: dict, poses: dict, params: SourcePixelParams, *,
                          progress: bool = False):
    """g with its colours fitted at every capture pose (capture_fit.fit_capture_colors at params.capture_fit_height
    rows) and the fit's figures, per panorama. While its operators would exceed params.capture_fit_max_gb the fit
    tries, at each height, capture_fit_prune and then capture_fit_prune_fallback where larger, and halves the height
    down to CAPTURE_FIT_MIN_HEIGHT; "reduced_from" lists what was refused (height, prune, why)."""
    views = [(sources[n][0], poses[n]) for n in names]
    prunes = sorted({params.capture_fit_prune, max(params.capture_fit_prune, params.capture_fit_prune_fallback)})
    tries, height = [], params.capture_fit_height
    while not tries or height >= CAPTURE_FIT_MIN_HEIGHT:
        tries += [(height, p) for p in prunes]
        height //= 2
    refused = []
    for k, (height, prune) in enumerate(tries):
        out, fit = fit_capture_colors(
            g, views, height=height, supersample=params.capture_fit_supersample,
            iters=params.capture_fit_iters, damping=params.capture_fit_damping,
            sh_degree=params.capture_fit_sh_degree, sh_damping=params.fit_sh_damping,
            max_bytes=params.capture_fit_max_gb * 1e9, prune=prune, smooth=params.capture_fit_smooth,
            min_psnr=params.capture_fit_min_psnr, max_rounds=params.capture_fit_max_rounds, progress=progress)
        if "skipped" not in fit or k == len(tries) - 1:  # the last try's refusal is the fit's "skipped"
            break
        refused.append({"height": height, "prune": prune, "why": fit["skipped"]})
    if refused:
        fit["reduced_from"] = refused
    if "skipped" in fit:
        return out, fit
    return out, {**fit, "rmse_before": dict(zip(names, fit["rmse_before"])),
                 "rmse_after": dict(zip(names, fit["rmse_after"])),
                 "rounds": [[names[k] for k in low] for low in fit["rounds"]]}
