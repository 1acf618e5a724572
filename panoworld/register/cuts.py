"""Pose-graph cuts judged by the floor images of every pair across them (refuse_outvoted_cuts)."""

from __future__ import annotations

import numpy as np

from panoworld.core.conventions import invert_pose
from panoworld.geometry.floor_view import FloorView
from panoworld.geometry.upright import wrap_angle, yaw_of
from panoworld.io.home import first_few
from panoworld.register.floor import FloorPose, floor_support
from panoworld.register.graph import DIRECTION, FLOOR, LAYOUT, Edge, ancestry, solve_graph, tree_path
from panoworld.register.options import BEYOND_SHARE

AGREE_M, AGREE_DEG = 0.25, 2.0
"""Two placements of one side are the same when they put its cameras' mean position within AGREE_M of each other and
its yaw within AGREE_DEG."""
MIN_SUPPORT = 4
"""A pair's floor images support a placement when at least this many of their matches agree with the relative pose it
gives (floor_support's tests, counted once per keypoint spot); between floors that share nothing, a given pose keeps
0-2."""
SAME_SPOT_M = 0.25
"""Panoramas on one side of a cut whose capture points lie within this of each other on the floor are one capture spot
(a retake, an exposure bracket): they see the same floor from the same place, so a chance fit of one repeats with the
other, and their pairs across the cut count once in the vote."""


def refuse_outvoted_cuts(names: list[str], edges: list[Edge], given: dict[str, np.ndarray],
                         floors: dict[tuple[int, int], FloorPose | None], views: dict[str, FloorView | None],
                         min_floor_inliers: int, lone_inliers: int = 0, beyond_rooms: int = 0,
                         refused_fits: set[tuple[int, int]] | frozenset = frozenset()
                         ) -> dict[tuple[str, str], tuple[str, str]]:
    """Remove from `edges` each floor or layout edge the images do not confirm that the solved registration joins two
    sides by, where the floor images of the pairs across that cut (floors: each tried pair's fit, keyed by name indices)
    outvote it: another placement of the side, given by a metric edge or a floor fit of >= min_floor_inliers across
    the cut (not one of refused_fits: fits their own pair's images or rooms refuse, keyed as floors are), is
    supported (MIN_SUPPORT) by at least two pairs and by more pairs than the tree's placement (pairs counted once per
    two capture spots, SAME_SPOT_M) -> {(a, b): (edge kind, reason)}. Two rooms with one flooring can give a single
    floor fit of many inliers metres off, which the pair alone cannot tell from the truth; independent pairs agreeing
    on one placement are not chance. A floor edge of fewer than lone_inliers inliers is also refused where its own pair
    is the only one across its cut whose floor images support it, or the only pair across it (a chance fit between
    floors that share nothing reaches that many), unless at least beyond_rooms (> 0) of its inlier matches, and
    BEYOND_SHARE of them, lie beyond both rooms' walls (the edge's info["beyond_rooms"] of info["inlier_matches"]: floor
    both see through openings, a space between their rooms)."""
    at = {n: i for i, n in enumerate(names)}
    out: dict[tuple[str, str], tuple[str, str]] = {}
    for _ in range(len(edges)):
        poses, info = solve_graph(names, edges, given)
        found = None
        for n in sorted(poses, key=at.get):
            parent = info[n].get("parent")
            path = tree_path(n, parent, info, edges) if parent is not None else []
            if not path or path[0].confirmed or path[0].kind not in (FLOOR, LAYOUT):
                continue
            side = {m for m in poses if n in ancestry(m, info)}
            centre = np.mean([poses[m][:3, 3] for m in side], axis=0)
            alts = [X for X in _placements(names, poses, side, edges, floors, min_floor_inliers, refused_fits)
                    if not _same(X, np.eye(4), centre)]
            weak = weak_floor(path[0], lone_inliers) and not _between_rooms(path[0], beyond_rooms)
            if not alts and not weak:
                continue
            across = [(names[i], names[j], f.matched) for (i, j), f in floors.items()
                      if f is not None and f.matched is not None and names[i] in poses and names[j] in poses
                      and (names[i] in side) != (names[j] in side)
                      and views.get(names[i]) is not None and views.get(names[j]) is not None]
            spot = _spots(poses, side)
            here = _supporters(np.eye(4), across, poses, side, views)
            if weak and _count(here, spot) < 2:
                others = (f"no other of the {len(across)} pairs across it has floor images that agree with it"
                          if len(across) > 1 else "no other pair across it to agree with it")
                if len(here) > 1:  # a retake or an exposure bracket repeats the fit from the same place
                    others = (f"of the {len(across)} pairs across it only those from its own capture spots "
                              f"({_names(here)}) have floor images that agree with it")
                found = (path[0], f"{path[0].inliers} floor inliers, and {others}: a chance fit between floors that "
                                  "share nothing cannot be told from it")
                break
            if not alts:
                continue
            best = max(((_supporters(X, across, poses, side, views), k) for k, X in enumerate(alts)),
                       key=lambda sk: _count(sk[0], spot))
            if _count(best[0], spot) >= 2 and _count(best[0], spot) > _count(here, spot):
                X, there = alts[best[1]], best[0]
                moved = float(np.linalg.norm(X[:3, :3] @ centre + X[:3, 3] - centre))
                found = (path[0], f"the floor images of {len(there)} pairs across it ({_names(there)}) place "
                                  f"{_names(sorted(side))} {moved:.2f} m from where it does, {len(here)} agree with it")
                break
        if found is None:
            return out
        e, why = found
        edges[:] = [f for f in edges if f is not e]
        out[e.a, e.b] = (e.kind, why)
    return out


def weak_floor(e: Edge, lone_inliers: int) -> bool:
    """Whether an edge is a floor edge the images do not confirm with fewer than lone_inliers inliers: one that
    refuse_outvoted_cuts keeps only where another pair across its cut agrees."""
    return e.kind == FLOOR and not e.confirmed and e.inliers < lone_inliers


def _placements(names: list[str], poses: dict[str, np.ndarray], side: set[str], edges: list[Edge],
                floors: dict[tuple[int, int], FloorPose | None], min_floor_inliers: int,
                refused_fits: set[tuple[int, int]] | frozenset = frozenset()) -> list[np.ndarray]:
    """Where each metric edge and each floor fit (of >= min_floor_inliers, not in refused_fits) across the cut would put
    the side: the transform (4, 4) that moves the side's poses there."""
    out = []
    rels = [(e.a, e.b, e.a_from_b) for e in edges if e.kind != DIRECTION]
    rels += [(names[i], names[j], f.a_from_b) for (i, j), f in floors.items()
             if f is not None and f.inliers >= min_floor_inliers and (i, j) not in refused_fits]
    for a, b, a_from_b in rels:
        if a not in poses or b not in poses or (a in side) == (b in side):
            continue
        if a in side:
            out.append(poses[b] @ invert_pose(a_from_b) @ invert_pose(poses[a]))
        else:
            out.append(poses[a] @ a_from_b @ invert_pose(poses[b]))
    return out


def _between_rooms(e: Edge, beyond_rooms: int) -> bool:
    """Whether a floor edge's inliers lie beyond both rooms' walls (at least beyond_rooms > 0 of its inlier matches,
    and BEYOND_SHARE of them): floor both panoramas see only through openings, a hallway between their rooms."""
    beyond = e.info.get("beyond_rooms", 0)
    return beyond_rooms > 0 and beyond >= beyond_rooms and beyond >= BEYOND_SHARE * e.info.get("inlier_matches", 0)


def _supporters(X: np.ndarray, across: list[tuple[str, str, np.ndarray]], poses: dict[str, np.ndarray],
                side: set[str], views: dict[str, FloorView | None]) -> list[tuple[str, str]]:
    """The pairs (a, b, their floor matches (M, 2)) across the cut whose floor images support (MIN_SUPPORT) the side
    moved by X (4, 4)."""
    out = []
    for a, b, m in across:
        pa = X @ poses[a] if a in side else poses[a]
        pb = X @ poses[b] if b in side else poses[b]
        if floor_support(views[a], views[b], invert_pose(pa) @ pb, matches=m) >= MIN_SUPPORT:
            out.append((a, b))
    return out


def _spots(poses: dict[str, np.ndarray], side: set[str]) -> dict[str, str]:
    """Each registered panorama's capture spot: the first (by name) on its side of the cut whose capture point lies
    within SAME_SPOT_M of its own on the floor (x, z), else itself."""
    spot: dict[str, str] = {}
    for n in sorted(poses):
        spot[n] = next((m for m in spot if spot[m] == m and (m in side) == (n in side)
                        and np.linalg.norm(poses[m][[0, 2], 3] - poses[n][[0, 2], 3]) <= SAME_SPOT_M), n)
    return spot


def _count(pairs: list[tuple[str, str]], spot: dict[str, str]) -> int:
    """How many pairs of distinct capture spots (_spots) the pairs are."""
    return len({frozenset((spot[a], spot[b])) for a, b in pairs})


def _same(X: np.ndarray, Y: np.ndarray, centre: np.ndarray) -> bool:
    """Whether two placements X, Y (4, 4) of one side agree (AGREE_M at the point centre (3,), AGREE_DEG)."""
    dyaw = abs(float(np.degrees(wrap_angle(yaw_of(X[:3, :3]) - yaw_of(Y[:3, :3])))))
    return dyaw <= AGREE_DEG and float(np.linalg.norm((X - Y)[:3, :3] @ centre + (X - Y)[:3, 3])) <= AGREE_M


def _names(items: list, most: int = 6) -> str:
    """A short list of names or pairs (at most `most`, then how many more) for a message."""
    return first_few([x if isinstance(x, str) else "-".join(x) for x in items], most)
