"""Implausible room geometry masked: floor or ceiling receding past the walls that bound it, surfaces through the camera."""

from __future__ import annotations

import numpy as np

from panoworld.core.conventions import erp_dirs, erp_pixel_solid_angle
from panoworld.core.parallel import map_ahead

PLANE_TOL = 0.02
"""A pixel lies on the floor (ceiling) plane when its height is within this fraction of the plane's distance."""
REACH_REL, REACH_ABS_M = 0.05, 0.10
"""Floor or ceiling seen farther out horizontally than bound x (1 + REACH_REL) + REACH_ABS_M is beyond its room."""
STAND_RADIUS_M = 1.0
"""Floor and ceiling within this horizontal distance of the camera are kept where no wall bounds them: the floor the
tripod stands on and the photographer walked, wide enough for the NavMesh's agent to stand at the capture point."""
NEAR_PLANE_M = 0.15
"""A surface whose plane passes nearer the camera centre than a camera on a tripod can stand to a wall is not
geometry (a doorway line through the camera in a layout annotation): a tripod's legs spread >= 0.3 m, so with two
feet against a wall its centre stands >= ~15 cm from it."""
ANALYSIS_HEIGHT = 512
"""Walls and planes through the camera are found at most at this ERP height (a power-of-two stride)."""
NEAR_REACH_M = 0.5
"""Such a surface counts only where it comes this near the camera (a doorway line through the camera does; the side
of a door jamb seen edge-on across the room does not); through another capture point, the wall within this of it
horizontally (a doorway's half width)."""
GROW_PASSES = 3
"""near_plane_mask grows its planes this many pixels into their rim (where the plane meets the floor or ceiling)."""
COLLINEAR_REL = 0.01
"""A pixel and its four neighbours lie on one plane when within this fraction of its shortest step to them."""


def _plane_masks(depth, valid, dirs, floor_m, ceil_m):
    y = depth * dirs[..., 1]  # camera frame: +Y is down
    floor = np.zeros(depth.shape, bool) if floor_m is None else valid & (np.abs(y - floor_m) <= PLANE_TOL * floor_m)
    ceil = np.zeros(depth.shape, bool) if ceil_m is None else valid & (np.abs(-y - ceil_m) <= PLANE_TOL * ceil_m)
    return floor, ceil


def _gaps(has: np.ndarray) -> list[tuple[int, int]]:
    """Circular runs of False in has (W,) as (last True column before, first True column after)."""
    W = len(has)
    cols = np.flatnonzero(has)
    out = []
    for a, b in zip(cols, np.roll(cols, -1)):
        if (b - a) % W != 1 and not (len(cols) == 1 and W == 1):
            out.append((int(a), int(b)))
    return out


def wall_bounds(depth: np.ndarray, valid: np.ndarray, floor_m: float | None, ceil_m: float | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Per ERP column (W,): how far out horizontally its room reaches, the wall points (W, 2) in the horizontal
    plane (x, z) and whether the column sees a wall. A column's bound is its farthest wall (a valid pixel on neither
    the floor nor the ceiling plane); in a run of columns that see none, it is where the column's ray crosses the line
    joining the walls at the run's two ends (the room closed by that chord; at most the farthest wall), 0 where it
    does not cross it.
    None when no column sees a wall."""
    H, W = depth.shape
    dirs = erp_dirs(H, W, np.float32)
    floor, ceil = _plane_masks(depth, valid, dirs, floor_m, ceil_m)
    wall = valid & ~floor & ~ceil
    horiz = np.where(wall, depth * np.hypot(dirs[..., 0], dirs[..., 2]), 0.0)
    r = horiz.max(0).astype(np.float64)
    has = r > 0
    if not has.any():
        return None
    az = np.arctan2(dirs[H // 2, :, 0], dirs[H // 2, :, 2]).astype(np.float64)
    u = np.stack([np.sin(az), np.cos(az)], axis=1)
    pts = u * r[:, None]
    bound = r.copy()
    for a, b in _gaps(has):
        cols = np.arange(a + 1, a + 1 + (b - a - 1) % W) % W
        e = pts[b] - pts[a]
        den = u[cols, 0] * e[1] - u[cols, 1] * e[0]
        s = (pts[a, 0] * e[1] - pts[a, 1] * e[0]) / np.where(np.abs(den) > 1e-12, den, np.nan)
        bound[cols] = np.where(np.isfinite(s) & (s > 0), np.minimum(s, r.max()), 0.0)
    return bound, pts, has


def room_floor_area(pts: np.ndarray, has: np.ndarray) -> float:
    """Area (m^2) of the polygon through the wall points (W, 2) of the columns that see a wall, in column order (a
    run without walls is closed by the chord between its ends): the room's floor as its walls outline it."""
    p = pts[has]
    if len(p) < 3:
        return 0.0
    x, z = p[:, 0], p[:, 1]
    return float(0.5 * abs(np.dot(x, np.roll(z, -1)) - np.dot(z, np.roll(x, -1))))


def near_plane_mask(depth: np.ndarray, valid: np.ndarray, near_m: float = NEAR_PLANE_M,
                    centres: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: valid pixels on a surface whose plane passes within near_m of the camera centre (or of any of
    centres (M, 3), camera frame: other capture points of a home): the pixel and its four neighbours (seam wrapped)
    lie on one plane (within COLLINEAR_REL of the shortest step to them: never across a depth edge) and that plane
    passes that near. A wall line through the camera is seen edge-on, so every pixel of it qualifies, however far
    along it, when the surface reaches within NEAR_REACH_M of the camera (_reaching). A wall through another capture
    point qualifies within NEAR_REACH_M of it horizontally, at every height: the doorway that camera stood in, not
    the wall beside it."""
    H, W = depth.shape
    pts = erp_dirs(H, W, np.float32) * np.where(valid, depth, 0.0).astype(np.float32)[..., None]
    ok = valid & np.roll(valid, 1, 1) & np.roll(valid, -1, 1)
    ok[1:] &= valid[:-1]
    ok[:-1] &= valid[1:]
    ok[0] = ok[-1] = False
    nbrs = (np.roll(pts, 1, 1), np.roll(pts, -1, 1), np.concatenate([pts[:1], pts[:-1]]),
            np.concatenate([pts[1:], pts[-1:]]))
    n = np.cross(nbrs[1] - nbrs[0], nbrs[3] - nbrs[2])
    nn = np.linalg.norm(n, axis=-1)
    ok &= nn > 0
    n = n / np.maximum(nn, 1e-30)[..., None]
    step = np.min([np.linalg.norm(q - pts, axis=-1) for q in nbrs], axis=0)
    radius = np.linalg.norm(pts, axis=-1)
    tol = COLLINEAR_REL * step + 1e-5 * radius + _depth_quantum(depth, valid)
    for q in nbrs:
        ok &= np.abs((n * (q - pts)).sum(-1)) <= tol
    ok &= step > 0
    c = (n * pts).sum(-1)
    if centres is None:
        near = _reaching(ok & (np.abs(c) < near_m), depth)
    else:
        near = np.zeros_like(ok)
        for q in np.asarray(centres, np.float32).reshape(-1, 3):
            on = ok & (np.abs(c - n @ q) < near_m)
            close = _maybe_within(radius, valid, q, near_m)
            dist = np.full(on.shape, np.inf, np.float32)  # the distance to q where it is read: near q
            dist[close] = np.linalg.norm(pts[close] - q, axis=-1)
            on[on] = np.hypot(pts[on][:, 0] - q[0], pts[on][:, 2] - q[2]) < NEAR_REACH_M  # within reach, horizontally
            near |= on | (close & (dist < near_m))
    for _ in range(GROW_PASSES):  # the rim where a neighbour lies on another surface: on the plane of a near pixel
        grow = np.zeros_like(near)
        free = valid & ~near
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy or dx:
                    nb = np.roll(np.roll(near, dy, 0), dx, 1)
                    if dy:
                        nb[0 if dy > 0 else -1] = False
                    y, x = np.nonzero(nb & free & ~grow)  # tested there alone: grow keeps only free pixels
                    sy, sx = (y - dy) % H, (x - dx) % W  # the near neighbour (np.roll's source pixel)
                    on = np.abs((n[sy, sx] * pts[y, x]).sum(-1) - c[sy, sx])
                    grow[y, x] = on <= COLLINEAR_REL * radius[y, x] + 0.002
        if not grow.any():
            break
        near |= grow
        n[grow], c[grow] = _first_neighbour_plane(near & ~grow, n, c, grow)
    return near


def _depth_quantum(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(H, W) the rounding step of depth values stored as float16 (ZInD's layout depth: 1 mm at 1-2 m), 0 for finer
    ones and invalid pixels: a plane's points leave it by up to that step."""
    exact, d16 = float16_exact(depth, valid)
    with np.errstate(invalid="ignore"):
        return np.where(exact, np.spacing(d16).astype(np.float32), 0.0)


def float16_exact(depth: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The valid pixels whose depth (H, W) is exactly a float16 value (depth stored at float16's precision), (H, W)
    bool, and the depth as float16 (0 where not valid)."""
    with np.errstate(over="ignore", invalid="ignore"):  # past float16's range: inf, not float16
        d16 = np.where(valid, depth, 0.0).astype(np.float16)
        return valid & (d16.astype(np.float32) == depth), d16


def label_wrapped(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """8-connected labels (H, W) of mask with the seam wrapped (a region across column 0 / W - 1 is one), and the
    largest label."""
    from scipy import ndimage

    W = mask.shape[1]
    labels, n = ndimage.label(np.concatenate([mask, mask[:, :1]], axis=1), structure=np.ones((3, 3)))
    parent = np.arange(n + 1)

    def root(a):
        while parent[a] != a:
            a = parent[a]
        return a

    for a, b in zip(labels[:, 0], labels[:, W]):  # the same pixels: column 0 and its copy past the seam
        if a and b:
            ra, rb = root(a), root(b)
            if ra != rb:
                parent[rb] = ra
    roots = np.array([root(a) for a in range(n + 1)])
    return roots[labels[:, :W]], n


def _reaching(near: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """near less its regions (label_wrapped) that come no nearer the camera than NEAR_REACH_M: a surface seen edge-on
    (a door jamb's side, a table's edge) lies on a plane through the camera too, but far from it."""
    from scipy import ndimage

    if not near.any():
        return near
    labels, n = label_wrapped(near)
    closest = np.asarray(ndimage.minimum(depth, labels, np.arange(1, n + 1)))
    return np.concatenate([[False], np.nan_to_num(closest, nan=np.inf) < NEAR_REACH_M])[labels]


def _first_neighbour_plane(src, n, c, at):
    """Plane (normal, offset) of a src pixel among the 8-neighbours of each pixel of at."""
    H, W = at.shape
    y, x = np.nonzero(at)
    nn, cc = np.zeros((len(y), 3), n.dtype), np.zeros(len(y), c.dtype)
    done = np.zeros(len(cc), bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                sy, sx = (y - dy) % H, (x - dx) % W  # np.roll's source pixel
                has = src[sy, sx] & ~done
                nn[has] = n[sy[has], sx[has]]
                cc[has] = c[sy[has], sx[has]]
                done |= has
    return nn, cc


def implausible_mask(depth: np.ndarray, valid: np.ndarray, floor_m: float | None, ceil_m: float | None,
                     *, near_m: float = NEAR_PLANE_M) -> tuple[np.ndarray, dict]:
    """(H, W) bool: valid pixels of implausible room geometry in depth, valid (H, W), and a record for the manifest.

    Beyond the room: in the columns that see no wall, floor (ceiling) pixels, on the horizontal plane floor_m below
    (ceil_m above) the camera, seen farther out than their column's wall_bounds (the chord closing the walls, x 1 +
    REACH_REL, + REACH_ABS_M), but never within STAND_RADIUS_M:
    where the camera stands outside its own annotated room, rays that miss every wall otherwise reach the plane
    hundreds of metres away; with no wall at all only that stand is kept (a column that sees a wall keeps its floor:
    beyond a wall it is a real scan's noise, not a room's). Through the camera: near_plane_mask, any pixel nearer
    than near_m, and where those found any, with floor_m, any point in the tripod's column (tripod_column: a camera
    set on a table, with no surface through it, keeps the table). The first two are found on every
    k-th row and column (ANALYSIS_HEIGHT rows at most: the resolution provided layout depth comes at, enlarged by k
    for its panorama) and apply to their k x k blocks."""
    H, W = depth.shape
    k = max(1, H // ANALYSIS_HEIGHT)
    k = k if H % k == 0 and W % k == 0 else 1
    small_d, small_v = depth[::k, ::k], valid[::k, ::k]
    near_small = near_plane_mask(small_d, small_v, near_m) | (small_v & (small_d < near_m))
    near = (near_small if k == 1 else np.repeat(np.repeat(near_small, k, 0), k, 1)) & valid
    near |= valid & (depth < near_m)
    rec: dict = {"near_plane_m": near_m, "near_surface_px": int(near.sum()), "far_floor_px": 0, "far_ceiling_px": 0,
                 "tripod_column_px": 0}
    far = np.zeros((H, W), bool)
    dirs = erp_dirs(H, W, np.float32) if floor_m is not None or ceil_m is not None else None
    if floor_m is not None and near.any():  # a surface through the camera: what is left of it near the nadir
        column = tripod_column(depth, valid & ~near, floor_m, dirs, near_m)
        rec["tripod_column_px"] = int(column.sum())
        near |= column
    if dirs is not None:
        b = wall_bounds(small_d, small_v & ~near_small, floor_m, ceil_m)
        w = W // k
        bound, pts, has = b if b is not None else (np.zeros(w), np.zeros((w, 2)), np.zeros(w, bool))
        bound = np.repeat(bound, k)
        floor, ceil = _plane_masks(depth, valid & ~near, dirs, floor_m, ceil_m)
        horiz = depth * np.hypot(dirs[..., 0], dirs[..., 2])
        reach = np.where(np.repeat(has, k), np.inf, np.maximum(bound * (1 + REACH_REL) + REACH_ABS_M, STAND_RADIUS_M))
        reach = reach[None, :]
        beyond = horiz > reach
        rec.update(far_floor_px=int((floor & beyond).sum()), far_ceiling_px=int((ceil & beyond).sum()),
                   wall_columns_fraction=float(has.mean()), room_floor_area_m2=room_floor_area(pts, has))
        far = (floor | ceil) & beyond
    drop = near | far
    omega = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W))
    rec["masked_fraction"] = float(drop.mean())
    rec["masked_sphere_fraction"] = float(omega[drop].sum() / omega.sum())
    if drop.any():
        rec["max_depth_before"] = float(depth[valid].max())
        rest = valid & ~drop
        rec["max_depth_after"] = float(depth[rest].max()) if rest.any() else None
    return drop, rec


def tripod_column(depth: np.ndarray, valid: np.ndarray, floor_m: float, dirs: np.ndarray,
                  near_m: float = NEAR_PLANE_M) -> np.ndarray:
    """(H, W) bool: valid pixels of depth (H, W) (ray directions dirs (H, W, 3), erp_dirs) whose point lies in the
    tripod's column: within near_m of the camera's vertical axis, below the camera and above the floor plane floor_m
    below it (by more than PLANE_TOL of it). The tripod stood there, so no surface did: the rest of a layout's doorway
    line through the camera that the plane test missed near the nadir, where ERP pixels are too stretched for it."""
    d = np.where(valid, depth, 0.0)
    y = d * dirs[..., 1]
    return valid & (d * np.hypot(dirs[..., 0], dirs[..., 2]) < near_m) & (y > 0) & (y < floor_m * (1 - PLANE_TOL))


def mask_implausible(depth: np.ndarray, valid: np.ndarray, floor_m: float | None, ceil_m: float | None,
                     *, near_m: float = NEAR_PLANE_M) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict]:
    """depth, valid (H, W) with implausible_mask made invalid (depth 0), what completions must leave unknown
    (unknown_beyond, (H, W) bool) and the record; the same arrays and None when nothing is found.

    Where a surface through the camera hid it, the floor the tripod stands on (within STAND_RADIUS_M, on the plane
    floor_m below the camera) is completed from that plane (record: stand_floor_px): a camera standing on a layout's
    doorway line stands on the floor of both rooms."""
    drop, rec = implausible_mask(depth, valid, floor_m, ceil_m, near_m=near_m)
    rec["stand_floor_px"] = 0
    if not drop.any():
        return depth, valid, None, rec
    unknown = unknown_beyond(drop, valid)
    valid = valid & ~unknown
    depth = np.where(valid, depth, 0.0).astype(depth.dtype)
    if floor_m is not None and rec["near_surface_px"]:  # the tripod's column is searched only then
        dirs = erp_dirs(*depth.shape, np.float32)
        down = dirs[..., 1]
        stand = unknown & (down > 0) & (floor_m * np.hypot(dirs[..., 0], dirs[..., 2]) <= STAND_RADIUS_M * down)
        depth[stand] = floor_m / down[stand]
        valid, unknown = valid | stand, unknown & ~stand
        rec["stand_floor_px"] = int(stand.sum())
    return depth, valid, unknown, rec


def unknown_beyond(drop: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(H, W) bool: drop plus the invalid regions (label_wrapped) that touch it: what is left unknown rather than
    completed from its rim (the rest of a surface through the camera, nearer than any depth kept)."""
    if not drop.any():
        return drop
    labels, _ = label_wrapped(~valid | drop)
    touch = np.unique(labels[drop])
    return np.isin(labels, touch[touch > 0])


def near_captures_mask(depth: np.ndarray, world_from_cam: np.ndarray, centres_world: np.ndarray,
                       near_m: float = NEAR_PLANE_M) -> np.ndarray:
    """(H, W) bool: pixels of a home's panorama (depth (H, W), 0 = none, at world_from_cam) on a surface through
    another capture point (centres_world (M, 3)): within near_m of it, or on a plane passing that near, within
    NEAR_REACH_M of it horizontally (near_plane_mask): a camera stood there, so it is the doorway of a layout
    annotation's wall line, not a wall. Found at most at ANALYSIS_HEIGHT rows, applied to their k x k blocks."""
    H, W = depth.shape
    valid = np.isfinite(depth) & (depth > 0)
    centres = np.asarray(centres_world, np.float64).reshape(-1, 3)
    if not len(centres) or not valid.any():
        return np.zeros((H, W), bool)
    from panoworld.core.conventions import invert_pose, transform_points

    local = transform_points(invert_pose(np.asarray(world_from_cam, np.float64)), centres)
    k = max(1, H // ANALYSIS_HEIGHT)
    k = k if H % k == 0 and W % k == 0 else 1
    small = near_plane_mask(depth[::k, ::k], valid[::k, ::k], near_m, centres=local)
    out = (small if k == 1 else np.repeat(np.repeat(small, k, 0), k, 1)) & valid
    d = np.where(valid, depth, 0.0).astype(np.float32)
    dirs = None
    for q in local.astype(np.float32):
        close = _maybe_within(d, valid, q, near_m)
        if close.any():
            dirs = erp_dirs(H, W, np.float32) if dirs is None else dirs
            out[close] |= np.linalg.norm(dirs[close] * d[close][:, None] - q, axis=-1) < near_m
    return out


def _maybe_within(radius: np.ndarray, valid: np.ndarray, q: np.ndarray, near_m: float) -> np.ndarray:
    """valid pixels whose point (at distance radius from the camera) may lie within near_m of q: |radius - |q|| is
    a lower bound of that distance (with a margin for float32 rounding); the rest is surely farther."""
    return valid & (np.abs(radius - float(np.linalg.norm(q))) < near_m + 1e-3 + 1e-5 * radius)


def drop_near_captures(depths: dict[str, np.ndarray], world_from_cam: dict[str, np.ndarray], *, workers: int = 1
                       ) -> dict[str, int]:
    """Zero, in place, each home panorama's depth (H, W) where near_captures_mask finds a surface through another
    capture point, the panoramas' masks found on `workers` threads; {NAME: pixels dropped}."""

    def drop_mask(n: str) -> np.ndarray:
        others = np.array([np.asarray(world_from_cam[m])[:3, 3] for m in depths if m != n]).reshape(-1, 3)
        return near_captures_mask(depths[n], world_from_cam[n], others)

    out = {}
    for n, drop in zip(list(depths), map_ahead(drop_mask, list(depths), workers=workers)):
        depths[n][drop] = 0.0
        out[n] = int(drop.sum())
    return out


def describe(rec: dict) -> str | None:
    """One line for the depth manifest's decisions, or None when nothing was masked."""
    if not (rec["near_surface_px"] or rec["far_floor_px"] or rec["far_ceiling_px"]):
        return None
    return (f"implausible room geometry masked ({rec['masked_fraction']:.1%} of the pixels): "
            f"{rec['far_floor_px']} floor and {rec['far_ceiling_px']} ceiling px beyond the walls that bound them "
            f"(max depth {rec['max_depth_before']:.1f} -> {rec['max_depth_after'] or 0:.1f} m), "
            f"{rec['near_surface_px']} px on a surface through the camera (< {rec['near_plane_m']:g} m)"
            + (f", {rec['tripod_column_px']} px in the tripod's column under the camera" if rec.get("tripod_column_px")
               else "")
            + (f", {rec['stand_floor_px']} px of the floor the camera stands on behind it completed from the floor plane"
               if rec.get("stand_floor_px") else ""))
