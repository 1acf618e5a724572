"""Layout registration of upright panoramas in adjoining rooms: a wall of one room against an opposed wall of the other,
judged by where the images agree (the other room seen through a doorway)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from panoworld.core.conventions import erp_dirs64
from panoworld.core.shapes import check_shape
from panoworld.geometry.floor_view import camera_height
from panoworld.geometry.polygons import fit_line
from panoworld.geometry.resize import resize_depth
from panoworld.geometry.upright import yaw_matrix, yaw_matrix_xz


@dataclass(kw_only=True)
class Wall:
    """A straight wall of the outline in its camera's floor plane (x right, z forward; metres)."""

    p0: np.ndarray
    """(2,) one end."""
    p1: np.ndarray
    """(2,) the other end."""
    normal: np.ndarray
    """(2,) unit, pointing away from the camera."""
    offset: float
    """Distance of the wall's line from the camera (normal . p0 > 0)."""


@dataclass(kw_only=True)
class Room:
    """One panorama's room as its layout shows it, and its image at low resolution."""

    dist: np.ndarray
    """(W,) horizontal distance to the wall per ERP column (metres; nan where unknown)."""
    walls: list[Wall]
    theta: float
    """Dominant wall normal direction modulo 90 degrees (radians, atan2(z, x))."""
    height_m: float
    """Camera height above the floor."""
    gray: np.ndarray
    """(h, 2h) float32 gray image in [0, 1] (the target of the other room's projection)."""
    depth: np.ndarray
    """(h, 2h) float64 ray depth (0 = unknown)."""
    src_gray: np.ndarray
    """(2h, 4h) float32 gray of the source pixels (projected into the other view)."""
    src_pts: np.ndarray
    """(2h, 4h, 3) float64 camera-frame points of the source pixels (the origin where the depth is unknown)."""


@dataclass(kw_only=True)
class LayoutPose:
    """a_from_b of two panoramas from their layouts and images."""

    a_from_b: np.ndarray
    """(4, 4) rigid: yaw about gravity, horizontal translation, camera height difference."""
    score: float
    """Agreeing image area of the best hypothesis (pixels of the scoring resolution, both directions)."""
    second: float
    """The same for the best hypothesis farther than the distinctness radius from it."""
    hypotheses: int
    """Hypotheses scored (after the overlap test)."""
    thickness_m: float
    """Wall thickness of the hypothesis the best placement was refined from."""


def _gray(rgb: np.ndarray, rows: int) -> np.ndarray:
    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    return cv2.resize(g, (2 * rows, rows), interpolation=cv2.INTER_AREA)


def _depth_at(depth: np.ndarray, rows: int) -> np.ndarray:
    """Ray depth at `rows` rows (resize_depth; 0 = unknown)."""
    return np.nan_to_num(resize_depth(depth, rows, 2 * rows), nan=0.0, posinf=0.0).astype(np.float64)


def outline(depth: np.ndarray, *, band_deg: float = 25.0, max_dist_m: float = 20.0) -> np.ndarray:
    """(W,) horizontal distance to the wall per column of a ray depth (H, W): the median of depth times the ray's
    horizontal component within band_deg of the horizon (a vertical wall keeps it constant); nan where fewer than half
    of those pixels are valid or beyond max_dist_m."""
    check_shape("depth", depth, "H W")
    h, w = depth.shape
    dirs = erp_dirs64(h, w)
    band = np.abs(dirs[:, 0, 1]) < np.sin(np.radians(band_deg))
    d = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)[band]
    horiz = d * np.hypot(dirs[band, :, 0], dirs[band, :, 2])
    ok = np.isfinite(horiz).sum(0) >= 0.5 * band.sum()
    out = np.full(w, np.nan)
    if ok.any():
        out[ok] = np.nanmedian(horiz[:, ok], axis=0)
    out[~(out < max_dist_m)] = np.nan
    return out


def outline_points(dist: np.ndarray) -> np.ndarray:
    """(W, 2) floor-plane points (x, z) of an outline (W,) (nan where unknown)."""
    lon = (np.arange(len(dist)) + 0.5) / len(dist) * 2 * np.pi - np.pi
    return np.stack([np.sin(lon), np.cos(lon)], 1) * dist[:, None]


def walls_of(dist: np.ndarray, *, tol_m: float = 0.03, min_len_m: float = 0.4, jump_m: float = 0.25,
             min_facing: float = 0.25) -> list[Wall]:
    """Straight walls of an outline (W,): the closed polyline split at unknown columns and depth jumps, simplified
    (Douglas-Peucker, tol_m), segments of at least min_len_m whose normal faces the camera (|cos| of the angle between
    the normal and the ray to the segment's middle at least min_facing; grazing segments are occlusion edges)."""
    pts = outline_points(dist)
    ok = np.isfinite(dist)
    n = len(dist)
    if ok.sum() < 8:
        return []
    start = int(np.argmin(ok)) if not ok.all() else int(np.nanargmax(dist))  # a corner
    order = np.roll(np.arange(n), -start)
    runs, cur = [], []
    for k in order:
        if ok[k] and cur and np.linalg.norm(pts[k] - pts[cur[-1]]) > jump_m:
            runs.append(cur)
            cur = []
        if ok[k]:
            cur.append(k)
        elif cur:
            runs.append(cur)
            cur = []
    if cur:
        runs.append(cur)
    if ok.all() and len(runs) > 1 and np.linalg.norm(pts[runs[0][0]] - pts[runs[-1][-1]]) <= jump_m:
        runs[0] = runs.pop() + runs[0]
    walls = []
    for run in runs:
        if len(run) < 3:
            continue
        c = (pts[run] * 1000.0).astype(np.float32).reshape(-1, 1, 2)
        idx = cv2.approxPolyDP(c, tol_m * 1000.0, False).reshape(-1, 2) / 1000.0
        for p0, p1 in zip(idx[:-1], idx[1:]):
            v = p1 - p0
            length = float(np.linalg.norm(v))
            if length < min_len_m:
                continue
            nrm = np.array([-v[1], v[0]]) / length
            mid = 0.5 * (p0 + p1)
            if nrm @ mid < 0:
                nrm = -nrm
            if nrm @ mid / max(np.linalg.norm(mid), 1e-9) < min_facing:
                continue
            walls.append(Wall(p0=p0.astype(np.float64), p1=p1.astype(np.float64), normal=nrm,
                              offset=float(nrm @ p0)))
    return walls


def dominant_direction(walls: list[Wall]) -> float:
    """Length-weighted mean of the wall normals' directions modulo 90 degrees (radians)."""
    z = sum(np.linalg.norm(w.p1 - w.p0) * np.exp(4j * np.arctan2(w.normal[1], w.normal[0])) for w in walls)
    return float(np.angle(z) / 4) if walls else 0.0


def manhattan_fraction(walls: list[Wall], theta: float, *, tol_deg: float = 5.0) -> float:
    """Fraction of the wall length whose normal lies within tol_deg of the axes of theta."""
    length = np.array([np.linalg.norm(w.p1 - w.p0) for w in walls])
    ang = np.array([np.arctan2(w.normal[1], w.normal[0]) for w in walls]) - theta
    off = np.abs(np.angle(np.exp(4j * ang))) / 4
    return float(length[off < np.radians(tol_deg)].sum() / max(length.sum(), 1e-9))


def manhattan_frame(depth: np.ndarray, *, min_manhattan: float = 0.9, min_valid: float = 0.95, tol_deg: float = 5.0
                    ) -> float | None:
    """The wall directions of a panorama's room modulo 90 degrees (radians, atan2(z, x) of the wall normals, the
    length-weighted mean of the walls within tol_deg of the dominant axes) from its ray depth (H, W) (0 = unknown);
    None when the outline is known in fewer than min_valid of the columns (masked or open layout) or less than
    min_manhattan of the wall length lies within tol_deg of the axes (not a Manhattan room, or a layout seen from
    outside its polygon)."""
    dist = outline(depth)
    if np.isfinite(dist).mean() < min_valid:
        return None
    walls = walls_of(dist)
    if not walls:
        return None
    theta = dominant_direction(walls)
    if manhattan_fraction(walls, theta, tol_deg=tol_deg) < min_manhattan:
        return None
    on_axis = [w for w in walls if abs(np.angle(np.exp(4j * (np.arctan2(w.normal[1], w.normal[0]) - theta)))) / 4
               < np.radians(tol_deg)]
    pts = outline_points(dist)
    pts = pts[np.isfinite(dist)]
    return dominant_direction([fitted_wall(w, pts) for w in on_axis])


def fitted_wall(wall: Wall, pts: np.ndarray, *, tol_m: float = 0.03, trim: float = 0.05) -> Wall:
    """The wall with its normal fitted (total least squares) to the outline points pts (N, 2) within tol_m of its
    line, its ends' trim of its length left out (a corner rounds there); walls_of takes the normal from two outline
    samples, the ends of the simplified polyline, whose noise tilts it. The wall itself where fewer than 5 points
    lie on it."""
    v = wall.p1 - wall.p0
    length = float(np.linalg.norm(v))
    rel = pts - wall.p0
    along = rel @ v / max(length, 1e-9)
    on = pts[(along > trim * length) & (along < (1 - trim) * length) & (np.abs(rel @ wall.normal) < tol_m)]
    if len(on) < 5:
        return wall
    nrm, offset = fit_line(on)
    sign = 1.0 if nrm @ wall.normal >= 0 else -1.0
    return Wall(p0=wall.p0, p1=wall.p1, normal=sign * nrm, offset=sign * offset)


def room(rgb: np.ndarray, depth: np.ndarray, *, rows: int = 96, min_manhattan: float = 0.8) -> Room | None:
    """The Room of a panorama rgb (H, 2H, 3) with ray depth (h, 2h) (0 = unknown); None without walls or a camera
    height, or when less than min_manhattan of the wall length is at right angles (no dominant direction: a layout
    seen from outside its polygon looks like a circle)."""
    check_shape("panorama", rgb, "H W 3")
    h = camera_height(depth)
    dist = outline(depth)
    walls = walls_of(dist)
    if h is None or not walls or manhattan_fraction(walls, dominant_direction(walls)) < min_manhattan:
        return None
    gray = _gray(rgb, rows)
    d = _depth_at(depth, rows)
    src_rows = 2 * rows
    sg = _gray(rgb, src_rows)
    sd = _depth_at(depth, src_rows)
    pts = erp_dirs64(src_rows, 2 * src_rows) * sd[..., None]
    return Room(dist=dist, walls=walls, theta=dominant_direction(walls), height_m=float(h), gray=gray, depth=d,
                src_gray=sg, src_pts=pts)


def pose_2d(yaw: float, t: np.ndarray, dy: float = 0.0) -> np.ndarray:
    """(4, 4) a_from_b of a yaw (radians) and a floor-plane translation t (x, z), dy the vertical offset."""
    T = np.eye(4)
    T[:3, :3] = yaw_matrix(yaw)
    T[:3, 3] = [t[0], dy, t[1]]
    return T


def _inside_fraction(dist_a: np.ndarray, pts: np.ndarray, margin: float) -> float:
    """Fraction of the floor points pts (N, 2) (a's frame, finite) inside a's outline by more than margin."""
    if not len(pts):
        return 0.0
    w = len(dist_a)
    col = (np.floor((np.arctan2(pts[:, 0], pts[:, 1]) + np.pi) / (2 * np.pi) * w).astype(int)) % w
    r = dist_a[col]
    return float(np.mean(np.isfinite(r) & (np.linalg.norm(pts, axis=1) < r - margin)))


def overlaps(a: Room, b: Room, yaw: float, t: np.ndarray, *, margin_m: float = 0.1, max_fraction: float = 0.03
             ) -> bool:
    """Whether b's room placed at (yaw, t) in a's frame overlaps a's room in area (more than max_fraction of either
    outline inside the other by more than margin_m), or either camera stands in the other's room."""
    R = yaw_matrix_xz(yaw)
    pb = outline_points(b.dist)
    pb = pb[np.isfinite(b.dist)] @ R.T + t
    pa = outline_points(a.dist)
    pa = (pa[np.isfinite(a.dist)] - t) @ R  # into b's frame
    cams = (_inside_fraction(a.dist, t[None], 0.0) > 0) or (_inside_fraction(b.dist, (-t @ R)[None], 0.0) > 0)
    return cams or _inside_fraction(a.dist, pb, margin_m) > max_fraction or \
        _inside_fraction(b.dist, pa, margin_m) > max_fraction


@numba.njit(cache=True)
def _splat(pts, gray, T, stride, depth_t, behind, beyond):
    """Project the source points pts (H, W, 3) (every stride-th row and column) by T (4, 4) into the target ERP
    (h, 2h): the nearest point per pixel that lies beyond the target's depth times `behind` plus `beyond` metres ->
    (gray (h, w), filled (h, w) bool)."""
    h, w = depth_t.shape
    zb = np.full((h, w), np.inf)
    out = np.zeros((h, w), np.float32)
    for i in range(0, pts.shape[0], stride):
        for j in range(0, pts.shape[1], stride):
            p0, p1, p2 = pts[i, j, 0], pts[i, j, 1], pts[i, j, 2]
            if p0 == 0 and p1 == 0 and p2 == 0:
                continue
            x = T[0, 0] * p0 + T[0, 1] * p1 + T[0, 2] * p2 + T[0, 3]
            y = T[1, 0] * p0 + T[1, 1] * p1 + T[1, 2] * p2 + T[1, 3]
            z = T[2, 0] * p0 + T[2, 1] * p1 + T[2, 2] * p2 + T[2, 3]
            _put(x, y, z, gray[i, j], depth_t, behind, beyond, zb, out, h, w)
    return out, np.isfinite(zb)


@numba.njit(cache=True, inline="always")
def _put(x, y, z, g, depth_t, behind, beyond, zb, out, h, w):
    r = np.sqrt(x * x + y * y + z * z)
    if r < 1e-6:
        return
    lon = np.arctan2(x, z)
    lat = np.arcsin(-y / r)
    u = int((lon / (2 * np.pi) + 0.5) * w) % w
    v = int((0.5 - lat / np.pi) * h)
    if v < 0 or v >= h:
        return
    d = depth_t[v, u]
    if d <= 0 or r < d * behind + beyond or r >= zb[v, u]:
        return
    zb[v, u] = r
    out[v, u] = g


def _agreeing(a: np.ndarray, b: np.ndarray, m: np.ndarray, weight: np.ndarray, win: int, min_std: float,
              min_ncc: float) -> float:
    """Count, weighted by the row weights (h,), of the pixels of images a, b (h, w) whose win x win windows, filled by
    mask m (at least 80 %) and textured in both (std above min_std), correlate above min_ncc."""
    def box(x):
        return cv2.boxFilter(x, -1, (win, win), normalize=False, borderType=cv2.BORDER_REFLECT)

    n = box(m)
    sa, sb = box(a * m), box(b * m)
    saa, sbb, sab = box(a * a * m), box(b * b * m), box(a * b * m)
    nn = np.maximum(n, 1)
    va = saa / nn - (sa / nn) ** 2
    vb = sbb / nn - (sb / nn) ** 2
    cov = sab / nn - sa * sb / nn**2
    tex = (n >= 0.8 * win * win) & (va > min_std**2) & (vb > min_std**2)
    ncc = np.where(tex, cov / np.sqrt(np.maximum(va * vb, 1e-12)), 0)
    return float(((ncc > min_ncc) * weight[:, None]).sum())


def agreement(target: Room, source: Room, target_from_source: np.ndarray, *, stride: int = 1, win: int = 5,
              min_std: float = 0.03, min_ncc: float = 0.6, behind: float = 1.02, beyond_m: float = 0.4,
              null_shifts: tuple[int, ...] = (-16, -8, 8, 16)) -> float:
    """Image area (pixels of target's grid, weighted by cos latitude) where the source room, projected into the
    target's view well behind the target's layout (beyond its depth times `behind` plus beyond_m: the rooms' own
    floor and ceiling lines just behind a shared wall are alike at any slide), agrees with the target image (_agreeing:
    local NCC), less the mean agreement with the target image turned by null_shifts columns (what agrees by chance in
    the same region): what the target sees through a doorway."""
    warped, filled = _splat(source.src_pts, source.src_gray, np.ascontiguousarray(target_from_source, np.float64), stride,
                            target.depth, behind, beyond_m)
    rows = np.flatnonzero(filled.any(1))
    if len(rows) == 0:
        return 0.0
    r0, r1 = max(rows[0] - win, 0), min(rows[-1] + win + 1, len(filled))  # only the rows the projection reaches
    a, b, m = target.gray[r0:r1], warped[r0:r1], filled[r0:r1].astype(np.float32)
    lat = (0.5 - (np.arange(r0, r1) + 0.5) / len(filled)) * np.pi
    hit = _agreeing(a, b, m, np.cos(lat), win, min_std, min_ncc)
    if not null_shifts or hit == 0:
        return hit
    return hit - float(np.mean([_agreeing(np.roll(a, k, 1), b, m, np.cos(lat), win, min_std, min_ncc)
                                for k in null_shifts]))


def hypotheses(a: Room, b: Room, *, thickness_m: tuple[float, ...] = (0.15,), step_m: float = 0.1,
               min_shared_m: float = 0.6, snap_deg: float = 10.0) -> list[tuple[float, np.ndarray, float]]:
    """(yaw, t (2,), thickness) placing b in a's frame: the yaw one of the 4 Manhattan candidates of the rooms'
    dominant directions; a wall of a and a wall of b facing it (normals opposed within snap_deg) at a wall thickness;
    the slide along them every step_m where they share at least min_shared_m; rooms that overlap are dropped."""
    out, seen = [], set()
    for k in range(4):
        yaw = float(np.angle(np.exp(1j * (b.theta - a.theta + k * np.pi / 2))))
        R = yaw_matrix_xz(yaw)
        for wa in a.walls:
            tau = np.array([-wa.normal[1], wa.normal[0]])
            a0, a1 = sorted((tau @ wa.p0, tau @ wa.p1))
            for wb in b.walls:
                m = R @ wb.normal
                if m @ wa.normal > -np.cos(np.radians(snap_deg)):
                    continue
                b0, b1 = sorted((tau @ (R @ wb.p0), tau @ (R @ wb.p1)))
                lo, hi = a0 - b1 + min_shared_m, a1 - b0 - min_shared_m
                if hi < lo:
                    continue
                for th in thickness_m:
                    along_n = wa.offset + th + wb.offset
                    for s in np.arange(lo, hi + 1e-9, step_m):
                        t = along_n * wa.normal + s * tau
                        key = (k, round(t[0] / 0.05), round(t[1] / 0.05))
                        if key in seen:
                            continue
                        seen.add(key)
                        if not overlaps(a, b, yaw, t):
                            out.append((yaw, t, th))
    return out


def score(a: Room, b: Room, yaw: float, t: np.ndarray, *, stride: int = 1, null: bool = True) -> float:
    """Agreement both ways of b placed at (yaw, t) in a's frame (without the chance level unless null)."""
    T = pose_2d(yaw, t, a.height_m - b.height_m)
    shifts = (-16, -8, 8, 16) if null else ()
    return (agreement(a, b, T, stride=stride, null_shifts=shifts)
            + agreement(b, a, np.linalg.inv(T), stride=stride, null_shifts=shifts))


def _distinct(h: tuple[float, np.ndarray], others: list[tuple[float, np.ndarray]], radius_m: float, yaw_deg: float
              ) -> bool:
    return all(np.linalg.norm(h[1] - o[1]) > radius_m or abs(np.degrees(np.angle(np.exp(1j * (h[0] - o[0]))))) > yaw_deg
               for o in others)


def _refine(a: Room, b: Room, yaw: float, t: np.ndarray, s: float, *, stride: int, steps: tuple[tuple[float, float], ...]
            ) -> tuple[float, np.ndarray, float]:
    """Pattern search of the score over (yaw, t) from (yaw, t) scoring s, with (yaw radians, metres) step pairs,
    overlapping placements excluded."""
    for dyaw, dt in steps:
        moved = True
        while moved:
            moved = False
            for cand in ((yaw + dyaw, t), (yaw - dyaw, t), (yaw, t + [dt, 0]), (yaw, t - [dt, 0]), (yaw, t + [0, dt]),
                         (yaw, t - [0, dt])):
                if overlaps(a, b, *cand):
                    continue
                c = score(a, b, *cand, stride=stride)
                if c > s:
                    yaw, t, s, moved = cand[0], cand[1], c, True
    return yaw, t, s


def layout_pair(a: Room, b: Room, *, thickness_m: tuple[float, ...] = (0.15,), step_m: float = 0.1,
                keep: int = 6, radius_m: float = 0.3, yaw_deg: float = 5.0, stride: int = 2) -> LayoutPose | None:
    """a_from_b of two panoramas in adjoining rooms: every hypothesis scored (score without the chance level), the
    `keep` best that are distinct (farther than radius_m or yaw_deg from a better one) refined on the score less its
    chance level by a pattern search (0.5 deg / 5 cm, then half); the best and the best distinct from it reported.
    None without a hypothesis."""
    H = hypotheses(a, b, thickness_m=thickness_m, step_m=step_m)
    if not H:
        return None
    sc = np.array([score(a, b, y, t, stride=stride, null=False) for y, t, _ in H])
    top: list[tuple[float, np.ndarray, float, float]] = []
    for k in np.argsort(-sc):
        if _distinct(H[k][:2], [x[:2] for x in top], radius_m, yaw_deg):
            top.append((H[k][0], H[k][1], float(sc[k]), H[k][2]))
            if len(top) == keep:
                break
    steps = ((np.radians(0.5), 0.05), (np.radians(0.25), 0.025))
    refined = []
    for y, t, _, th in top:
        y2, t2, s2 = _refine(a, b, y, t, score(a, b, y, t, stride=stride), stride=stride, steps=steps)
        refined.append((y2, t2, s2, th))
    refined.sort(key=lambda x: -x[2])
    best = refined[0]
    second = next((r[2] for r in refined[1:] if _distinct(r[:2], [best[:2]], radius_m, yaw_deg)), 0.0)
    return LayoutPose(a_from_b=pose_2d(best[0], best[1], a.height_m - b.height_m), score=best[2], second=second,
                      hypotheses=len(H), thickness_m=best[3])
