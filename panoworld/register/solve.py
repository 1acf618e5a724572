"""All panoramas of a home into one frame: depth-backed and bearing-only estimates over the candidate pairs
(pair_select), a pose graph of rigid groups joined where the geometry fixes them (panoworld/register/graph.py), and
per-panorama quality figures; panoramas that cannot be joined are reported, not placed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from panoworld.core.conventions import invert_pose, pose_from_rt
from panoworld.core.parallel import cpu_threads, map_ahead
from panoworld.geometry.floor_view import FloorView, camera_height
from panoworld.geometry.level import level_from_cam, levelled, levelled_depth, tilt_deg
from panoworld.geometry.resize import rgbd_at_height
from panoworld.geometry.upright import wrap_angle, yaw_of
from panoworld.io.home import to_levelled
from panoworld.register.cuts import refuse_outvoted_cuts, weak_floor
from panoworld.register.floor import (
    FloorPose,
    beyond_both_rooms,
    floor_pair,
    floor_rooms_refusal,
    panorama_floor_view,
    room_sides,
)
from panoworld.register.graph import (
    BEARING,
    DEPTH,
    DIRECTION,
    FLOOR,
    LAYOUT,
    Edge,
    bridging_groups,
    group_of,
    solve_graph,
    strength,
    tree_path,
)
from panoworld.register.layout import LayoutPose, layout_pair, manhattan_frame, room
from panoworld.register.options import RegisterOptions
from panoworld.register.pair_select import appearance_descriptor, bridge_pairs, candidate_pairs
from panoworld.register.pairwise import (
    WHOLE_ROOM,
    Features,
    PairResult,
    erp_features,
    grow_exclusion,
    match,
    register_pair,
    rooms_overlap_refusal,
    same_room_refusal,
    valid_share,
)
from panoworld.register.registration import Registration
from panoworld.register.upright import UprightPose, max_baseline, metric_scale, upright_relative_pose

MAX_PAIR_THREADS = 8
"""Panoramas prepared and pairs registered at once at most (threads)."""

FEW_KEYPOINTS = 100
"""An unregistered panorama with fewer SIFT keypoints than this is named as featureless in its reason (a blank,
dark or blurred image: nothing to match); a real 2048 x 1024 room keeps thousands."""


def pair_threads() -> int:
    """Panoramas prepared (features, floor view) and pairs registered at once: core.parallel.cpu_threads (the CPUs,
    or OMP_NUM_THREADS where set), at most MAX_PAIR_THREADS."""
    return cpu_threads(MAX_PAIR_THREADS)


def _bearing_pair(fi: Features, fj: Features, m: np.ndarray, rows: int, height_i: float | None, o: RegisterOptions
                  ) -> tuple[UprightPose | None, float, int]:
    """Upright two-view geometry of the matches m (panoramas of `rows` rows), its metric scale and, with camera i's
    height above the floor (metres), the longest baseline the floor allows -> (pose or None, scale (nan: none),
    support)."""
    xi, xj = fi.bearings[m[:, 0]], fj.bearings[m[:, 1]]
    pose = upright_relative_pose(xi, xj, threshold_deg=o.bearing_threshold_px * 180.0 / rows,
                                 min_inliers=o.min_bearing_inliers)
    if pose is None:
        return None, float("nan"), 0
    if height_i is not None:
        pose = replace(pose, max_baseline_m=max_baseline(pose, xi, xj, height_i))
    scale, support = metric_scale(pose, xi, xj, fi.depth[m[:, 0]], fj.depth[m[:, 1]])
    return pose, scale, support


def register_panoramas(names: list[str], rgbs: dict[str, np.ndarray], depths: dict[str, np.ndarray], *,
                       given: dict[str, np.ndarray] | None = None, options: RegisterOptions | None = None,
                       rig_masks: dict[str, np.ndarray] | None = None, progress=None) -> Registration:
    """Register panoramas (RGB uint8 and metric ray depth (H, W) each; rig_masks: an ERP mask (H', 2H') bool per
    panorama that has a detected capture rig, where no keypoint is taken, on the panorama or its floor image); given
    poses are kept as they are (and anchor the others), otherwise the largest set joined together is registered in
    its first panorama's frame. A panorama whose depth shows its floor tilted is registered levelled and its pose
    composed with the levelling (geometry.level; registration.json's levelled_tilt_deg). A pair is a
    depth edge when RANSAC keeps >= min_inliers, the refined pose has >= min_consistency free-space consistency and
    >= min_overlap overlap, and the bearing-only estimate of the same matches does not contradict it (_contradiction);
    otherwise a bearing edge when upright two-view geometry keeps >= min_bearing_inliers
    (metric when >= min_scale_support matched points' depths agree on its scale, a direction edge when not)."""
    o = options or RegisterOptions()
    level = {n: R for n in names if n in depths and (R := level_from_cam(depths[n])) is not None}
    lift = {n: pose_from_rt(level[n], np.zeros(3)) for n in level}
    rgbs = {n: levelled(x, level[n]) if n in level else x for n, x in rgbs.items()}
    depths = {n: levelled_depth(x, level[n]) if n in level else x for n, x in depths.items()}
    rig_masks = {n: levelled(m, level[n], nearest=True) if n in level else m for n, m in (rig_masks or {}).items()}
    given = to_levelled(given or {}, level)
    need = [n for n in names if n not in given]
    pairs: dict[tuple[int, int], PairResult] = {}
    bearing: dict[tuple[int, int], tuple[UprightPose | None, float, int]] = {}
    floors: dict[tuple[int, int], FloorPose | None] = {}
    frames: dict[str, float | None] = {}
    small: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    views: dict[str, FloorView | None] = {}
    keypoints: dict[str, int] = {}
    k = len(names)
    if need and k > 1:  # one panorama has no pair: nothing to prepare
        def one_panorama(n: str):
            rgbd = rgbd_at_height(rgbs[n], depths[n], o.height)
            rig = grow_exclusion((rig_masks or {}).get(n))
            walls = manhattan_frame(rgbd[1]) if o.manhattan or o.floor_along_walls else None
            view = panorama_floor_view(rgbs[n], rgbd[1], rig, walls, o) if o.floor else None
            return (rgbd, erp_features(*rgbd, max_features=o.max_features, exclude=rig), walls, view,
                    appearance_descriptor(rgbd[0]) if k > o.all_pairs_up_to else None)

        # Each panorama on its own, on pair_threads() threads (SIFT, the floor view's sampling and resizing release
        # the GIL), results taken in name order: the same as one at a time.
        small, feats, walls, views, looks = (dict(zip(names, x)) for x in zip(
            *map_ahead(one_panorama, names, workers=pair_threads())))
        frames = walls if o.manhattan else dict.fromkeys(names)
        keypoints = {n: len(f.bearings) for n, f in feats.items()}
        looks = looks if k > o.all_pairs_up_to else None
        heights = {n: v.height_m if (v := views[n]) is not None else camera_height(small[n][1]) for n in names}

        def one_pair(ab: tuple[int, int]):
            a, b = ab
            fa, fb = feats[names[a]], feats[names[b]]
            m = match(fa, fb)
            pair = register_pair(fa, fb, small[names[a]][1], small[names[b]][1], max_error_m=o.max_error_m,
                                 min_inliers=o.min_inliers, refine_height=o.refine_height,
                                 refine_iterations=o.refine_iterations, matches=m)
            rows = max(small[names[a]][1].shape[0], small[names[b]][1].shape[0])
            va, vb = views[names[a]], views[names[b]]
            return pair, _bearing_pair(fa, fb, m, rows, heights[names[a]], o), (
                None if va is None or vb is None else floor_pair(
                    va, vb, threshold_m=o.floor_threshold_m, ratio=o.floor_ratio,
                    yaws=manhattan_yaws(frames[names[a]], frames[names[b]])))

        def try_pairs(todo: list[tuple[int, int]]) -> None:
            # Each pair on its own: on pair_threads() threads (matching, RANSAC and the floor's distance matrix release
            # the GIL), results taken in the pairs' order, so the registration is the same as one pair at a time; only
            # a few pairs are in flight, so an error or Ctrl-C waits for those alone.
            for (a, b), (pairs[a, b], bearing[a, b], floors[a, b]) in zip(
                    todo, map_ahead(one_pair, todo, workers=pair_threads())):
                if progress:
                    progress(names[a], names[b], pairs[a, b])

        try_pairs(candidate_pairs(names, looks, given=given, all_up_to=o.all_pairs_up_to))
        if k > o.all_pairs_up_to:
            group = bridging_groups(names, _edges(names, pairs, bearing, floors, frames, small, views, o)[0], given)
            try_pairs(bridge_pairs(names, group, set(pairs)))
    edges, refused, depth_ok, floor_refused, off_frames, beyond, impossible = _edges(
        names, pairs, bearing, floors, frames, small, views, o)
    layouts: dict[tuple[int, int], LayoutPose | None] = {}
    layout_refused: dict[tuple[int, int], str] = {}
    if o.layout and need:  # tried across weak floor edges too: the cut vote may refuse them (refuse_outvoted_cuts)
        group = group_of(names, [e for e in edges if not weak_floor(e, o.floor_lone_inliers)], given)
        rooms: dict = {}
        for a, b in pairs:
            if group[names[a]] == group[names[b]]:
                continue
            for n in (names[a], names[b]):
                if n not in rooms:
                    rooms[n] = room(*small[n])
            if rooms[names[a]] is not None and rooms[names[b]] is not None:
                layouts[a, b] = layout_pair(rooms[names[a]], rooms[names[b]])
        for (a, b), lp in layouts.items():
            if lp is None:
                continue
            layout_refused[a, b] = (off_frames((a, b), lp.a_from_b) or _layout_refusal(lp, bearing[a, b], o)
                                    or _placement_refusal(lp.a_from_b, small[names[a]][1], small[names[b]][1], o))
            if not layout_refused[a, b]:
                edges.append(Edge(a=names[a], b=names[b], a_from_b=lp.a_from_b, kind=LAYOUT, inliers=int(lp.score),
                                  confirmed=_confirmed(bearing[a, b], o),
                                  info={"layout_score": round(lp.score, 1), "layout_second": round(lp.second, 1)}))
    room_depths = {n: small[n][1] for n in small}
    overlaps = refuse_overlapping_rooms(names, edges, given, room_depths, o) if need else {}
    # a floor fit refused by its own images or rooms (impossible) proposes no placement in the cut vote
    outvoted = (refuse_outvoted_cuts(names, edges, given, floors, views, o.min_floor_inliers, o.floor_lone_inliers,
                                     o.floor_beyond_rooms, impossible)
                if need else {})
    if outvoted:
        overlaps |= outvoted | refuse_overlapping_rooms(names, edges, given, room_depths, o)
    poses, info = solve_graph(names, edges, given,
                              featureless={n for n, c in keypoints.items() if c < FEW_KEYPOINTS})
    poses = {n: T @ lift[n] if n in lift else T for n, T in poses.items()}
    for n in level:
        info[n]["levelled_tilt_deg"] = round(tilt_deg(level[n]), 3)
    for n, theta in frames.items():
        if theta is not None:
            info[n]["walls_deg"] = round(float(np.degrees(theta)), 3)
    for n, count in keypoints.items():
        info[n]["keypoints"] = count
    anchor = next(n for n in names if n in poses)
    cam_from_world = invert_pose(poses[anchor])
    out = {n: cam_from_world @ poses[n] for n in names if n in poses}
    used = {(e.a, e.b): e.kind for e in edges}
    rows = []
    for (a, b), p in sorted(pairs.items()):
        row = {"a": names[a], "b": names[b], "matches": p.matches, "inliers": p.inliers,
               "overlap": round(p.overlap, 4), "consistency": round(p.consistency, 4),
               "residual": None if not np.isfinite(p.residual) else round(p.residual, 5), "accepted": depth_ok[a, b],
               "edge": used.get((names[a], names[b]))}
        if refused.get((a, b)):
            row["depth_refused"] = refused[a, b]
        if (names[a], names[b]) in overlaps:
            kind, why = overlaps[names[a], names[b]]
            row[f"{kind}_refused"] = why
        if floors.get((a, b)) is not None:
            f = floors[a, b]
            row.update(floor_inliers=f.inliers, floor_matches=f.matches, floor_residual_m=round(f.residual_m, 4),
                       floor_second=f.second, floor_yaw_deg=round(float(np.degrees(yaw_of(f.a_from_b[:3, :3]))), 2),
                       floor_xz_m=[round(float(f.a_from_b[0, 3]), 3), round(float(f.a_from_b[2, 3]), 3)])
            if (a, b) in beyond:
                row["floor_beyond_rooms"] = beyond[a, b][0]
            if floor_refused.get((a, b)):
                row["floor_refused"] = floor_refused[a, b]
        if layouts.get((a, b)) is not None:
            lp = layouts[a, b]
            row.update(layout_score=round(lp.score, 1), layout_second=round(lp.second, 1),
                       layout_hypotheses=lp.hypotheses,
                       layout_yaw_deg=round(float(np.degrees(yaw_of(lp.a_from_b[:3, :3]))), 2),
                       layout_xz_m=[round(float(lp.a_from_b[0, 3]), 3), round(float(lp.a_from_b[2, 3]), 3)])
            if layout_refused.get((a, b)):
                row["layout_refused"] = layout_refused[a, b]
        if (a, b) in bearing:
            pose, scale, support = bearing[a, b]
            row["bearing_inliers"] = 0 if pose is None else int(pose.inliers.sum())
            if pose is not None:
                row.update(yaw_deg=round(float(np.degrees(pose.yaw)), 3),
                           scale_m=None if not np.isfinite(scale) else round(scale, 4), scale_support=support)
                if off := off_frames((a, b), pose.i_from_j()):
                    row["bearing_refused"] = off
        rows.append(row)
    for n in names:
        if not info[n]["registered"]:
            info[n]["reason"] += _evidence_across(set(info[n].get("group") or [n]), set(poses), rows, o)
            if keypoints.get(n, FEW_KEYPOINTS) < FEW_KEYPOINTS:
                info[n]["reason"] += (f"; {keypoints[n]} keypoints on the panorama: a blank, dark or blurred image has "
                                      "nothing to match")
    return Registration(world_from_cam=out, panoramas={n: info[n] for n in names}, pairs=rows)


def _evidence_across(group: set[str], registered: set[str], rows: list[dict], o: RegisterOptions) -> str:
    """What the pairs tried (registration.json's pair rows) between an unregistered panorama's group and the
    registered panoramas found, for its reason: the group, the pair of most floor inliers (then depth-backed inliers)
    and why it is no edge."""
    across = [r for r in rows if {r["a"], r["b"]} & group and {r["a"], r["b"]} & registered]
    parts = [f"group: {', '.join(sorted(group))}"] if len(group) > 1 else []
    if not across:
        parts.append("no pair with the registered panoramas was tried")
    else:
        best = max(across, key=lambda r: (r.get("floor_inliers", 0), r["inliers"], r["consistency"]))
        k = best.get("floor_inliers", 0)
        why = best.get("floor_refused") or (f"below {o.min_floor_inliers}" if k < o.min_floor_inliers else "")
        parts.append(f"{len(across)} pair(s) tried with the registered panoramas, the best {best['a']}-{best['b']}: "
                     f"{k} floor inliers{f' ({why})' if why else ''}, {best['inliers']} depth-backed inliers at "
                     f"{best['consistency']:.2f} consistency")
    return " (" + "; ".join(parts) + ")"


def _edges(names, pairs, bearing, floors, frames, small, views, o: RegisterOptions):
    """The pose graph's edges of the pairs tried so far (each pair's best trusted estimate: depth-backed, floor, then
    bearing-only), with why depth-backed and floor poses were refused, the Manhattan yaw test they used, per floor
    fit of min_floor_inliers (its inlier matches beyond both rooms' walls, its inlier matches) (beyond_both_rooms),
    and the floor fits refused by their own images or rooms (not as ambiguous alone)."""
    def off_frames(ab: tuple[int, int], a_from_b: np.ndarray) -> str:
        return _off_manhattan(a_from_b, manhattan_yaws(frames.get(names[ab[0]]), frames.get(names[ab[1]])), o)

    refused = {ab: off_frames(ab, p.i_from_j) or _contradiction(p.i_from_j, bearing[ab], o)
               for ab, p in pairs.items() if accepted(p, o)}
    depth_ok = {ab: accepted(p, o) and not refused[ab] for ab, p in pairs.items()}
    floor_refused: dict[tuple[int, int], str] = {}
    beyond: dict[tuple[int, int], tuple[int, int]] = {}
    impossible: set[tuple[int, int]] = set()  # refused by the pair's own images or rooms, not as ambiguous alone
    for ab, f in floors.items():
        if f is None or f.inliers < o.min_floor_inliers:
            continue
        da, db = small[names[ab[0]]][1], small[names[ab[1]]][1]
        sides = room_sides(f, views[names[ab[0]]], views[names[ab[1]]], da, db, threshold_m=o.floor_threshold_m)
        beyond[ab] = beyond_both_rooms(sides)
        contradiction = _contradiction(f.a_from_b, bearing[ab], o)
        ambiguous = "" if contradiction else _ambiguous_floor(f, bearing[ab], o)
        floor_refused[ab] = (contradiction or ambiguous or _placement_refusal(f.a_from_b, da, db, o)
                             or floor_rooms_refusal(sides))
        if floor_refused[ab] and not ambiguous:
            impossible.add(ab)
    edges = []
    for (a, b), p in pairs.items():
        f = floors.get((a, b))
        if depth_ok[a, b]:
            edges.append(Edge(a=names[a], b=names[b], a_from_b=p.i_from_j, kind=DEPTH, inliers=p.inliers,
                              confirmed=_confirmed(bearing[a, b], o),
                              info={"inliers": p.inliers, "overlap": round(p.overlap, 4),
                                    "consistency": round(p.consistency, 4), "residual": round(p.residual, 5)}))
        elif f is not None and (a, b) in floor_refused and not floor_refused[a, b]:
            edges.append(Edge(a=names[a], b=names[b], a_from_b=f.a_from_b, kind=FLOOR, inliers=f.inliers,
                              confirmed=_confirmed(bearing[a, b], o),
                              info={"inliers": f.inliers, "matches": f.matches, "residual": round(f.residual_m, 4),
                                    "beyond_rooms": beyond[a, b][0], "inlier_matches": beyond[a, b][1]}))
        elif (a, b) in bearing and bearing[a, b][0] is not None and not off_frames(
                (a, b), bearing[a, b][0].i_from_j()):
            pose, scale, support = bearing[a, b]
            metric = support >= o.min_scale_support
            edges.append(Edge(a=names[a], b=names[b], a_from_b=pose.i_from_j(scale if metric else 1.0),
                              kind=BEARING if metric else DIRECTION, inliers=int(pose.inliers.sum()),
                              info={"inliers": int(pose.inliers.sum()), "scale_support": support}))
    return edges, refused, depth_ok, floor_refused, off_frames, beyond, impossible


def refuse_overlapping_rooms(names: list[str], edges: list[Edge], given: dict[str, np.ndarray],
                             depths: dict[str, np.ndarray], o: RegisterOptions
                             ) -> dict[tuple[str, str], tuple[str, str]]:
    """Remove from `edges` the floor, layout and bearing-only poses (estimated without the dense depths) that the solved
    registration needs to put two panoramas' rooms inside each other: while some registered pair whose depths (H, W)
    hold their whole room overlaps (rooms_overlap_refusal) and the way between them in the pose graph runs through such
    edges, the weakest of those goes -> {(a, b): (edge kind, reason)}. A chance fit between two rooms is caught this
    way by any panorama of either room, not only by the pair it joined."""
    whole = {n for n, d in depths.items() if valid_share(d) >= WHOLE_ROOM}
    reach = {n: float(np.max(np.where(np.isfinite(d), d, 0.0))) for n, d in depths.items()}
    judged: dict[tuple[str, str, bytes], str] = {}
    out: dict[tuple[str, str], tuple[str, str]] = {}
    while True:
        poses, info = solve_graph(names, edges, given)
        found = None
        ranked = sorted(whole & set(poses), key=names.index)
        for i, x in enumerate(ranked):
            for y in ranked[i + 1:]:
                weak = [e for e in tree_path(x, y, info, edges) if e.kind in (FLOOR, LAYOUT, BEARING)]
                x_from_y = invert_pose(poses[x]) @ poses[y]
                if not weak or np.linalg.norm(x_from_y[:3, 3]) > reach[x] + reach[y]:
                    continue
                key = (x, y, np.round(x_from_y, 6).tobytes())
                if key not in judged:
                    judged[key] = rooms_overlap_refusal(x_from_y, depths[x], depths[y],
                                                        max_share=o.max_free_space_violation)
                if judged[key]:
                    found = (x, y, judged[key], weak)
                    break
            if found:
                break
        if found is None:
            return out
        x, y, why, weak = found
        e = min(weak, key=strength)
        edges[:] = [f for f in edges if f is not e]
        out[e.a, e.b] = (e.kind, f"with it the registration puts {y}'s room into {x}'s: {why}")


def _placement_refusal(a_from_b: np.ndarray, depth_a: np.ndarray, depth_b: np.ndarray, o: RegisterOptions) -> str:
    """Why the depths refuse a pose estimated without them (a floor or layout pose; '' when they do not): one room whose
    depths disagree (same_room_refusal), or two rooms that overlap (rooms_overlap_refusal)."""
    return (same_room_refusal(a_from_b, depth_a, depth_b, min_consistency=o.min_consistency)
            or rooms_overlap_refusal(a_from_b, depth_a, depth_b, max_share=o.max_free_space_violation))


def _ambiguous_floor(f: FloorPose, bearing: tuple[UprightPose | None, float, int], o: RegisterOptions) -> str:
    """Why a floor pose the images do not confirm is ambiguous ('' when it is not): another translation at its yaw
    keeps nearly as many inliers (floor_min_margin), and enough to be a floor fit itself (min_floor_inliers: fewer
    is the chance agreement any two floors leave somewhere, no rival)."""
    if _confirmed(bearing, o) or f.second < o.min_floor_inliers or f.inliers >= o.floor_min_margin * f.second:
        return ""
    return (f"{f.inliers} floor inliers, another translation {f.second}: a repeated floor pattern, and no bearing-only "
            "estimate to tell them apart")


def _confirmed(bearing: tuple[UprightPose | None, float, int], o: RegisterOptions) -> bool:
    """Whether a pair's bearing-only estimate is well supported (>= min_bearing_inliers): then it can contradict, or
    confirm, the pair's depth-backed, floor or layout pose (_contradiction)."""
    pose = bearing[0]
    return pose is not None and int(pose.inliers.sum()) >= o.min_bearing_inliers


def _contradiction(i_from_j: np.ndarray, bearing: tuple[UprightPose | None, float, int], o: RegisterOptions) -> str:
    """Why the images contradict a depth-backed or floor pose i_from_j (4, 4) ('' when they do not): the bearing-only
    estimate of the pair's ERP matches, when well supported, differs in yaw, baseline direction or (where it is
    metric) baseline length beyond the tolerances, or the baseline is longer than its matched points allow above
    the floor (UprightPose.max_baseline_m)."""
    pose, scale, support = bearing
    if not _confirmed(bearing, o):
        return ""
    dyaw = abs(float(np.degrees(wrap_angle(yaw_of(i_from_j[:3, :3]) - pose.yaw))))
    if dyaw > o.depth_yaw_tol_deg:
        return f"bearing-only yaw differs by {dyaw:.1f} deg ({int(pose.inliers.sum())} inliers)"
    t = i_from_j[:3, 3]
    if np.linalg.norm(t) > 2 * o.max_error_m:
        ang = float(np.degrees(np.arccos(np.clip(t @ pose.t / np.linalg.norm(t), -1.0, 1.0))))
        if ang > o.depth_direction_tol_deg:
            return f"bearing-only baseline direction differs by {ang:.1f} deg ({int(pose.inliers.sum())} inliers)"
    if support >= o.min_scale_support and abs(np.linalg.norm(t) / scale - 1) > o.depth_scale_tol:
        return (f"baseline {np.linalg.norm(t):.2f} m, bearing-only {scale:.2f} m from {support} points whose depths "
                "agree")
    if np.linalg.norm(t) > pose.max_baseline_m:
        return (f"baseline {np.linalg.norm(t):.2f} m puts points both views see under the floor (at most "
                f"{pose.max_baseline_m:.2f} m)")
    return ""


def manhattan_yaws(theta_a: float | None, theta_b: float | None) -> np.ndarray | None:
    """The 4 yaws (radians) of a_from_b that the wall directions theta_a, theta_b (manhattan_frame, modulo 90
    degrees) of two panoramas in one Manhattan home allow; None when either has none."""
    if theta_a is None or theta_b is None:
        return None
    return wrap_angle(theta_b - theta_a + np.arange(4) * np.pi / 2)


def _off_manhattan(a_from_b: np.ndarray, yaws: np.ndarray | None, o: RegisterOptions) -> str:
    """Why a pose a_from_b (4, 4) contradicts the yaws its panoramas' wall directions allow ('' when it does not, or
    without them)."""
    if yaws is None:
        return ""
    off = float(np.degrees(np.abs(wrap_angle(yaw_of(a_from_b[:3, :3]) - yaws)).min()))
    return f"yaw {off:.1f} deg off the rooms' wall directions" if off > o.manhattan_tol_deg else ""


def _layout_refusal(lp: LayoutPose, bearing: tuple[UprightPose | None, float, int], o: RegisterOptions) -> str:
    """Why a layout pose is not trusted ('' when it is): too little agreeing image area, no clear margin over the best
    distinct hypothesis, or the bearing-only estimate contradicts it."""
    if lp.score < o.layout_min_score:
        return f"agreeing area {lp.score:.0f} below {o.layout_min_score:.0f}"
    if lp.score < o.layout_min_margin * lp.second:
        return f"agreeing area {lp.score:.0f} not clearly above the next hypothesis' {lp.second:.0f}"
    return _contradiction(lp.a_from_b, bearing, o)


def accepted(p: PairResult, o: RegisterOptions) -> bool:
    """Whether a depth-backed pair estimate is trusted."""
    return (p.i_from_j is not None and p.inliers >= o.min_inliers and p.consistency >= o.min_consistency
            and p.overlap >= o.min_overlap)
