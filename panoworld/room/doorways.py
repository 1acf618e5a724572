"""Doorways that a layout depth closes, opened where two panoramas see one floor through them."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from panoworld.core.conventions import (
    erp_dirs64,
    erp_lonlat_from_pixel,
    erp_pixel_from_dir,
    erp_pixel_from_lonlat,
    invert_pose,
    transform_points,
)
from panoworld.core.parallel import map_ahead
from panoworld.core.shapes import check_shape
from panoworld.geometry.floor_view import (
    FloorView,
    agrees_with_pose,
    camera_height,
    floor_matches,
    floor_view,
    plane_distance,
)
from panoworld.room.floor import column_reach

CELL_M = 0.02
"""Floor grid cell (metres) on which two panoramas' views of one floor are compared."""
REACH_M = 4.0
"""Floor points within this of the panorama that sees them directly are compared."""
BLUR_CELLS = 2.0
"""The floor images are compared at this scale (Gaussian sigma in cells): the texture one view resolves at 1 m and
the other at 4 m through a doorway differs, the pattern of light and wear does not."""
WINDOW = 35
"""Side of the square of cells over which the two views' floor textures are correlated."""
MIN_NCC = 0.5
"""Two views agree on a floor cell when their textures around it correlate at least this much ..."""
MIN_STD = 4.0
"""... and both vary by at least this (grey levels, standard deviation over the window): plain floor tells nothing."""
MIN_MATCHES = 3
"""A run of agreeing columns is an opening when at least this many floor keypoints seen through it match the other
panorama's at the registered pose (SIFT on the floor images, geometry.floor_view): textures alone agree by chance on plain
walls lit like the floor."""
MATCHED_OPENING = 8
"""A run of columns holding at least this many floor keypoints seen through the wall that match the other
panorama's at the registered pose (gaps of 1 % closed) is an opening without the textures' agreement: a floor a
panorama sees behind its wall is seen through an opening, and chance agreement stays at 3-4 keypoints."""
MARGIN_M = 0.15
"""An opening is widened by this on either side along its wall: the views agree only where both see the floor, short
of the door frame."""
DOOR_TOP_M = 2.0
"""A wall is opened from the floor up to this height above it (the lintel above a door stays)."""
THRESHOLD_M = 0.5
"""An opened doorway's floor is continued this far beyond the wall (horizontally): the other room's floor begins a
wall's thickness away."""
SIDE_M = 0.3
"""Another panorama's wall within this of an opening (across it, horizontally, and between its ends) is the same
doorway seen from the other room (two rooms' layouts put it a wall's thickness apart); it is opened too."""


def open_doorways(names: list[str], rgbs: dict[str, np.ndarray], depths: dict[str, np.ndarray],
                  world_from_cam: dict[str, np.ndarray], *, workers: int = 1) -> dict[str, int]:
    """Open, in place, the doorways that the layout depths (H, W) of registered panoramas close (is_layout: walls,
    floor and ceiling of the panorama's own room, every doorway a wall). An opening of panorama a is a run of its
    columns where the floor another panorama b sees directly lies behind a's wall and both images' floor textures
    there correlate, confirmed by at least MIN_MATCHES floor keypoints seen through it that match b's at the
    registered pose; it is widened by MARGIN_M, and the other panoramas' walls across it (within SIDE_M) open with it.
    A run of columns holding at least MATCHED_OPENING such keypoints matched to one panorama b is an opening too.
    Opened: the wall from the floor up to DOOR_TOP_M, the floor continued THRESHOLD_M through. rgbs (H', 2H', 3)
    uint8 (the cleaned panoramas); each panorama's floor view and looks through its walls on `workers` threads;
    -> {NAME: wall pixels opened}."""
    for n in names:
        check_shape(f"depth of {n}", depths[n], "H W")
        check_shape(f"panorama of {n}", rgbs[n], "H W 3")
    heights = {n: camera_height(depths[n]) for n in names}
    known = [n for n in names if heights[n] is not None]
    layouts = [n for n in known if is_layout(depths[n], heights[n])]
    out = dict.fromkeys(names, 0)
    if not layouts:
        return out
    grey = {n: cv2.cvtColor(rgbs[n], cv2.COLOR_RGB2GRAY).astype(np.float32) for n in known}
    views = dict(zip(known, map_ahead(lambda n: floor_view(rgbs[n], depths[n]), known, workers=workers)))
    walls = {n: _walls(depths[n], heights[n]) for n in layouts}
    reach = {n: column_reach(depths[n]) for n in known}
    near = {a: [b for b in known if b != a and _near(world_from_cam[a], world_from_cam[b])] for a in layouts}
    seen_by = [b for b in known if any(b in near[a] for a in layouts)]
    direct = dict(zip(seen_by, map_ahead(lambda b: _seen_directly(b, grey, depths, heights, world_from_cam), seen_by,
                                         workers=workers)))

    def look(a: str) -> tuple[np.ndarray, list[np.ndarray]]:  # a's agreeing columns, keypoints through its walls
        cols = np.zeros(depths[a].shape[1], bool)
        for b in near[a]:
            cols |= _agreeing_columns(a, b, *direct[b], grey, depths, heights, world_from_cam)
        return cols, [_through_door(a, b, views, reach, world_from_cam) for b in near[a]]

    masks, segments = {}, []
    for a, (cols, through) in zip(layouts, map_ahead(look, layouts, workers=workers)):
        w = depths[a].shape[1]
        plan = _wall_plan(reach[a])
        keep = np.zeros(w, bool)
        seen = np.concatenate(through or [np.zeros(0, np.int64)])
        runs = [idx for idx in _runs(cols) if np.isin(seen, idx).sum() >= MIN_MATCHES]
        runs += [idx for cols_b in through for idx in _runs(np.bincount(cols_b, minlength=w) > 0)
                 if np.isin(cols_b, idx).sum() >= MATCHED_OPENING]
        for idx in runs:
            idx = _widen(idx, plan)
            keep[idx] = True
            segments.append((a, _to_world_plan(world_from_cam[a], plan[[idx[0], idx[-1]]])))
        masks[a] = walls[a] & keep[None, :]

    def across(c: str) -> np.ndarray | None:  # c's walls within SIDE_M of the other panoramas' openings
        other = [seg for n, seg in segments if n != c]
        if not other:
            return None
        side = np.zeros_like(walls[c])
        side[walls[c]] = _on_segments(_plan_points(depths[c], world_from_cam[c], walls[c]), other)
        return side

    for c, side in zip(layouts, map_ahead(across, layouts, workers=workers)):
        if side is not None:
            masks[c] |= side
        _open(depths[c], heights[c], reach[c], masks[c])
        out[c] = int(masks[c].sum())
    return out


def is_layout(depth: np.ndarray, height: float, *, tol: float = 0.02, share: float = 0.995) -> bool:
    """Whether a ray depth (H, W) with the camera `height` above its floor holds a room's layout only: at least `share`
    of its valid pixels within tol (relative) of the nearest of the floor plane, a flat ceiling (its height the most
    common over the rays above 40 degrees, plane_distance) and, per column, one vertical wall at the column's farthest
    horizontal reach. A depth with furniture, or of a real sensor, is not: its doorways are open already."""
    dirs = erp_dirs64(*depth.shape)
    valid = depth > 0
    up = -dirs[..., 1]
    ceiling = plane_distance(depth, below=False)
    if ceiling is None or valid.sum() < 0.5 * valid.size:
        return False
    flat = np.maximum(np.hypot(dirs[..., 0], dirs[..., 2]), 1e-9)
    pred = np.minimum(column_reach(depth)[None, :] / flat, np.where(up < 0, height / np.maximum(-up, 1e-9), np.inf))
    pred = np.minimum(pred, np.where(up > 0, ceiling / np.maximum(up, 1e-9), np.inf))
    good = valid & (np.abs(depth / pred - 1) < tol)
    return bool(good.sum() >= share * valid.sum())


def _near(world_from_a: np.ndarray, world_from_b: np.ndarray) -> bool:
    return float(np.linalg.norm(np.asarray(world_from_a)[[0, 2], 3] - np.asarray(world_from_b)[[0, 2], 3])) <= 2 * REACH_M


def _look(name: str, pts: np.ndarray, depths, world_from_cam):
    """For world points pts (n, n, 3): (distance from the panorama's camera, its depth along that ray, the depth
    column, the unit directions (n * n, 3) in the camera frame)."""
    p = transform_points(invert_pose(np.asarray(world_from_cam[name], np.float64)), pts)
    dist = np.linalg.norm(p, axis=-1)
    d = (p / np.maximum(dist, 1e-9)[..., None]).reshape(-1, 3)
    depth = depths[name]
    h, w = depth.shape
    u, v = erp_pixel_from_dir(d, h, w)
    iu, iv = np.floor(u).astype(int) % w, np.clip(np.floor(v).astype(int), 0, h - 1)
    return dist, depth[iv, iu].reshape(dist.shape), iu.reshape(dist.shape), d


def _grey_at(g: np.ndarray, d: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The grey image g (bilinear, the seam wrapped) in the unit directions d (shape[0] * shape[1], 3), blurred by
    BLUR_CELLS on the grid of shape."""
    gu, gv = erp_pixel_from_dir(d, *g.shape)
    padded = np.concatenate([g[:, -2:], g, g[:, :2]], 1)  # the seam wraps
    val = cv2.remap(padded, (gu - 0.5 + 2).astype(np.float32).reshape(shape),
                    (gv - 0.5).astype(np.float32).reshape(shape), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return cv2.GaussianBlur(val.astype(np.float32), (0, 0), BLUR_CELLS)


def _grid() -> tuple[np.ndarray, np.ndarray]:
    """The floor grid's cell centres (x, z) around a camera, each (n, n) metres."""
    c = (np.arange(int(round(2 * REACH_M / CELL_M))) + 0.5) * CELL_M - REACH_M
    return np.meshgrid(c, c)


def _seen_directly(b, grey, depths, heights, world_from_cam) -> tuple[np.ndarray, np.ndarray | None]:
    """b's floor on the grid around its camera: (cells b sees directly (n, n) bool, within REACH_M and beyond the rig's
    inpainted floor; b's blurred grey image there, None when fewer than WINDOW x WINDOW cells are: too few to compare)."""
    Tb = np.asarray(world_from_cam[b], np.float64)
    x, z = _grid()
    floor_b = Tb[:3, 3] + np.stack([x, np.full_like(x, heights[b]), z], -1)
    dist_b, depth_b, _, d = _look(b, floor_b, depths, world_from_cam)
    r = np.hypot(x, z)
    seen_b = (depth_b > 0) & (dist_b <= depth_b * 1.02 + 0.03) & (r < REACH_M)
    seen_b &= r > heights[b] * np.tan(np.radians(35.0))  # not the rig's inpainted floor
    return seen_b, (_grey_at(grey[b], d, x.shape) if seen_b.sum() >= WINDOW * WINDOW else None)


def _agreeing_columns(a, b, seen_b, gb, grey, depths, heights, world_from_cam) -> np.ndarray:
    """(W,) bool: columns of a's depth through which a sees, behind its wall, floor that b sees directly (seen_b, gb:
    _seen_directly of b), with both images' textures correlating there (at least 3 cells and half of those compared in
    the column)."""
    w = depths[a].shape[1]
    if gb is None:
        return np.zeros(w, bool)
    Ta, Tb = (np.asarray(world_from_cam[n], np.float64) for n in (a, b))
    x, z = _grid()
    floor_a = Tb[:3, 3] + np.stack([x, np.zeros_like(x), z], -1)
    floor_a[..., 1] = Ta[1, 3] + heights[a]
    dist_a, depth_a, col_a, d = _look(a, floor_a, depths, world_from_cam)
    behind_a = (depth_a > 0) & (dist_a > depth_a * 1.05 + 0.10)
    cand = seen_b & behind_a
    if cand.sum() < WINDOW * WINDOW:
        return np.zeros(w, bool)
    m = cand.astype(np.float32)

    def box(q):
        return cv2.boxFilter(q.astype(np.float32), -1, (WINDOW, WINDOW), normalize=False,
                             borderType=cv2.BORDER_CONSTANT)

    ga = _grey_at(grey[a], d, x.shape)
    cnt = box(m)
    n = np.maximum(cnt, 1.0)
    ma, mb = box(ga * m) / n, box(gb * m) / n
    va, vb = box(ga * ga * m) / n - ma**2, box(gb * gb * m) / n - mb**2
    cov = box(ga * gb * m) / n - ma * mb
    tried = cand & (cnt >= 0.6 * WINDOW * WINDOW) & (va > MIN_STD**2) & (vb > MIN_STD**2)
    agree = tried & (cov / np.sqrt(np.maximum(va * vb, 1e-6)) > MIN_NCC)
    n_agree = np.bincount(col_a[agree], minlength=w)
    return (n_agree >= 3) & (n_agree >= 0.5 * np.bincount(col_a[tried], minlength=w))


def _through_door(a: str, b: str, views: dict[str, FloorView | None], reach: dict[str, np.ndarray],
                  world_from_cam: dict[str, np.ndarray]) -> np.ndarray:
    """(K,) int: the columns of a's depth of the floor keypoints a sees behind its walls that match b's inside b's room
    at the registered pose (geometry.floor_view.agrees_with_pose); reach: each panorama's column_reach."""
    va, vb = views[a], views[b]
    if va is None or vb is None:
        return np.zeros(0, np.int64)
    col_a = _column_of(va.xz, reach[a].size)
    col_b = _column_of(vb.xz, reach[b].size)
    behind = np.flatnonzero(np.linalg.norm(va.xz, axis=1) > reach[a][col_a] * 1.05 + 0.1)
    inside = np.flatnonzero(np.linalg.norm(vb.xz, axis=1) < reach[b][col_b] * 0.98)
    if len(behind) < 2 or len(inside) < 2:
        return np.zeros(0, np.int64)
    sa, sb = _subset(va, behind), _subset(vb, inside)
    a_from_b = invert_pose(np.asarray(world_from_cam[a], np.float64)) @ np.asarray(world_from_cam[b], np.float64)
    m = floor_matches(sa, sb)
    return col_a[behind[m[agrees_with_pose(sa, sb, a_from_b, m), 0]]]


def _subset(v: FloorView, idx: np.ndarray) -> FloorView:
    return replace(v, xz=v.xz[idx], descriptors=v.descriptors[idx], angles=v.angles[idx], sizes=v.sizes[idx])


def _column_of(xz: np.ndarray, w: int) -> np.ndarray:
    """(N,) int: the ERP column (of w) of each camera-frame floor point xz (N, 2)."""
    u, _ = erp_pixel_from_lonlat(np.arctan2(xz[:, 0], xz[:, 1]), np.zeros(len(xz)), w // 2, w)
    return np.floor(u).astype(np.int64) % w


def _wall_plan(reach: np.ndarray) -> np.ndarray:
    """(W, 2) camera-frame x, z of each column's wall (at its column_reach (W,), horizontally)."""
    w = reach.size
    lon, _ = erp_lonlat_from_pixel(np.arange(w) + 0.5, np.zeros(w), w // 2, w)
    return np.stack([reach * np.sin(lon), reach * np.cos(lon)], -1)


def _runs(cols: np.ndarray) -> list[np.ndarray]:
    """The runs of cols (W,) bool, gaps of at most 1 % of the width closed, the seam wrapping: column indices each."""
    w = cols.size
    gap = max(1, w // 100)
    cols = cv2.morphologyEx(np.tile(cols, 3).astype(np.uint8)[None], cv2.MORPH_CLOSE,
                            np.ones((1, 2 * gap + 1), np.uint8))[0, w:2 * w].astype(bool)
    if not cols.any() or cols.all():
        return []
    start = int(np.argmin(cols))  # a column outside every run: no run straddles it
    rolled = np.roll(cols, -start)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], rolled.astype(np.int8), [0]])))
    return [(start + np.arange(s, e)) % w for s, e in zip(edges[::2], edges[1::2])]


def _widen(idx: np.ndarray, plan: np.ndarray) -> np.ndarray:
    """The run idx extended on either side while its wall points plan (W, 2) stay within MARGIN_M of the end's (at
    most an eighth of the turn)."""
    w = len(plan)

    def steps(col: int, step: int) -> int:
        n = 0
        while n < w // 8 and np.linalg.norm(plan[(col + (n + 1) * step) % w] - plan[col]) <= MARGIN_M:
            n += 1
        return n

    lo, hi = steps(int(idx[0]), -1), steps(int(idx[-1]), 1)
    return (idx[0] + np.arange(-lo, len(idx) + hi)) % w


def _walls(depth: np.ndarray, height: float) -> np.ndarray:
    """(H, W) bool: the pixels of depth (H, W) on a surface between 5 cm and DOOR_TOP_M above the floor."""
    above = height - depth * erp_dirs64(*depth.shape)[..., 1]
    return (depth > 0) & (above > 0.05) & (above < DOOR_TOP_M)


def _to_world_plan(world_from_cam: np.ndarray, xz: np.ndarray) -> np.ndarray:
    """(N, 2) world x, z of camera-frame floor-plan points xz (N, 2)."""
    return transform_points(np.asarray(world_from_cam, np.float64),
                            np.stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]], -1))[:, [0, 2]]


def _plan_points(depth: np.ndarray, world_from_cam: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(N, 2) world x, z of the pixels mask (H, W) of depth (H, W)."""
    iv, iu = np.nonzero(mask)
    pts = erp_dirs64(*depth.shape)[iv, iu] * depth[iv, iu, None]
    return transform_points(np.asarray(world_from_cam, np.float64), pts)[:, [0, 2]]


def _on_segments(pts: np.ndarray, segments: list[np.ndarray]) -> np.ndarray:
    """(N,) bool: which plan points pts (N, 2) lie within SIDE_M of one of the segments ((2, 2) each), across it and
    between its ends."""
    out = np.zeros(len(pts), bool)
    for p0, p1 in segments:
        length = float(np.linalg.norm(p1 - p0))
        if length < 1e-6:
            continue
        u = (p1 - p0) / length
        rel = pts - p0
        t = rel @ u
        out |= (t >= 0) & (t <= length) & (np.abs(rel @ np.array([-u[1], u[0]])) <= SIDE_M)
    return out


def _open(depth: np.ndarray, height: float, reach: np.ndarray, mask: np.ndarray) -> None:
    """Open the wall pixels mask (H, W) of depth (H, W) (its column_reach (W,)) in place: the floor continues THRESHOLD_M
    beyond the wall, the rest is unknown."""
    dirs = erp_dirs64(*depth.shape)
    flat = np.hypot(dirs[..., 0], dirs[..., 2])
    floor = height / np.maximum(dirs[..., 1], 1e-9)
    through = mask & (dirs[..., 1] > 0) & (floor * flat <= reach[None, :] + THRESHOLD_M)
    depth[mask] = 0.0
    depth[through] = floor[through]
