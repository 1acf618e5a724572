"""Floor-plane registration of upright panoramas: each panorama's floor as a metric top-down image (camera height from
its depth), SIFT on those images and a 1-point rigid RANSAC over (x, z, yaw) whose inliers agree in position, keypoint
orientation and keypoint scale."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from panoworld.core.shapes import check_shape
from panoworld.geometry.floor_view import FloorView, agrees_with_pose, floor_matches, floor_view
from panoworld.geometry.upright import wrap_angle, yaw_matrix, yaw_matrix_xz
from panoworld.register.options import RegisterOptions


@dataclass(kw_only=True)
class FloorPose:
    """a_from_b of two panoramas from their floor images."""

    a_from_b: np.ndarray
    """(4, 4) rigid: yaw about gravity, horizontal translation, camera height difference."""
    inliers: int
    """Inliers counted once per keypoint spot (distinct_inliers)."""
    matches: int
    residual_m: float
    """RMS floor distance of the inliers (metres)."""
    second: int = 0
    """Inliers of the best other translation at the same yaw (at least DISTINCT_M from this one), counted as inliers
    are: a repeated floor pattern (tiles, planks) agrees nearly as well one pattern period along the baseline."""
    matched: np.ndarray | None = None
    """(matches, 2) int32: the floor matches the fit was made from (index in a, index in b), for floor_support at
    other poses."""


SAME_SPOT_M = 0.03
"""Inliers whose keypoints lie within this of each other (metres on the floor, in either view) are one piece of
evidence (distinct_inliers)."""


def spot_ids(v: FloorView, idx: np.ndarray) -> np.ndarray:
    """(M,) int64: the keypoint spot (SAME_SPOT_M cell) of each of v's keypoints idx (M,); equal ids, one spot."""
    cell = np.floor(v.xz[idx] / SAME_SPOT_M).astype(np.int64)
    return cell[:, 0] * (1 << 32) + cell[:, 1]


def _distinct(spots_a: np.ndarray, spots_b: np.ndarray) -> int:
    return int(min(len(np.unique(spots_a)), len(np.unique(spots_b))))


def distinct_inliers(a: FloorView, b: FloorView, m: np.ndarray) -> int:
    """How many of the matches m (M, 2) of floor views a, b are distinct evidence: the fewer of the distinct keypoint
    spots (SAME_SPOT_M cells) they use in a and in b. SIFT puts several keypoints on one spot (orientations, scales),
    and a chance match of two spots repeats as a cluster of inliers, most often where a wall's radial smear meets
    another's."""
    if len(m) == 0:
        return 0
    return _distinct(spot_ids(a, m[:, 0]), spot_ids(b, m[:, 1]))


DISTINCT_M = 0.3
"""A translation this far (metres) from the fitted one is another hypothesis (FloorPose.second)."""


def _translation_votes(p: np.ndarray, q: np.ndarray, dtheta: np.ndarray, dlog2: np.ndarray, yaw: float, *,
                       angle_tol: float, scale_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """The matches whose orientation difference is within angle_tol of yaw and whose sizes agree -> (their indices
    (M,), the translation p - R q each gives (M, 2))."""
    idx = np.flatnonzero((np.abs(dlog2) < scale_tol) & (np.abs(wrap_angle(dtheta - yaw)) < angle_tol))
    return idx, p[idx] - q[idx] @ yaw_matrix_xz(yaw).T


def _neighbour_counts(d: np.ndarray, threshold: float) -> np.ndarray:
    """(M,) int: how many of the translations d (M, 2) lie within threshold of each (itself included)."""
    counts = np.zeros(len(d), np.int64)
    for k0 in range(0, len(d), 1024):
        counts[k0:k0 + 1024] = (((d[k0:k0 + 1024, None] - d[None]) ** 2).sum(-1) < threshold**2).sum(1)
    return counts


def runner_up(p: np.ndarray, q: np.ndarray, dtheta: np.ndarray, dlog2: np.ndarray, yaw: float, t: np.ndarray, *,
              threshold: float, angle_tol: float = np.radians(15.0), scale_tol: float = 0.6,
              distinct: float = DISTINCT_M, spots: tuple[np.ndarray, np.ndarray] | None = None) -> int:
    """Inliers of the best translation at least `distinct` from t (2,) at the same yaw, over matched keypoints p, q
    (N, 2) with orientation and size differences dtheta, dlog2 (N,) (the inlier tests of oriented_rigid2d_ransac);
    with spots (each match's keypoint spot in a and in b, (N,) int64 each: spot_ids), counted as the fit's inliers
    are, once per spot (distinct_inliers)."""
    check_shape("p", p, "N 2")
    check_shape("q", q, "N 2")
    idx, d = _translation_votes(p, q, dtheta, dlog2, yaw, angle_tol=angle_tol, scale_tol=scale_tol)
    away = np.linalg.norm(d - t, axis=1) >= distinct
    idx, d = idx[away], d[away]
    counts = _neighbour_counts(d, threshold)
    if spots is None:
        return int(counts.max(initial=0))
    best = 0
    for k in np.argsort(-counts, kind="stable"):  # a translation's distinct count is at most its raw count
        if counts[k] <= best:
            break
        near = idx[np.linalg.norm(d - d[k], axis=1) < threshold]
        best = max(best, _distinct(spots[0][near], spots[1][near]))
    return best


def oriented_rigid2d_ransac(p: np.ndarray, q: np.ndarray, dtheta: np.ndarray, dlog2: np.ndarray, *, threshold: float,
                            angle_tol: float = np.radians(15.0), scale_tol: float = 0.6, hypotheses: int = 2000
                            ) -> tuple[float, np.ndarray, np.ndarray] | None:
    """2D rigid p ~ yaw_matrix_xz(yaw) q + t (no scale) over matched keypoints p, q (N, 2) whose orientations differ by dtheta
    (N,) (a_angle - b_angle, radians) and whose sizes differ by dlog2 (N,) octaves. Each match is a hypothesis by itself
    (yaw = its orientation difference); a match is an inlier when it lands within threshold, its orientation difference
    is within angle_tol of the yaw and its sizes within scale_tol octaves: three independent tests, so chance
    agreement stays at a few matches even without a ratio test. The first `hypotheses` matches whose sizes agree are
    the hypotheses (floor_pair orders them best descriptor distance first). The best is refined by least squares on
    its inliers. -> (yaw, t (2,), inliers (N,) bool), None without a hypothesis."""
    check_shape("p", p, "N 2")
    check_shape("q", q, "N 2")
    same = np.abs(dlog2) < scale_tol
    cand = np.flatnonzero(same)
    if len(cand) < 1:
        return None
    cand = np.sort(cand[:hypotheses])
    # A hypothesis can only gather matches whose orientation difference is within angle_tol of its own: bins of
    # angle_tol, each hypothesis tested against its own bin and the two beside it.
    nb = max(1, int(2 * np.pi // angle_tol))
    bins = np.floor((dtheta % (2 * np.pi)) / (2 * np.pi) * nb).astype(int) % nb
    best, best_n = -1, -1
    for b in range(nb):
        k = cand[bins[cand] == b]
        near = np.flatnonzero(same & np.isin(bins, [(b - 1) % nb, b, (b + 1) % nb]))
        for k0 in range(0, len(k), 256):
            kk = k[k0:k0 + 256]
            c, s = np.cos(dtheta[kk])[:, None], np.sin(dtheta[kk])[:, None]  # yaw_matrix_xz, written out
            qx, qz, px, pz = q[near, 0], q[near, 1], p[near, 0], p[near, 1]
            ex = c * (qx - q[kk, :1]) + s * (qz - q[kk, 1:]) - (px - p[kk, :1])
            ez = c * (qz - q[kk, 1:]) - s * (qx - q[kk, :1]) - (pz - p[kk, 1:])
            n = ((ex**2 + ez**2 < threshold**2)
                 & (np.abs(wrap_angle(dtheta[near][None] - dtheta[kk, None])) < angle_tol)).sum(1)
            if n.max() > best_n:
                best_n, best = int(n.max()), int(kk[int(np.argmax(n))])
    yaw = float(dtheta[best])
    t = p[best] - yaw_matrix_xz(yaw) @ q[best]
    inl = np.zeros(len(p), bool)
    inl[best] = True
    for _ in range(3):
        inl = inl | ((np.linalg.norm(q @ yaw_matrix_xz(yaw).T + t - p, axis=1) < threshold)
                     & (np.abs(wrap_angle(dtheta - yaw)) < angle_tol) & same)
        if inl.sum() >= 2:
            pc, qc = p[inl].mean(0), q[inl].mean(0)
            U, _, Vt = np.linalg.svd((q[inl] - qc).T @ (p[inl] - pc))
            Rr = Vt.T @ np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
            yaw, t = float(np.arctan2(Rr[0, 1], Rr[0, 0])), pc - Rr @ qc
        inl = ((np.linalg.norm(q @ yaw_matrix_xz(yaw).T + t - p, axis=1) < threshold)
               & (np.abs(wrap_angle(dtheta - yaw)) < angle_tol) & same)
    return yaw, t, inl


def fixed_yaw_translation(p: np.ndarray, q: np.ndarray, dtheta: np.ndarray, dlog2: np.ndarray, yaws: np.ndarray, *,
                          threshold: float, angle_tol: float = np.radians(15.0), scale_tol: float = 0.6
                          ) -> tuple[float, np.ndarray, np.ndarray] | None:
    """oriented_rigid2d_ransac with the yaw one of the candidates yaws (K,) (radians): per candidate, every match
    whose orientation difference is within angle_tol of it and whose sizes agree gives one translation p - R q; the
    translation most of them agree with (within threshold) is refined as their mean. The candidate with the most
    inliers wins. -> (yaw, t (2,), inliers (N,) bool), None without a hypothesis."""
    check_shape("p", p, "N 2")
    check_shape("q", q, "N 2")
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    for yaw in np.asarray(yaws, np.float64).ravel():
        idx, d = _translation_votes(p, q, dtheta, dlog2, yaw, angle_tol=angle_tol, scale_tol=scale_tol)
        if not len(idx):
            continue
        t = d[int(np.argmax(_neighbour_counts(d, threshold)))]
        for _ in range(3):
            near = np.linalg.norm(d - t, axis=1) < threshold
            t = d[near].mean(0)
        inl = np.zeros(len(p), bool)
        inl[idx[np.linalg.norm(d - t, axis=1) < threshold]] = True
        if best is None or inl.sum() > best[2].sum():
            best = (float(yaw), t, inl)
    return best


def panorama_floor_view(rgb: np.ndarray, small_depth: np.ndarray, exclude: np.ndarray | None, walls: float | None,
                        o: RegisterOptions) -> FloorView | None:
    """The floor view registration matches of a panorama rgb (H, 2H, 3) with its depth at the registration's height
    (small_depth (h, 2h)), no keypoint where exclude (grow_exclusion's rig mask) is: its image's x axis along a wall
    normal at `walls` (manhattan_frame: atan2(z, x), modulo 90 degrees) with floor_along_walls, the camera's axes
    without wall directions."""
    turn = -float(walls) if o.floor_along_walls and walls is not None else 0.0
    return floor_view(rgb, small_depth, radius_m=o.floor_radius_m, cell_m=o.floor_cell_m, exclude=exclude, turn=turn,
                      supersample=o.floor_supersample)


def floor_pair(a: FloorView, b: FloorView, *, threshold_m: float = 0.05, ratio: float = 1.0,
               yaws: np.ndarray | None = None) -> FloorPose | None:
    """a_from_b of two floor views: each keypoint of either view with its nearest neighbour in the other (Lowe's ratio
    test below 1; the same matches, and so the same fit inverted, whichever view is a),
    oriented_rigid2d_ransac (threshold_m on the floor), or fixed_yaw_translation when the yaw is known to be one of
    yaws (radians); the vertical offset from the camera heights (one floor), and the best distinct translation's
    inliers (FloorPose.second). None without a model."""
    if len(a.descriptors) < 2 or len(b.descriptors) < 2:
        return None
    m = floor_matches(a, b, ratio=ratio, both_ways=True)
    if len(m) < 2:
        return None
    args = (a.xz[m[:, 0]], b.xz[m[:, 1]], a.angles[m[:, 0]] - b.angles[m[:, 1]],
            np.log2(a.sizes[m[:, 0]] / b.sizes[m[:, 1]]))
    fit = (oriented_rigid2d_ransac(*args, threshold=threshold_m) if yaws is None
           else fixed_yaw_translation(*args, yaws, threshold=threshold_m))
    if fit is None:
        return None
    yaw, t, inl = fit
    T = np.eye(4)
    T[:3, :3] = yaw_matrix(yaw)
    T[:3, 3] = [t[0], a.height_m - b.height_m, t[1]]
    res = np.linalg.norm(b.xz[m[inl, 1]] @ yaw_matrix_xz(yaw).T + t - a.xz[m[inl, 0]], axis=1)
    spots = (spot_ids(a, m[:, 0]), spot_ids(b, m[:, 1]))
    return FloorPose(a_from_b=T, inliers=_distinct(spots[0][inl], spots[1][inl]), matches=len(m),
                     residual_m=float(np.sqrt(np.mean(res**2))) if len(res) else float("nan"),
                     second=runner_up(*args, yaw, t, threshold=threshold_m, spots=spots), matched=m.astype(np.int32))


def floor_support(a: FloorView, b: FloorView, a_from_b: np.ndarray, *, threshold_m: float = 0.08,
                  angle_tol: float = np.radians(15.0), scale_tol: float = 0.6, matches: np.ndarray | None = None) -> int:
    """How many of floor_matches(a, b) (or `matches`, (M, 2)) agree with a given pose a_from_b (4, 4): land within
    threshold_m of their partner on the floor, turn by the pose's yaw within angle_tol and keep their size within
    scale_tol octaves (the tests of floor_pair's inliers), counted once per keypoint spot (distinct_inliers)."""
    m = floor_matches(a, b) if matches is None else matches
    return distinct_inliers(a, b, m[agrees_with_pose(a, b, a_from_b, m, threshold_m=threshold_m, angle_tol=angle_tol,
                                                     scale_tol=scale_tol)])


def room_sides(f: FloorPose, a: FloorView, b: FloorView, depth_a: np.ndarray, depth_b: np.ndarray, *,
               threshold_m: float, margin_m: float = 0.15, margin_frac: float = 0.15
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the inlier matches (M,) of a floor pose f of two panoramas in two rooms lie, for a and for b: 1 inside
    that camera's room (nearer to it than its depth (H, W) in that direction, by margin_m plus margin_frac of that
    depth), 0 beyond its walls, -1 unknown (no depth there). None where the cameras stand in each other's free space
    (one room) or f keeps no matches."""
    from panoworld.register.pairwise import cameras_in_one_room, depth_toward

    T = f.a_from_b
    if f.matched is None or cameras_in_one_room(T, depth_a, depth_b, margin_m=margin_m, margin_frac=margin_frac):
        return None
    m = f.matched[agrees_with_pose(a, b, T, f.matched, threshold_m=threshold_m)]

    def inside(view: FloorView, depth: np.ndarray, idx: np.ndarray) -> np.ndarray:
        out = np.full(len(idx), -1)
        for k, i in enumerate(idx):
            p = np.array([view.xz[i, 0], view.height_m, view.xz[i, 1]])
            d = depth_toward(depth, p, window=1)
            if d > 0:
                out[k] = int(np.linalg.norm(p) <= d * (1 + margin_frac) + margin_m)
        return out

    return inside(a, depth_a, m[:, 0]), inside(b, depth_b, m[:, 1])


def floor_rooms_refusal(sides: tuple[np.ndarray, np.ndarray] | None, *, max_share: float = 0.5) -> str:
    """Why a floor pose of two panoramas in two rooms cannot hold ('' when it can), from where its inlier matches lie
    (room_sides' result): more than max_share of them inside both rooms. Floor that two rooms both see through a doorway
    lies in one of them, behind the other's wall; a chance fit between the floors of two rooms that share no view
    matches each room's own floor. Not judged where the cameras stand in each other's free space (sides None: one
    room, same_room_refusal) or where fewer than 3 inliers, or than half of them, have a depth in both views (a masked
    layout)."""
    if sides is None:
        return ""
    ia, ib = sides
    known = (ia >= 0) & (ib >= 0)
    both = int(((ia == 1) & (ib == 1)).sum())
    if known.sum() < max(3, 0.5 * len(ia)) or both <= max_share * known.sum():
        return ""
    return (f"{both} of its {int(known.sum())} floor inliers lie inside both rooms, and the cameras stand in two: "
            "each room's own floor matched by chance")


def beyond_both_rooms(sides: tuple[np.ndarray, np.ndarray] | None) -> tuple[int, int]:
    """How many inlier matches of a floor pose of two panoramas in two rooms lie beyond both rooms' walls, of how many,
    from room_sides' result: floor that both see only through openings their depths close, such as a hallway between
    two bedrooms that no panorama stands in; (0, 0) for cameras in one room (sides None)."""
    return (0, 0) if sides is None else (int(((sides[0] == 0) & (sides[1] == 0)).sum()), len(sides[0]))
