"""Camera trajectories on a NavMesh: sector and ring planning, smoothing, uniform re-parameterisation, I/O, validation."""

from __future__ import annotations

import enum
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from panoworld.conventions import quat_wxyz_from_rotmat, quat_wxyz_from_xyzw, quat_xyzw_from_wxyz, rotmat_from_quat_wxyz
from panoworld.navmesh import NavMesh

TRAJECTORY_JSON = "trajectory.json"
TRAJECTORY_TUM = "trajectory.tum"
FRAME = "canonical (pose 0 = identity)"


class PathKind(enum.StrEnum):
    """Planned path families of the paper."""

    SECTOR = "sector"
    """Out-and-back petals to the farthest reachable point of each directional sector (covers 360 degrees)."""
    RING = "ring"
    """A closed loop through free space that starts and ends at the camera."""


class YawMode(enum.StrEnum):
    """Camera orientation along the path (always upright: rotation about the gravity axis only)."""

    FIXED = "fixed"
    """Identity rotation for every pose (the panorama's orientation; ERP covers every direction)."""
    FORWARD = "forward"
    """Yaw follows the (smoothed) direction of travel, relative to the initial heading so pose 0 = identity."""


class TrajectoryFileError(ValueError):
    """A trajectory file cannot be read or holds no valid SE(3) poses."""


@dataclass(kw_only=True)
class TrajectoryParams:
    """How a trajectory is planned on a NavMesh (canonical frame, metres)."""

    kind: PathKind = PathKind.SECTOR
    """Path family: sector (exploration petals, 360 degree coverage) or ring (closed loop)."""
    frames: int = 81
    """Number of poses N (pose 0 is the source camera)."""
    step_m: float = 0.05
    """Distance between consecutive poses at stride 1, in metres."""
    stride: int = 1
    """Step multiplier r in {1, 2, 4}: the planned path length is (N - 1) * step_m * stride (ring: N * step)."""
    yaw: YawMode = YawMode.FIXED
    """Camera orientation: fixed (identity) or forward (turns with the path; pose 0 stays identity)."""
    sectors: int = 8
    """Number of directional sectors visited by sector paths."""
    smooth_iterations: int = 4
    """Chaikin corner-cutting iterations; a cut that would leave the NavMesh keeps its corner."""
    plan_margin_m: float = 0.03
    """Paths are planned on the NavMesh shrunk by this margin so smoothing and rounding stay inside it."""
    seed: int = 0
    """Seed of the candidate points used to find each sector's farthest reachable point."""


@dataclass
class Plan:
    """A planned path: positions (N, 2) x,z with position 0 at the start, and facts about it."""

    positions: np.ndarray
    step_m: float
    """Actual spacing (smaller than requested when the room is too small)."""
    info: dict = field(default_factory=dict)
    exempt: list[int] = field(default_factory=lambda: [0])
    """Poses not held to the NavMesh: the start, and the straight way to the NavMesh when the start is off it."""


# ---------------------------------------------------------------- polylines


def polyline_length(pts: np.ndarray, closed: bool = False) -> float:
    p = np.concatenate([pts, pts[:1]]) if closed else pts
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def resample_polyline(
    pts: np.ndarray, n: int, *, closed: bool = False, spacing: float | None = None, equalize: int = 5
) -> np.ndarray:
    """n points (n, D) at equal arc length along a polyline (K, D), starting at pts[0].

    Open: the last point is the end (or at (n - 1) * spacing when given). Closed: the loop back to pts[0] is
    included and the spacing is length / n, so the last point is one step before the start. `equalize`
    iterations then move the points along the curve so the straight steps between them (chords, shorter
    than arcs at bends) become equal, keeping the first and (open) the last point.
    """
    pts = np.asarray(pts, np.float64)
    p = np.concatenate([pts, pts[:1]]) if closed else pts
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if spacing is None:
        spacing = s[-1] / n if closed else s[-1] / max(n - 1, 1)
    t = np.minimum(np.arange(n) * spacing, s[-1])

    def at(t):
        return np.stack([np.interp(t, s, p[:, k]) for k in range(p.shape[1])], axis=1)

    total = s[-1] if closed else t[-1]
    for _ in range(equalize if n > 2 and total > 0 else 0):
        q = at(t)
        chord = np.linalg.norm((np.concatenate([q[1:], q[:1]]) - q) if closed else np.diff(q, axis=0), axis=1)
        arc = np.diff(np.concatenate([t, [s[-1]]])) if closed else np.diff(t)
        w = arc / np.maximum(chord, 1e-9 * max(total, 1e-9))
        arc = w / w.sum() * total
        t = np.concatenate([[0.0], np.cumsum(arc)[:-1]]) if closed else np.concatenate([[0.0], np.cumsum(arc)])
    return at(t)


def subdivide_polyline(pts: np.ndarray, max_segment: float, closed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Insert points so no segment is longer than max_segment -> (points (K, 2), (K,) index of the source vertex or -1)."""
    p = np.concatenate([pts, pts[:1]]) if closed else pts
    n = np.maximum(np.ceil(np.linalg.norm(np.diff(p, axis=0), axis=1) / max_segment).astype(int), 1)
    out = [p[i] + (p[i + 1] - p[i]) * (np.arange(n[i])[:, None] / n[i]) for i in range(len(n))]
    src = [np.concatenate([[i], np.full(n[i] - 1, -1)]) for i in range(len(n))]
    if not closed:
        out.append(p[-1:])
        src.append(np.array([len(p) - 1]))
    return np.concatenate(out), np.concatenate(src).astype(int)


def smooth_polyline(
    nav: NavMesh, pts: np.ndarray, *, closed: bool, iterations: int, pinned: int | None = 0, max_segment: float = 0.3
) -> np.ndarray:
    """Constrained Chaikin corner cutting: a corner is cut only when the new chord stays inside the NavMesh.

    Segments are first split to at most max_segment so cuts stay local. Open polylines keep both ends;
    `pinned` (a vertex index of pts) is never cut (the start of a closed loop).
    """
    pts, src = subdivide_polyline(np.asarray(pts, np.float64), max_segment, closed)
    keep = np.zeros(len(pts), bool)
    if pinned is not None:
        keep[src == pinned] = True
    for _ in range(iterations):
        n = len(pts)
        if n < 3:
            break
        prev = np.roll(pts, 1, axis=0)
        nxt = np.roll(pts, -1, axis=0)
        a = 0.25 * prev + 0.75 * pts
        b = 0.75 * pts + 0.25 * nxt
        cut = ~keep.copy()
        if not closed:
            cut[[0, -1]] = False
        cut[cut] &= ~nav.blocked(a[cut], b[cut])
        out, out_keep = [], []
        for i in range(n):
            if cut[i]:
                out += [a[i], b[i]]
                out_keep += [False, False]
            else:
                out.append(pts[i])
                out_keep.append(bool(keep[i]))
        pts = np.asarray(out)
        keep = np.asarray(out_keep)
        d = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        dup = np.concatenate([[False], d < 1e-9]) & ~keep
        pts, keep = pts[~dup], keep[~dup]
    return pts


def truncate_polyline(pts: np.ndarray, length: float) -> np.ndarray:
    """The first `length` metres of a polyline (K, 2)."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if length >= s[-1]:
        return pts.copy()
    k = int(np.searchsorted(s, length, side="right"))
    t = (length - s[k - 1]) / max(seg[k - 1], 1e-30)
    return np.concatenate([pts[:k], (pts[k - 1] + t * (pts[k] - pts[k - 1]))[None]])


# ---------------------------------------------------------------- planning


def _planning_mesh(nav: NavMesh, start: np.ndarray, margin: float) -> NavMesh:
    """The NavMesh shrunk by margin (its piece containing or nearest to the start), or itself if nothing is left."""
    if margin <= 0:
        return nav
    try:
        return nav.offset(-margin, keep_xz=start)
    except ValueError:
        return nav


def _hub(nav: NavMesh, start: np.ndarray) -> tuple[np.ndarray, float]:
    """Where planning starts: the start itself, or the nearest NavMesh point (and its distance)."""
    if nav.contains(start)[0]:
        return start.copy(), 0.0
    hub = nav.closest_point(start)[0]
    return hub, float(np.linalg.norm(hub - start))


def sector_of(xz: np.ndarray, start: np.ndarray, n_sectors: int) -> np.ndarray:
    """Sector index (N,) of points around start: sector k is centred on lon = k * 2 pi / n (lon 0 = +z, +x at pi/2)."""
    d = np.asarray(xz, np.float64).reshape(-1, 2) - start
    lon = np.arctan2(d[:, 0], d[:, 1])
    return np.mod(np.round(lon / (2 * np.pi / n_sectors)), n_sectors).astype(int)


def sector_coverage(xz: np.ndarray, start: np.ndarray, n_sectors: int = 8, min_dist: float = 0.1) -> np.ndarray:
    """(n_sectors,) bool: whether some point lies in the sector at least min_dist from start."""
    xz = np.asarray(xz, np.float64).reshape(-1, 2)
    far = np.linalg.norm(xz - start, axis=1) >= min_dist
    out = np.zeros(n_sectors, bool)
    out[np.unique(sector_of(xz[far], start, n_sectors))] = True
    return out


def sector_reach(nav: NavMesh, start: np.ndarray, n_sectors: int, seed: int = 0, n_candidates: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Farthest NavMesh point of each sector from start: (targets (n, 2), distances (n,), 0 where empty).

    Points within the central half of a sector win over the rest of it, so petals spread evenly.
    """
    cand = np.concatenate([nav.sample_points(n_candidates, seed), nav.vertices])
    cand = cand[nav.contains(cand)]
    d = cand - start
    dist = np.linalg.norm(d, axis=1)
    width = 2 * np.pi / n_sectors
    lon = np.arctan2(d[:, 0], d[:, 1])
    sec = np.mod(np.round(lon / width), n_sectors).astype(int)
    off_centre = np.abs(np.angle(np.exp(1j * (lon - sec * width))))
    score = dist * np.where(off_centre <= 0.25 * width, 1.0, 0.5)
    targets = np.tile(start, (n_sectors, 1))
    reach = np.zeros(n_sectors)
    for k in range(n_sectors):
        m = np.flatnonzero(sec == k)
        if len(m):
            j = m[np.argmax(score[m])]
            targets[k], reach[k] = cand[j], dist[j]
    return targets, reach


def _water_fill(caps: np.ndarray, total: int) -> np.ndarray:
    """Integers m_k <= caps_k with sum(m) = min(total, sum(caps)), as equal as possible (largest caps last)."""
    m = np.zeros(len(caps), int)
    left = min(int(total), int(caps.sum()))
    while left > 0:
        open_ = np.flatnonzero(m < caps)
        give = max(left // len(open_), 1)
        for k in open_[np.argsort(caps[open_])]:
            g = min(give, caps[k] - m[k], left)
            m[k] += g
            left -= g
            if left == 0:
                break
    return m


def plan_sector(nav: NavMesh, start: np.ndarray, params: TrajectoryParams) -> Plan:
    """Sector exploration: from the start, out and back to the farthest reachable point of each sector in turn.

    Legs share the step budget (N - 1) equally, capped by each sector's reach; when even full legs cannot fill
    it, the step shrinks (info["step_adapted"]). A leg is the straight ray nearest the sector's centre line that
    is free for its whole length, else the smoothed NavMesh shortest path (A* + funnel) to the sector's farthest
    point. Legs are truncated to a whole number of steps so the tip and the return to the start fall on poses.
    """
    start = np.asarray(start, np.float64).reshape(2)
    n_steps = params.frames - 1
    step = params.step_m * params.stride
    plan_nav = _planning_mesh(nav, start, params.plan_margin_m)
    hub, off = _hub(plan_nav, start)
    approach = resample_polyline(np.stack([start, hub]), max(int(np.ceil(off / step)), 1) + 1) if off > 0 else start[None]
    targets, reach = sector_reach(plan_nav, hub, params.sectors, params.seed)
    width = 2 * np.pi / params.sectors
    fan = np.array([0.0, 0.1, -0.1, 0.2, -0.2, 0.3, -0.3, 0.4, -0.4]) * width  # centre line first
    legs, rays, lengths, sectors = [], [], [], []
    for k in range(params.sectors):
        lon = k * width + fan
        dirs = np.stack([np.sin(lon), np.cos(lon)], 1)
        free = np.maximum(plan_nav.ray_reach(hub, dirs) - 1e-3, 0.0)
        leg = np.stack([hub, hub])
        if reach[k] >= step:
            leg = smooth_polyline(plan_nav, plan_nav.path(hub, targets[k]), closed=False, iterations=params.smooth_iterations)
        cap = max(free.max(), polyline_length(leg))
        if cap < step:
            continue
        legs.append(leg)
        rays.append((dirs, free))
        lengths.append(cap)
        sectors.append(k)
    budget = n_steps - (len(approach) - 1)
    if not legs or budget <= 0:
        raise ValueError(
            f"no sector reaches {step:.3f} m (one step) from the start: the walkable area is too small "
            f"({nav.area:.2f} m^2); reduce step_m/stride or the agent radius"
        )
    lengths = np.asarray(lengths)
    want = budget + (budget % 2)  # whole out-and-back legs; an odd budget drops the very last pose

    def steps_at(s):
        return np.floor(lengths / s + 1e-9).astype(int)

    s_used = step
    if 2 * steps_at(step).sum() < want:
        lo, hi = 1e-4, step  # largest s with enough whole steps
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if 2 * steps_at(mid).sum() >= want else (lo, mid)
        s_used = lo
    m = _water_fill(steps_at(s_used), want // 2)
    pts = [approach]
    for leg, (dirs, free), mk in zip(legs, rays, m):
        if mk == 0:
            continue
        d = mk * s_used
        ok = np.flatnonzero(free >= d - 1e-9)
        if len(ok):
            out = hub + np.linspace(0.0, d, mk + 1)[:, None] * dirs[ok[0]]
        else:
            out = resample_polyline(truncate_polyline(leg, d), mk + 1)
        pts += [out[1:], out[::-1][1:]]
    positions = np.concatenate(pts)[: params.frames]
    positions[0] = start
    return Plan(
        positions,
        s_used,
        {
            "sectors_visited": [int(k) for k, mk in zip(sectors, m) if mk > 0],
            "sector_reach_m": reach.round(4).tolist(),
            "leg_steps": [int(x) for x in m],
            "step_adapted": bool(s_used < step * (1 - 1e-6)),
            "start_off_navmesh_m": off,
            "hub": hub.tolist(),
        },
    )


def _ring_candidate(nav: NavMesh, hub: np.ndarray, center: np.ndarray, radius: float, n_dirs: int, margin: float):
    """Star-shaped loop around center through hub: (loop points (n_dirs, 2) with loop[0] = hub, roundness) or None."""
    if not nav.contains(center)[0]:
        return None
    theta0 = np.arctan2(*(hub - center)[::-1])
    theta = theta0 + np.arange(n_dirs) * 2 * np.pi / n_dirs
    dirs = np.stack([np.cos(theta), np.sin(theta)], 1)
    reach = nav.ray_reach(center, dirs)
    if reach[0] < radius - 1e-9:
        return None
    rho = np.clip(np.minimum(radius, reach - margin), 0.0, None)
    rho[0] = radius
    loop = center + rho[:, None] * dirs
    loop[0] = hub
    return loop, float(np.mean(rho / radius))


def _ring_loop(plan_nav: NavMesh, hub: np.ndarray, loop_target: float, step: float, margin: float):
    """The best star-shaped loop through hub of length <= loop_target: (loop (K, 2), roundness, radius, centre, length)."""

    def candidate(radius: float, phi: float):
        c = hub + radius * np.array([np.cos(phi), np.sin(phi)])
        cand = _ring_candidate(plan_nav, hub, c, radius, 48, margin)
        return None if cand is None else (cand[0], cand[1], radius, c, polyline_length(cand[0], closed=True))

    r0 = loop_target / (2 * np.pi)
    cands = []
    for scale in (1.6, 1.3, 1.0, 0.85, 0.7, 0.55, 0.4, 0.3, 0.2, 0.12):
        if r0 * scale < 1.5 * step:
            break
        for phi in np.arange(16) * 2 * np.pi / 16:
            cand = candidate(r0 * scale, phi)
            if cand is not None:
                cands.append((phi, cand))
    if not cands:
        return None
    fits = [pc for pc in cands if pc[1][4] <= loop_target] or [min(cands, key=lambda pc: pc[1][4])]
    phi, best = max(fits, key=lambda pc: (round(pc[1][4] / loop_target, 2), pc[1][1]))
    longer = [c[2] for p_, c in cands if p_ == phi and c[4] > loop_target and c[2] > best[2]]
    if longer and best[4] <= loop_target:  # bisect the radius towards the target length on this bearing
        lo, hi = best[2], min(longer)
        for _ in range(12):
            cand = candidate(0.5 * (lo + hi), phi)
            if cand is not None and cand[4] <= loop_target:
                best, lo = cand, cand[2]
            else:
                hi = 0.5 * (lo + hi)
    return best


def plan_ring(nav: NavMesh, start: np.ndarray, params: TrajectoryParams) -> Plan:
    """A closed loop through the start around a nearby centre, run for 1-4 laps so the step stays as requested.

    For each lap count k the loop should be N * step / k long: centres on 16 bearings at distances R (around
    that length / 2 pi) from the start are tried; each loop has radius R, pulled in where the NavMesh is nearer;
    the longest loop not longer than the target (rounder on ties) wins and its radius is bisected towards the
    target. The fewest laps whose loop reaches 97 % of its target win (else the longest steps). Chords that would
    leave the NavMesh follow its shortest path instead; the loop is smoothed (the start stays a vertex) and the
    laps are resampled to N poses, the last one step before the first.
    """
    start = np.asarray(start, np.float64).reshape(2)
    step = params.step_m * params.stride
    target_len = params.frames * step
    plan_nav = _planning_mesh(nav, start, params.plan_margin_m)
    hub, off = _hub(plan_nav, start)
    margin = max(params.plan_margin_m, 0.5 * step)
    options = []
    for laps in (1, 2, 3, 4):
        loop_target = (target_len - 2 * off) / laps
        best = _ring_loop(plan_nav, hub, loop_target, step, margin) if loop_target > 0 else None
        if best is not None:
            options.append((laps, best, best[4] / loop_target))
            if best[4] >= 0.97 * loop_target:
                break
    if not options:
        raise ValueError(
            f"no loop of radius >= {1.5 * step:.3f} m fits around the start in the walkable area ({nav.area:.2f} m^2); "
            "reduce step_m/stride or the agent radius, or use kind=sector"
        )
    laps, (loop, roundness, radius, center, _), _ = next((o for o in options if o[2] >= 0.97), max(options, key=lambda o: o[2]))
    pieces = []
    for a, b in zip(loop, np.roll(loop, -1, axis=0)):
        if plan_nav.blocked(a[None], b[None])[0] or not plan_nav.contains(b)[0]:
            pieces.append(plan_nav.path(a, plan_nav.closest_point(b)[0])[:-1])
        else:
            pieces.append(a[None])
    loop = smooth_polyline(plan_nav, np.concatenate(pieces), closed=True, iterations=params.smooth_iterations, pinned=0)
    loop_length = polyline_length(loop, closed=True)
    tour = np.concatenate([loop] * laps)
    if off > 0:  # leave the camera to the NavMesh and come back the same way
        tour = np.concatenate([start[None], tour, hub[None]])
    length = polyline_length(tour, closed=True)
    spacing = length / params.frames
    positions = resample_polyline(tour, params.frames, closed=True)
    positions[0] = start
    return Plan(
        positions,
        spacing,
        {
            "ring_center": center.round(4).tolist(),
            "ring_radius_m": radius,
            "ring_roundness": roundness,
            "ring_laps": laps,
            "loop_length_m": loop_length,
            "step_adapted": bool(spacing < 0.98 * step),
            "start_off_navmesh_m": off,
            "hub": hub.tolist(),
        },
    )


def plan_path(nav: NavMesh, params: TrajectoryParams, start: np.ndarray | None = None) -> Plan:
    """Plan params.frames positions of params.kind on the NavMesh from start (x, z; default the camera, 0, 0)."""
    start = np.zeros(2) if start is None else np.asarray(start, np.float64).reshape(2)
    if params.frames < 2:
        raise ValueError(f"frames={params.frames} but a trajectory needs at least 2")
    if params.stride not in (1, 2, 4):
        raise ValueError(f"stride={params.stride} but it must be 1, 2 or 4")
    if params.step_m <= 0:
        raise ValueError(f"step_m={params.step_m} must be positive")
    plan = plan_sector(nav, start, params) if params.kind == PathKind.SECTOR else plan_ring(nav, start, params)
    if plan.info.get("start_off_navmesh_m", 0.0) > 0:  # poses on the straight way from the camera to the hub
        hub = np.asarray(plan.info["hub"])
        ab = hub - start
        t = np.clip((plan.positions - start) @ ab / (ab @ ab), 0.0, 1.0)
        on_way = np.linalg.norm(start + t[:, None] * ab - plan.positions, axis=1) < 1e-6
        plan.exempt = sorted({0, *np.flatnonzero(on_way & ~nav.contains(plan.positions)).tolist()})
    plan.info["requested_length_m"] = (params.frames - (0 if params.kind == PathKind.RING else 1)) * params.step_m * params.stride
    return plan


# ---------------------------------------------------------------- poses


def yaw_of_path(positions: np.ndarray, *, closed: bool, sigma_frames: float = 3.0) -> np.ndarray:
    """Heading (N,) about the up axis relative to the first pose's heading, smoothed, with yaw[0] = 0."""
    from scipy.ndimage import gaussian_filter1d

    p = np.asarray(positions, np.float64)
    d = (np.roll(p, -1, axis=0) - np.roll(p, 1, axis=0)) if closed else np.gradient(p, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 0], d[:, 1]))
    if sigma_frames > 0:
        heading = gaussian_filter1d(heading, sigma_frames, mode="wrap" if closed else "nearest")
    return heading - heading[0]


def poses_from_positions(positions: np.ndarray, yaw: np.ndarray | None = None, camera_y: float = 0.0) -> np.ndarray:
    """Upright world_from_cam poses (N, 4, 4) at x,z positions (N, 2), height camera_y, yaw (N,) about -Y.

    Yaw psi turns the camera's forward axis (+z) towards +x: forward = (sin psi, 0, cos psi).
    """
    positions = np.asarray(positions, np.float64)
    n = len(positions)
    yaw = np.zeros(n) if yaw is None else np.asarray(yaw, np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 0], T[:, 0, 2], T[:, 2, 0], T[:, 2, 2] = c, s, -s, c
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = positions[:, 0], camera_y, positions[:, 1]
    return T


def step_lengths(poses: np.ndarray) -> np.ndarray:
    """Distances (N - 1,) between consecutive camera centres of poses (N, 4, 4)."""
    return np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)


# ---------------------------------------------------------------- clearance against a mesh


CLEARANCE_CAP_M = 0.5
"""Clearances are measured exactly up to max(this, 2 x agent radius) and reported as that cap beyond it."""


def clearance_cap(agent_radius: float) -> float:
    return max(CLEARANCE_CAP_M, 2.0 * agent_radius)


def mesh_clearance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, cap: float = np.inf) -> np.ndarray:
    """Exact distance (N,) from points (N, 3) to the nearest triangle of a mesh (V, 3) / (F, 3), at most cap.

    Triangles whose bounding box is farther than cap from the points' bounding box are dropped first (a finite
    cap makes dense ERP meshes fast). The nearest vertex bounds each answer from above; the rest are bucketed
    by bounding-sphere radius (powers of two) with a KD-tree on their centroids per bucket, so only triangles
    whose sphere can be nearer are tested exactly (trimesh.triangles.closest_point).
    """
    import trimesh
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64).reshape(-1, 3)
    vertices = np.asarray(vertices)
    faces = np.asarray(faces).reshape(-1, 3)
    best = np.full(len(points), float(cap))
    if len(faces) == 0 or len(points) == 0:
        return best
    if np.isfinite(cap):
        lo, hi = points.min(axis=0) - cap, points.max(axis=0) + cap
        # Outcodes: a face's bounding box misses the box iff its three vertices share an outside bit.
        code = np.zeros(len(vertices), np.uint8)
        for k in range(3):
            code |= (vertices[:, k] < lo[k]).astype(np.uint8) << (2 * k)
            code |= (vertices[:, k] > hi[k]).astype(np.uint8) << (2 * k + 1)
        fc = code[faces]
        faces = faces[(fc[:, 0] & fc[:, 1] & fc[:, 2]) == 0]
        if len(faces) == 0:
            return best
    tri = vertices[faces].astype(np.float64)
    cen = tri.mean(axis=1)
    rad = np.sqrt(((tri - cen[:, None]) ** 2).sum(-1).max(axis=1))
    used = np.zeros(len(vertices), bool)
    used[faces.reshape(-1)] = True
    d_vertex = cKDTree(vertices[used].astype(np.float64)).query(points, distance_upper_bound=cap)[0]
    best = np.minimum(best, d_vertex)
    bucket = np.floor(np.log2(np.maximum(rad, 1e-6))).astype(int)
    for b in np.unique(bucket):
        idx = np.flatnonzero(bucket == b)
        cands = cKDTree(cen[idx]).query_ball_point(points, best + rad[idx].max())
        pi = np.repeat(np.arange(len(points)), [len(c) for c in cands])
        if len(pi) == 0:
            continue
        fi = idx[np.concatenate([np.asarray(c, int) for c in cands])]
        q = trimesh.triangles.closest_point(tri[fi], points[pi])
        np.minimum.at(best, pi, np.linalg.norm(q - points[pi], axis=1))
    return best


# ---------------------------------------------------------------- validation


@dataclass
class PoseIssue:
    index: int
    reasons: list[str]


def validate_poses(
    poses: np.ndarray, nav: NavMesh, clearance: np.ndarray, *, agent_radius: float, skip: tuple[int, ...] = ()
) -> list[PoseIssue]:
    """Every pose that leaves the walkable area, flies outside the agent's height band, or is closer than
    agent_radius to the mesh (clearance (N,) from mesh_clearance). Poses in `skip` are not checked."""
    xz = poses[:, [0, 2], 3]
    inside = nav.contains(xz)
    dist_out = np.where(inside, 0.0, -nav.clearance(xz))
    height = nav.floor_y - poses[:, 1, 3]
    step = nav.agent.get("step_height_m", 0.0)
    top = nav.agent.get("band_top_m", np.inf)
    issues = []
    for i in range(len(poses)):
        if i in skip:
            continue
        r = []
        if clearance[i] < agent_radius:
            r.append(f"clearance {clearance[i]:.3f} m < agent radius {agent_radius:.3f} m")
        if not inside[i]:
            r.append(f"outside the walkable NavMesh by {dist_out[i]:.3f} m")
        if not step < height[i] < top:
            r.append(f"camera {height[i]:.3f} m above the floor, outside ({step:.2f}, {top:.2f}) m")
        if r:
            issues.append(PoseIssue(i, r))
    return issues


def _ranges(idx: list[int]) -> str:
    out, k = [], 0
    while k < len(idx):
        j = k
        while j + 1 < len(idx) and idx[j + 1] == idx[j] + 1:
            j += 1
        out.append(str(idx[k]) if j == k else f"{idx[k]}-{idx[j]}")
        k = j + 1
    return ",".join(out)


def format_issues(issues: list[PoseIssue], n_poses: int) -> str:
    """One line naming every invalid pose, grouped by kind of problem."""
    groups: dict[str, list[tuple[int, str]]] = {}
    for it in issues:
        for r in it.reasons:
            key = r.split(" ", 1)[0] if not r.startswith("outside") else "outside"
            groups.setdefault(key, []).append((it.index, r))
    parts = []
    for key, items in groups.items():
        idx = [i for i, _ in items]
        worst = items[0][1]
        label = {"clearance": "too close to the mesh", "outside": "outside the walkable NavMesh", "camera": "outside the agent height band"}[key]
        parts.append(f"{label}: poses {_ranges(idx)} (e.g. pose {items[0][0]}: {worst})")
    return f"{len(issues)} of {n_poses} poses are invalid; " + "; ".join(parts)


# ---------------------------------------------------------------- files


def check_poses(poses: np.ndarray, where: str = "poses", tol: float = 1e-4) -> np.ndarray:
    """(N, 4, 4) float64 rigid transforms or TrajectoryFileError naming the first bad pose."""
    try:
        poses = np.asarray(poses, np.float64)
    except (TypeError, ValueError):
        raise TrajectoryFileError(f"{where}: poses are not a numeric array of 4x4 matrices") from None
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise TrajectoryFileError(f"{where}: {poses.shape=} but expected (N, 4, 4) with N >= 1")
    if not np.isfinite(poses).all():
        bad = int(np.flatnonzero(~np.isfinite(poses).reshape(len(poses), -1).all(1))[0])
        raise TrajectoryFileError(f"{where}: pose {bad} has NaN or inf entries")
    R = poses[:, :3, :3]
    err = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    row = np.abs(poses[:, 3] - [0, 0, 0, 1]).max(axis=1)
    bad = np.flatnonzero((err > tol) | (det < 0) | (row > tol))
    if len(bad):
        i = int(bad[0])
        raise TrajectoryFileError(
            f"{where}: pose {i} is not a rigid world_from_cam transform (|R R^T - I| = {err[i]:.2e}, det = {det[i]:.3f}, "
            f"last row {poses[i, 3].tolist()}); {len(bad)} such poses"
        )
    return poses


def read_tum(path: Path) -> np.ndarray:
    """TUM text `timestamp tx ty tz qx qy qz qw` (one pose a line, # comments) -> world_from_cam (N, 4, 4)."""
    rows = []
    for k, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise TrajectoryFileError(f"{path}:{k}: {len(parts)} values but TUM lines are 'timestamp tx ty tz qx qy qz qw'")
        try:
            rows.append([float(x) for x in parts])
        except ValueError:
            raise TrajectoryFileError(f"{path}:{k}: not numbers: {line[:60]!r}") from None
    if not rows:
        raise TrajectoryFileError(f"{path}: no poses")
    a = np.asarray(rows)
    q = quat_wxyz_from_xyzw(a[:, 4:8])
    norm = np.linalg.norm(q, axis=1)
    if (np.abs(norm - 1) > 1e-3).any():
        k = int(np.flatnonzero(np.abs(norm - 1) > 1e-3)[0])
        raise TrajectoryFileError(f"{path}: pose {k} has a quaternion of norm {norm[k]:.4f}, not 1")
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, :3] = rotmat_from_quat_wxyz(q)
    T[:, :3, 3] = a[:, 1:4]
    return T


def write_tum(path: Path, poses: np.ndarray, fps: float) -> None:
    q = quat_xyzw_from_wxyz(quat_wxyz_from_rotmat(poses[:, :3, :3]))
    lines = ["# timestamp tx ty tz qx qy qz qw  (world_from_cam, canonical frame: pose 0 = identity; OpenCV camera axes)"]
    for i, (T, qi) in enumerate(zip(poses, q)):
        t = T[:3, 3]
        lines.append(f"{i / fps:.6f} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} {qi[0]:.9f} {qi[1]:.9f} {qi[2]:.9f} {qi[3]:.9f}")
    Path(path).write_text("\n".join(lines) + "\n")


def read_trajectory_file(path: Path) -> np.ndarray:
    """A user trajectory: JSON ({"poses": [4x4, ...]} or a plain list of 4x4) or TUM text -> (N, 4, 4)."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise TrajectoryFileError(f"{path}: unreadable ({e})") from None
    if path.suffix.lower() == ".json" or text.lstrip().startswith(("{", "[")):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise TrajectoryFileError(f"{path}: invalid JSON ({e})") from None
        if isinstance(data, dict):
            if "poses" not in data:
                raise TrajectoryFileError(f"{path}: JSON object without a 'poses' list of 4x4 world_from_cam matrices")
            data = data["poses"]
        return check_poses(data, str(path))
    return check_poses(read_tum(path), str(path))


def load_trajectory(path: Path | str) -> np.ndarray:
    """world_from_cam poses (N, 4, 4) from a trajectory artifact directory, trajectory.json or a TUM file."""
    path = Path(path)
    if path.is_dir():
        path = path / TRAJECTORY_JSON
    return read_trajectory_file(path)


def write_trajectory(out_dir: Path, poses: np.ndarray, clearance: np.ndarray, *, fps: float, **meta) -> list[str]:
    """Write trajectory.json ({"poses", "clearance_m", "frame", "fps", **meta}) and trajectory.tum."""
    out_dir = Path(out_dir)
    doc = {
        "poses": np.asarray(poses, np.float64).tolist(),
        "clearance_m": np.asarray(clearance, np.float64).round(6).tolist(),
        "frame": FRAME,
        "convention": "world_from_cam 4x4, OpenCV camera axes (x right, y down, z forward), world up = -Y, metres",
        "fps": fps,
        **meta,
    }
    (out_dir / TRAJECTORY_JSON).write_text(json.dumps(doc))
    write_tum(out_dir / TRAJECTORY_TUM, poses, fps)
    return [TRAJECTORY_JSON, TRAJECTORY_TUM]
