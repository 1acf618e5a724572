"""Back-side Gaussians: a thin wall's other side, where the floor a user walks sees behind it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from panoworld.core.conventions import erp_pixel_from_dir, points_from_depth
from panoworld.core.rotations import rotmat_from_quat
from panoworld.io.gaussian_set import Gaussians, rgb_to_sh_dc

CELL_M = 0.05
"""Edge of the floor-plan grid of sight_grid."""
BAND_M = (0.2, 1.7)
"""Heights above the floor whose source points block the sight (below a doorway's lintel, above skirting and rugs)."""
UPRIGHT = 0.35
"""Surfaces whose normal's vertical component is at most this (walls, within ~20 degrees) get a back side."""
RAYS = 720
"""Directions of sight_grid's rays (0.5 degrees: about a cell apart 5 m away)."""
SIGHT_STEP_M = 0.25
"""sight_grid looks from the NavMesh's points on a grid of this step."""
WINDOW = 3
"""A back-side point must lie behind every source depth within this many pixels of its own (not at a doorway's
jamb, where the source sees past the wall's edge); with back_side_edge_clear, within its thickness across
(edge_clear)."""
MAX_WINDOW = 32
"""edge_clear's largest window, pixels."""
PLANE_STEPS = (0.5, 1.0)
"""plane_clear's offsets along the wall, in thicknesses."""
SHELL_TOL = 0.05
"""on_shell: a source point lies on the room's shell when its horizontal distance from the capture point is within
this fraction of its ERP column's wall (panoworld.room.layout_columns.wall_columns)."""


@dataclass
class BackSides:
    """The back-side Gaussians and what was done, for the manifest."""

    gaussians: Gaussians
    stats: dict


def normals_facing(g: Gaussians, centre: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of flat Gaussians (their shortest axis), turned towards the point centre (3,)."""
    rot = rotmat_from_quat(torch.as_tensor(np.asarray(g.quats, np.float32))).numpy()
    axis = np.argmin(np.asarray(g.scales), axis=1)
    n = np.take_along_axis(rot, axis[:, None, None].repeat(3, 1), 2)[..., 0]
    flip = ((centre - np.asarray(g.means)) * n).sum(1) < 0
    n[flip] *= -1
    return n


def on_shell(means: np.ndarray, depth: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray | None:
    """(N,) bool: which points means (N, 3, world) lie on the walls of the room's shell as the source view (depth
    (H, W) metres at world_from_cam) shows it (wall_columns: a wall meets the ceiling or floor in sight; furniture
    in front of it does not), within SHELL_TOL; False in columns whose wall is unknown. None without a floor plane."""
    from panoworld.room.floor import fit_planes
    from panoworld.room.layout_columns import column_of, wall_columns

    valid = np.isfinite(depth) & (depth > 0)
    d = np.where(valid, depth, 0.0).astype(np.float64)
    floor_m, ceiling_m = fit_planes(d, valid)
    if floor_m is None:
        return None
    ceiling = -ceiling_m if ceiling_m is not None else -1e6
    walls = wall_columns(points_from_depth(d), valid, floor_m, ceiling, nearest=True)  # not a doorway's far wall
    pose = np.asarray(world_from_cam, np.float64)
    p = (np.asarray(means, np.float64) - pose[:3, 3]) @ pose[:3, :3]  # camera frame
    wall = walls.dist[column_of(p / np.maximum(np.linalg.norm(p, axis=1), 1e-12)[:, None], depth.shape[1])]
    with np.errstate(invalid="ignore"):
        return np.abs(np.hypot(p[:, 0], p[:, 2]) - wall) <= SHELL_TOL * wall


def edge_clear(p: np.ndarray, depth: np.ndarray, thickness: float, adaptive: bool = True) -> np.ndarray:
    """(N,) bool: which points p (N, 3, camera frame) lie behind the source depth (H, W) metres of every pixel within
    `thickness` metres across their ray (at least WINDOW pixels, at most MAX_WINDOW): a copy that far behind its
    surface is then not seen past a wall's edge (a doorway's jamb) from views up to 45 degrees off the wall's normal.
    adaptive=False: within WINDOW pixels whatever the distance."""
    import cv2

    d = np.where(np.isfinite(depth) & (depth > 0), depth, 1e6).astype(np.float32)
    dist = np.linalg.norm(p, axis=1)
    u, v = erp_pixel_from_dir(p / np.maximum(dist, 1e-12)[:, None], *depth.shape)
    j = np.mod(np.floor(u).astype(np.int64), depth.shape[1])
    i = np.clip(np.floor(v).astype(np.int64), 0, depth.shape[0] - 1)
    px = thickness / np.maximum(dist, 1e-6) * depth.shape[1] / (2 * np.pi)
    win = np.clip(np.ceil(px), WINDOW, MAX_WINDOW if adaptive else WINDOW).astype(np.int64)
    out = np.zeros(len(p), bool)
    for w in np.unique(win):
        sel = win == w
        d_max = cv2.dilate(d, np.ones((2 * w + 1, 2 * w + 1), np.uint8))
        out[sel] = dist[sel] > d_max[i[sel], j[sel]]
    return out


def plane_clear(p: np.ndarray, n: np.ndarray, depth: np.ndarray, thickness: float) -> np.ndarray:
    """(N,) bool: which copies p (N, 3, camera frame) of surfaces with unit normals n (N, 3, camera frame) would stay
    hidden (behind the source depth (H, W) metres within WINDOW pixels) if moved up to `thickness` metres along their
    wall's plane (horizontally and vertically, PLANE_STEPS): the wall goes on that far around the copy, so no view up to
    45 degrees off its normal sees it past a jamb or a lintel. Unlike edge_clear the test follows the wall, not the
    capture point's rays, so a wall seen at a grazing angle (its depth rising fast across the pixels) keeps its copies."""
    import cv2

    d = np.where(np.isfinite(depth) & (depth > 0), depth, 1e6).astype(np.float32)
    d_max = cv2.dilate(d, np.ones((2 * WINDOW + 1, 2 * WINDOW + 1), np.uint8))
    along = np.cross(n, [0.0, 1.0, 0.0])  # horizontal on the wall (y is down)
    along /= np.maximum(np.linalg.norm(along, axis=1, keepdims=True), 1e-12)
    up = np.cross(n, along)
    out = np.ones(len(p), bool)
    for t in PLANE_STEPS:
        for axis in (along, up):
            for sign in (1.0, -1.0):
                s = p + sign * t * thickness * axis
                dist = np.linalg.norm(s, axis=1)
                u, v = erp_pixel_from_dir(s / np.maximum(dist, 1e-12)[:, None], *depth.shape)
                j = np.mod(np.floor(u).astype(np.int64), depth.shape[1])
                i = np.clip(np.floor(v).astype(np.int64), 0, depth.shape[0] - 1)
                out &= dist > d_max[i, j]
    return out


def sight_grid(nav, blockers: np.ndarray, reach_m: float) -> tuple[np.ndarray, float, float]:
    """Floor-plan cells (CELL_M, x0 + j * CELL_M, z0 + i * CELL_M) in the line of sight of the NavMesh nav within
    reach_m: rays in RAYS directions from points of nav every SIGHT_STEP_M, each up to the first cell holding (or next
    to) one of the source's points blockers (M, 3) (what it saw between BAND_M; unseen space counts as free):
    (seen (n, m) bool, x0, z0)."""
    import cv2

    v = np.asarray(nav.vertices, np.float64)
    pad = reach_m + 2 * CELL_M
    x0, z0 = v.min(0) - pad
    m, n = (np.ceil((v.max(0) + pad - (x0, z0)) / CELL_M).astype(int) + 1)
    jz = ((blockers[:, 2] - z0) / CELL_M).astype(np.int64)
    jx = ((blockers[:, 0] - x0) / CELL_M).astype(np.int64)
    ok = (jx >= 0) & (jx < m) & (jz >= 0) & (jz < n)
    occupied = np.zeros((n, m), np.uint8)
    occupied[jz[ok], jx[ok]] = 1
    occupied = cv2.dilate(occupied, np.ones((3, 3), np.uint8)).astype(bool)
    lo, hi = v.min(0), v.max(0)
    gx, gz = np.meshgrid(np.arange(lo[0], hi[0], SIGHT_STEP_M), np.arange(lo[1], hi[1], SIGHT_STEP_M))
    eyes = np.stack([gx.ravel(), gz.ravel()], 1)
    eyes = eyes[nav.contains(eyes)]
    a = np.linspace(0, 2 * np.pi, RAYS, endpoint=False)
    t = np.arange(1, int(reach_m / CELL_M) + 1) * CELL_M
    steps = np.stack([np.cos(a)[:, None] * t, np.sin(a)[:, None] * t], -1)  # (RAYS, T, 2)
    seen = np.zeros((n, m), bool)
    for e in eyes:
        p = e + steps
        j = ((p[..., 0] - x0) / CELL_M).astype(np.int64)
        i = ((p[..., 1] - z0) / CELL_M).astype(np.int64)
        clear = ~np.maximum.accumulate(occupied[i, j], axis=1)
        seen[i[clear], j[clear]] = True
    return seen, float(x0), float(z0)


def back_side_gaussians(g: Gaussians, depth: np.ndarray, world_from_cam: np.ndarray, nav, *, thickness: float,
                        reach: float, rgb: np.ndarray | None = None, shell: bool = True, edge: bool = False,
                        plane: bool = False) -> BackSides:
    """A second layer for the source's per-pixel Gaussians g on upright surfaces whose other side is in the line of
    sight of the NavMesh nav: each copied `thickness` metres behind its surface (along its normal, away from the capture point at
    world_from_cam), hidden from the capture point (behind the source depth (H, W) metres of every pixel within
    WINDOW of its own; with edge, within its thickness across: edge_clear; with plane, its neighbours along the
    wall within its thickness too: plane_clear), and the cell `thickness` + 2 CELL_M behind it seen from the NavMesh within `reach` metres
    (sight_grid: from the front side the wall itself blocks the sight).
    With shell, only surfaces on the room's shell (on_shell: walls, not the fronts of furniture whose unseen sides let
    the sight reach behind them). Coloured rgb (3,) uint8 when given (the next room's walls), else as the front. Splats are two-sided: from behind,
    the back layer is in front of the front layer; from the capture point, behind it."""
    pose = np.asarray(world_from_cam, np.float64)
    centre = pose[:3, 3]
    means = np.asarray(g.means, np.float64)
    n = normals_facing(g, centre)
    y_floor = float(nav.floor_y)
    height = y_floor - means[:, 1]  # y is down
    cand = (np.abs(n[:, 1]) <= UPRIGHT) & (height > 0.05)
    q = means[cand] - thickness * n[cand]
    # hidden from the capture point: behind every source depth near q's pixel
    p = (q - centre) @ pose[:3, :3]  # camera frame: cam_from_world applied
    hidden = edge_clear(p, depth, thickness, adaptive=edge)
    if plane:
        hidden &= plane_clear(p, n[cand] @ pose[:3, :3], depth, thickness)
    # in sight of the walkable floor from behind
    band = (height > BAND_M[0]) & (height < BAND_M[1])
    reached, x0, z0 = sight_grid(nav, means[band], reach)
    far = means[cand] - (thickness + 2 * CELL_M) * n[cand]
    ci = ((far[:, 2] - z0) / CELL_M).astype(np.int64)
    cj = ((far[:, 0] - x0) / CELL_M).astype(np.int64)
    inside = (ci >= 0) & (ci < reached.shape[0]) & (cj >= 0) & (cj < reached.shape[1])
    behind = np.zeros(len(q), bool)
    behind[inside] = reached[ci[inside], cj[inside]]
    keep = hidden & behind
    walls = on_shell(means[cand], depth, pose) if shell else None
    if walls is not None:
        keep &= walls
    idx = np.flatnonzero(cand)[keep]
    sh = np.asarray(g.sh_dc, np.float32)[idx]
    if rgb is not None:
        sh = np.broadcast_to(rgb_to_sh_dc(np.asarray(rgb, np.float32) / 255.0), sh.shape).astype(np.float32)
    back = Gaussians(q[keep].astype(np.float32), np.asarray(g.scales)[idx], np.asarray(g.quats)[idx],
                     np.asarray(g.opacities)[idx], sh, np.zeros((len(idx),) + np.asarray(g.sh_rest).shape[1:], np.float32))
    stats = {"num": len(idx), "upright": int(cand.sum()), "hidden": int(hidden.sum()), "reached": int(behind.sum()),
             "off_shell": None if walls is None else int((hidden & behind & ~walls).sum()),
             "thickness_m": thickness, "reach_m": reach, "color": None if rgb is None else [int(c) for c in rgb]}
    return BackSides(back, stats)


def next_room_wall_rgb(rgb: np.ndarray, depth: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray | None:
    """The next room's wall colour (3,) uint8 seen through the doorway in the source view (rgb (H, W, 3) uint8,
    depth (H, W) metres): plane_colors.floor_beyond's walls' median; None where none is seen."""
    from panoworld.room.plane_colors import floor_beyond

    valid = np.isfinite(depth) & (depth > 0)
    pose = np.asarray(world_from_cam, np.float64)
    pts = points_from_depth(np.where(valid, depth, 0.0), pose)
    fb = floor_beyond(pts, rgb, valid, floor=False, walls_ceiling=True)
    if fb is None or fb.wall_rgb is None:
        return None
    return np.clip(np.rint(fb.wall_rgb), 0, 255).astype(np.uint8)


def back_side_layer(pix: Gaussians, rgb: np.ndarray, depth: np.ndarray, world_from_cam: np.ndarray, *, nav,
                    thickness: float, reach: float, color: str = "next_room", shell: bool = True, edge: bool = False,
                    plane: bool = False) -> BackSides:
    """back_side_gaussians of the source's per-pixel Gaussians pix, coloured as `color` says: "next_room" (the next
    room's wall colour the doorway shows, next_room_wall_rgb; the front's colour where none is seen) or "front";
    shell, edge, plane: back_side_gaussians'."""
    wall = next_room_wall_rgb(rgb, depth, world_from_cam) if color == "next_room" else None
    return back_side_gaussians(pix, depth, world_from_cam, nav, thickness=thickness, reach=reach, rgb=wall,
                               shell=shell, edge=edge, plane=plane)
