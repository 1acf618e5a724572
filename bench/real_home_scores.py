"""How a built home reads at a pose: the Gaussians rendered against a panorama (PSNR, SSIM, coverage; seen / unseen
and per surface), the pixels another panorama sees, the panoramas as the run cleaned and levelled them."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def home_sources(scene: Path, poses: dict[str, np.ndarray]) -> tuple[dict, dict]:
    """{NAME: cleaned rgb}, {NAME: cleaned depth (0 = none)} of the run's depth artifact for the posed panoramas."""
    from panoworld.io.home import home_depth_dirs
    from panoworld.room.home_sources import home_sources as prepared

    _, rgbs, depths, _ = prepared(home_depth_dirs(scene / "artifacts" / "depth"), poses)  # as the gaussians stage
    return rgbs, depths


def outside_rig(rig_mask: Path, height: int, grow_px: int = 2) -> np.ndarray | None:
    """(height, 2 height) bool: the pixels no part of the removed rig (its mask at height rows, grown by grow_px)
    touches; None where no rig was removed."""
    from panoworld.io.images import read_rig_mask

    if not rig_mask.is_file():
        return None
    m = cv2.resize(read_rig_mask(rig_mask).astype(np.float32), (2 * height, height), interpolation=cv2.INTER_AREA) > 0
    return ~cv2.dilate(m.astype(np.uint8), np.ones((2 * grow_px + 1, 2 * grow_px + 1), np.uint8)).astype(bool)


def render_scores(g, pose: np.ndarray, rgb: np.ndarray, height: int, seen: np.ndarray | None = None,
                  surfaces: dict[str, np.ndarray] | None = None) -> dict:
    """PSNR, SSIM and coverage of the Gaussians g rendered at pose against rgb (area-downsampled to height rows),
    over the sphere and, with seen (height, 2 height) bool, over the seen and unseen pixels; on the seen pixels also
    the PSNR after one least-squares gain per channel (the captures' exposures differ) and per surface (surfaces:
    surface_masks)."""
    from panoworld.render.erp import render_erp
    from panoworld.render.metrics import psnr, ssim_map

    ref = cv2.resize(rgb, (2 * height, height), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    out = render_erp(g, pose, height, 2 * height)
    img = np.clip(np.asarray(out.rgb, np.float32), 0, 1)
    alpha = np.asarray(out.alpha, np.float32)
    smap = np.asarray(ssim_map(img, ref, data_range=1.0), np.float32)
    if smap.ndim == 3:
        smap = smap.mean(-1)
    res = {"psnr": psnr(img, ref, data_range=1.0), "ssim": float(smap.mean()), "coverage": float((alpha > 0.5).mean())}
    if seen is not None:
        for key, m in (("seen", seen), ("unseen", ~seen)):
            if m.any():
                res[key] = {"share": float(m.mean()), "psnr": psnr(img, ref, m, data_range=1.0),
                            "ssim": float(smap[m].mean()), "coverage": float((alpha[m] > 0.5).mean())}
        if seen.any():
            gain = (img[seen] * ref[seen]).sum(0) / np.maximum((img[seen] ** 2).sum(0), 1e-12)
            res["seen"].update(gain=[float(x) for x in gain],
                               psnr_gain_matched=psnr(np.clip(img * gain, 0, 1), ref, seen, data_range=1.0))
            for key, m in (surfaces or {}).items():
                if (m & seen).any():
                    res["seen"][key] = {"share": float((m & seen).sum() / seen.sum()),
                                        "psnr": psnr(img, ref, m & seen, data_range=1.0)}
    return res


def surface_masks(depth: np.ndarray, height: int) -> dict[str, np.ndarray]:
    """{"floor", "ceiling", "walls"}: (height, 2 height) bool masks of a panorama's pixels by the surface its ray
    depth puts them on: within 3 cm of its floor's or its ceiling's distance (plane_distance), or any other depth."""
    from panoworld.core.conventions import erp_dirs64
    from panoworld.geometry.floor_view import plane_distance
    from panoworld.geometry.resize import resize_depth

    d = resize_depth(depth, height, 2 * height)
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    y = erp_dirs64(height, 2 * height)[..., 1] * d
    out = {}
    for key, sign in (("floor", 1.0), ("ceiling", -1.0)):
        h = plane_distance(d, below=sign > 0)
        out[key] = (d > 0) & (np.abs(sign * y - h) < 0.03) if h is not None else np.zeros(d.shape, bool)
    out["walls"] = (d > 0) & ~out["floor"] & ~out["ceiling"]
    return out


def seen_by_others(name: str, poses: dict, depths: dict, height: int) -> np.ndarray:
    """(height, 2 height) bool: pixels of panorama name whose surface (its cleaned depth) another panorama sees."""
    from panoworld.core.conventions import erp_dirs, transform_points
    from panoworld.gaussians.home import SourcesVisibility
    from panoworld.gaussians.pixel import SourceVisibility
    from panoworld.geometry.resize import resize_depth

    d = resize_depth(depths[name], height, 2 * height)
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    pts = transform_points(poses[name], erp_dirs(height, 2 * height, np.float64).reshape(-1, 3) * d.reshape(-1, 1))
    others = SourcesVisibility([SourceVisibility(depths[n], poses[n], 0.03) for n in poses if n != name])
    return (others.explained(pts) & (d.reshape(-1) > 0)).reshape(height, 2 * height)


def nearest_vertex_m(scene: Path, poses: dict[str, np.ndarray]) -> dict[str, float]:
    """{NAME: distance (m) from that capture point to the nearest vertex of the fused mesh}."""
    import trimesh
    from scipy.spatial import cKDTree

    m = trimesh.load(scene / "artifacts" / "mesh" / "mesh.ply", process=False)
    tree = cKDTree(np.asarray(m.vertices))
    return {n: float(tree.query(T[:3, 3])[0]) for n, T in poses.items()}


def input_as_built(scene: Path, name: str) -> np.ndarray:
    """The input panorama `name` of a home that ran, levelled as the depth stage levelled it (a camera taken off
    level: the scene is built in the levelled camera's frame, docs/conventions.md)."""
    from panoworld.geometry.level import levelled
    from panoworld.io.depth import read_panorama
    from panoworld.io.home import levelled_panoramas

    raw = read_panorama(next((scene / "panoramas").glob(f"{name}.*")))
    R = levelled_panoramas(scene / "artifacts" / "depth").get(name)
    return raw if R is None else levelled(raw, R)
