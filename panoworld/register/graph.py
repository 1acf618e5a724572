"""The pose graph of a home: metric pair estimates join panoramas into rigid groups (maximum spanning trees, adjusted to
the edges that close loops; a tree edge a direction-only pair inside its group contradicts kept as a direction), then
direction-only pairs (bearings without a scale) place whole groups."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from panoworld.core.conventions import invert_pose
from panoworld.geometry.upright import wrap_angle, yaw_matrix, yaw_of

DEPTH, FLOOR, BEARING, LAYOUT, DIRECTION = "depth", "floor", "bearing", "layout", "direction"
"""Edge kinds: rigid fit of depth-backed points (ICP-refined, free-space consistent); 2D rigid fit of the floor images;
upright two-view geometry with its scale from the depths that agree; adjoining rooms' walls placed against each other
where the images agree; upright two-view geometry without a scale (the baseline's direction only)."""
_RANK = {DEPTH: 4, FLOOR: 3, BEARING: 2, LAYOUT: 1, DIRECTION: 0}


@dataclass(kw_only=True)
class Edge:
    """One trusted pair estimate."""

    a: str
    b: str
    a_from_b: np.ndarray
    """(4, 4); for a direction edge the translation is the unit direction from a to b in a's frame."""
    kind: str
    """DEPTH, FLOOR, BEARING, LAYOUT or DIRECTION."""
    inliers: int
    info: dict
    """Quality figures reported for the panorama this edge places."""
    confirmed: bool = True
    """The pair's images confirm it: its bearing-only estimate (>= min_bearing_inliers of the ERP matches) agrees.
    A depth-backed, floor or layout pose without one (too few matches agree on any two-view geometry) rests on the
    depths or the floor images alone; a bearing or direction edge is an image estimate itself."""

    def toward(self, src: str) -> tuple[str, np.ndarray]:
        """(the other panorama, src_from_other)."""
        if src == self.a:
            return self.b, self.a_from_b
        T = invert_pose(self.a_from_b)
        if self.kind == DIRECTION:
            T[:3, 3] /= max(np.linalg.norm(T[:3, 3]), 1e-12)
        return self.a, T


LOOP_SIGMA = {DEPTH: (0.0005, 0.01), FLOOR: (0.03, 0.3), BEARING: (0.05, 0.5), LAYOUT: (0.10, 1.0)}
"""Each metric edge kind's translation (m) and yaw (deg) uncertainty: how much it holds a group's poses where edges
close loops (_refine). Depth edges (dense points, ICP-refined) hold almost rigidly: the other kinds adjust around
them."""
LOOP_GATE = 5.0
"""A loop-closing edge farther than this many LOOP_SIGMA from its group's spanning-tree poses contradicts the edges
that outranked it there: it is left out of the adjustment."""


@dataclass(kw_only=True)
class GraphOptions:
    """When direction-only pairs may place a group."""

    yaw_tol_deg: float = 3.0
    """Direction pairs placing one group must agree on its yaw within this."""
    direction_tol_deg: float = 5.0
    """Each placing pair's baseline direction must point at the placed panorama within this."""
    min_angle_deg: float = 15.0
    """The placing directions must span at least this angle (rays nearly parallel do not fix a position)."""


def _groups(names: list[str], edges: list[Edge], given: dict[str, np.ndarray]
            ) -> list[tuple[dict[str, np.ndarray], dict[str, dict]]]:
    """Rigid groups joined by metric edges (Prim: edges the images confirm first, then depth, floor, bearing, then layout
    edges, then most inliers), the given poses forming the first group -> [(poses in the group frame, per-panorama
    info)]."""
    metric = [e for e in edges if e.kind != DIRECTION]
    left = [n for n in names if n not in given]
    out = []
    seeds: list[dict[str, np.ndarray]] = [dict(given)] if given else []
    while left or seeds:
        poses = seeds.pop(0) if seeds else {left[0]: np.eye(4)}
        info = {n: {"registered": True, "source": "given" if n in given else "estimated", "parent": None}
                for n in poses}
        left = [n for n in left if n not in poses]
        while True:
            best = None
            for e in metric:
                for src in (e.a, e.b):
                    dst, rel = e.toward(src)
                    if src in poses and dst not in poses and (best is None or strength(e) > strength(best[0])):
                        best = (e, src, dst, rel)
            if best is None:
                break
            e, src, dst, rel = best
            poses[dst] = poses[src] @ rel
            info[dst] = {"registered": True, "source": "estimated", "parent": src, "edge": e.kind, **e.info}
            left.remove(dst)
        out.append((poses, info))
    return out


def strength(e: Edge) -> tuple[bool, int, int]:
    """How much an edge is trusted, for the spanning tree and for choosing the weakest edge of a path: confirmed by the
    images, then kind, then inliers. A few matches whose depths agree by chance (layout depth: walls alone) or a floor
    fit a tile run along its baseline are what the images leave unconfirmed; where a confirmed path reaches the same
    panorama, such an edge only closes a loop, and the loop gate drops it when it disagrees."""
    return e.confirmed, _RANK[e.kind], e.inliers


def _refine(poses: dict[str, np.ndarray], edges: list[Edge], fixed: set[str]) -> dict[str, np.ndarray]:
    """A rigid group's upright poses (world_from_cam (4, 4) in the group frame) adjusted to all its metric edges at
    once: its spanning tree used one edge per panorama, the others close loops. Least squares (scipy, soft-L1 loss) on
    each edge's translation (in its first panorama's frame) and yaw, in LOOP_SIGMA units, over the edges within
    LOOP_GATE of the tree's poses; fixed poses (else the group's first) held. Unchanged when no edge closes a loop."""
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    names = list(poses)
    at = {n: i for i, n in enumerate(names)}
    inner = [e for e in edges if e.kind in LOOP_SIGMA and e.a in poses and e.b in poses]
    ia, ib = np.array([at[e.a] for e in inner], int), np.array([at[e.b] for e in inner], int)
    t_m = np.array([e.a_from_b[:3, 3] for e in inner]).reshape(-1, 3)
    yaw_m = np.array([yaw_of(e.a_from_b[:3, :3]) for e in inner])
    sig_t = np.array([LOOP_SIGMA[e.kind][0] for e in inner])[:, None]
    sig_y = np.radians([LOOP_SIGMA[e.kind][1] for e in inner])
    t0 = np.array([poses[n][:3, 3] for n in names])
    yaw0 = np.array([yaw_of(poses[n][:3, :3]) for n in names])
    dt, dy = _misfit(t0, yaw0, ia, ib, t_m, yaw_m)
    keep = np.maximum(np.linalg.norm(dt / sig_t, axis=1), np.abs(dy) / sig_y) <= LOOP_GATE
    ia, ib, t_m, yaw_m, sig_t, sig_y = ia[keep], ib[keep], t_m[keep], yaw_m[keep], sig_t[keep], sig_y[keep]
    held = [n for n in names if n in fixed] or names[:1]
    free = [n for n in names if n not in held]
    if len(ia) < len(names) or not free:
        return poses
    col = {n: i for i, n in enumerate(free)}
    idx = np.array([col.get(n, -1) for n in names])

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t, yaw = t0.copy(), yaw0.copy()
        f = idx >= 0
        v = x.reshape(-1, 4)
        t[f], yaw[f] = v[idx[f], :3], v[idx[f], 3]
        return t, yaw

    def residuals(x: np.ndarray) -> np.ndarray:
        d_t, d_y = _misfit(*unpack(x), ia, ib, t_m, yaw_m)
        return np.concatenate([(d_t / sig_t).ravel(), d_y / sig_y])

    sparsity = lil_matrix((4 * len(ia), 4 * len(free)), dtype=int)
    for k, (a, b) in enumerate(zip(ia, ib)):
        for j in (idx[a], idx[b]):
            if j >= 0:
                sparsity[3 * k:3 * k + 3, 4 * j:4 * j + 4] = 1
                sparsity[3 * len(ia) + k, 4 * j:4 * j + 4] = 1
    x0 = np.concatenate([[*t0[at[n]], yaw0[at[n]]] for n in free])
    t, yaw = unpack(least_squares(residuals, x0, loss="soft_l1", jac_sparsity=sparsity, x_scale="jac").x)
    out = {}
    for n in names:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = yaw_matrix(yaw[at[n]]), t[at[n]]
        out[n] = poses[n] if n in held else T
    return out


def _misfit(t: np.ndarray, yaw: np.ndarray, ia: np.ndarray, ib: np.ndarray, t_m: np.ndarray, yaw_m: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """How far upright poses (positions t (N, 3), yaws (N,)) put each edge's second panorama ib (E,) from where the
    edge does, seen from its first ia (E,): (translation (E, 3) in ia's frame, yaw (E,) radians) less the edges'
    t_m (E, 3), yaw_m (E,)."""
    d, c, s = t[ib] - t[ia], np.cos(yaw[ia]), np.sin(yaw[ia])
    rel = np.stack([c * d[:, 0] - s * d[:, 2], d[:, 1], s * d[:, 0] + c * d[:, 2]], 1)  # R_a^T (t_b - t_a)
    return rel - t_m, wrap_angle(yaw[ib] - yaw[ia] - yaw_m)


def group_of(names: list[str], edges: list[Edge], given: dict[str, np.ndarray] | None = None) -> dict[str, int]:
    """{NAME: index of its rigid group} (the groups of metric edges solve_graph starts from; the given poses one group)."""
    return {n: k for k, (poses, _) in enumerate(_groups(names, edges, given or {})) for n in poses}


def bridging_groups(names: list[str], edges: list[Edge], given: dict[str, np.ndarray] | None = None
                    ) -> dict[str, int]:
    """{NAME: group index} for choosing the pairs to try across groups (pair_select.bridge_pairs): the groups of the
    metric edges less the floor edges the images do not confirm. Such an edge stays in the graph, but the cut vote and
    the lone-fit rule (cuts.refuse_outvoted_cuts) weigh it by the other pairs tried across it, so those are tried."""
    return group_of(names, [e for e in edges if e.confirmed or e.kind != FLOOR], given)


def _place(group: dict[str, np.ndarray], placed: dict[str, np.ndarray], edges: list[Edge], o: GraphOptions
           ) -> tuple[np.ndarray | None, list[Edge], str]:
    """world_from_group (4, 4) fixing the group's yaw and position from the direction edges to placed panoramas, the
    edges used, and why not when it cannot be placed."""
    obs = []  # (placed panorama, group panorama, placed_from_group-panorama rotation yaw, unit direction, edge)
    for e in edges:
        if e.kind != DIRECTION:
            continue
        for src in (e.a, e.b):
            dst, rel = e.toward(src)
            if src in placed and dst in group:
                obs.append((src, dst, rel, e))
    if not obs:
        return None, [], "no pair with the registered panoramas"
    # The group's yaw from each edge: world yaw of dst = yaw(placed src) + edge yaw; group yaw = that - yaw in group.
    psi = np.array([yaw_of(placed[s][:3, :3] @ rel[:3, :3]) - yaw_of(group[d][:3, :3]) for s, d, rel, _ in obs])
    w = np.array([e.inliers for *_, e in obs], float)
    ref = psi[np.argmax(w)]
    ok = np.abs(wrap_angle(psi - ref)) < np.radians(o.yaw_tol_deg)
    psi0 = ref + np.average(wrap_angle(psi[ok] - ref), weights=w[ok])
    obs = [ob for ob, k in zip(obs, ok) if k]
    R = yaw_matrix(psi0)
    M, b, dirs = np.zeros((3, 3)), np.zeros(3), []
    for s, d, rel, _e in obs:
        u = placed[s][:3, :3] @ rel[:3, 3]
        u /= np.linalg.norm(u)
        P = np.eye(3) - np.outer(u, u)
        M += P
        b += P @ (placed[s][:3, 3] - R @ group[d][:3, 3])
        dirs.append(u)
    if np.linalg.eigvalsh(M)[0] < 1 - np.cos(np.radians(o.min_angle_deg)):
        return None, [], (f"{len(obs)} direction-only pair(s) with the registered panoramas, their baselines too close "
                          "to parallel to fix a position (no metric scale: the depths of the matched points disagree)")
    off = np.linalg.solve(M, b)
    for (s, d, _rel, _e), u in zip(obs, dirs):
        v = R @ group[d][:3, 3] + off - placed[s][:3, 3]
        if _angle_deg(v, u) > o.direction_tol_deg:
            return None, [], f"the direction-only pairs with the registered panoramas disagree ({s}-{d})"
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, off
    return T, [e for *_, e in obs], ""


def _without_contradicted(names: list[str], edges: list[Edge], given: dict[str, np.ndarray], o: GraphOptions
                          ) -> list[Edge]:
    """edges with each spanning-tree edge that a direction edge inside its group contradicts (the baseline direction it
    measured more than direction_tol_deg from where the group puts the two panoramas) turned into a direction edge
    (its own baseline direction, no length): of the tree path between that pair's panoramas, the weakest edge that is
    not a depth edge. A floor fit on a repeated pattern can be off along its baseline by a whole tile run (metres)
    while its direction holds; as a direction edge it still helps place its side (_place), checked against the others."""
    settled: set[int] = set()  # contradicting directions with only depth edges (or given poses) between their ends
    for _ in range(len(edges)):
        bad = None
        for poses, info in _groups(names, edges, given):
            for e in edges:
                if (e.kind == DIRECTION and id(e) not in settled and e.a in poses and e.b in poses
                        and _off_direction(poses, e) > o.direction_tol_deg):
                    weak = [t for t in tree_path(e.a, e.b, info, edges) if t.kind not in (DEPTH, DIRECTION)]
                    if weak:
                        bad = weak
                        break
                    settled.add(id(e))
            if bad:
                break
        if bad is None:
            return edges
        w = min(bad, key=strength)
        T = np.array(w.a_from_b, np.float64)
        T[:3, 3] /= max(np.linalg.norm(T[:3, 3]), 1e-12)
        edges = [x for x in edges if x is not w] + [Edge(a=w.a, b=w.b, a_from_b=T, kind=DIRECTION, inliers=w.inliers,
                                                        info=w.info, confirmed=w.confirmed)]
    return edges


def _off_direction(poses: dict[str, np.ndarray], e: Edge) -> float:
    """Degrees between a direction edge's baseline direction and the one poses give its two panoramas."""
    v = poses[e.a][:3, :3].T @ (poses[e.b][:3, 3] - poses[e.a][:3, 3])
    return 0.0 if np.linalg.norm(v) < 1e-9 else _angle_deg(v, e.a_from_b[:3, 3])


def _angle_deg(v: np.ndarray, u: np.ndarray) -> float:
    """Degrees between a vector v (3,) and a unit direction u (3,)."""
    return float(np.degrees(np.arccos(np.clip(v @ u / max(np.linalg.norm(v), 1e-12), -1.0, 1.0))))


def ancestry(n: str, info: dict[str, dict]) -> list[str]:
    """n and its spanning-tree ancestors up to its group's root (info: each panorama's parent, as _groups gives it)."""
    chain = [n]
    while info[chain[-1]].get("parent") is not None:
        chain.append(info[chain[-1]]["parent"])
    return chain


def tree_path(x: str, y: str, info: dict[str, dict], edges: list[Edge]) -> list[Edge]:
    """The metric edges of a group's spanning tree (info: each panorama's parent and edge kind, as _groups gives it) on
    the way from x to y (each panorama's edge to its parent)."""
    cx, cy = ancestry(x, info), ancestry(y, info)
    common = set(cx) & set(cy)
    steps = [n for n in cx if n not in common] + [n for n in cy if n not in common]
    out = []
    for n in steps:
        p, kind = info[n]["parent"], info[n].get("edge")
        out += [e for e in edges if e.kind == kind and {e.a, e.b} == {n, p}][:1]
    return out


def solve_graph(names: list[str], edges: list[Edge], given: dict[str, np.ndarray] | None = None,
                options: GraphOptions | None = None, featureless: set[str] | frozenset = frozenset()
                ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
    """world_from_cam of the panoramas that one connected, determined set holds (the group of the given poses, else
    the largest; of equal ones, one not made of featureless panoramas alone, then the first by name), in that group's
    frame, and per-panorama info (reason for those left out)."""
    o = options or GraphOptions()
    given = dict(given or {})
    edges = _without_contradicted(names, list(edges), given, o)
    groups = [(_refine(g, edges, set(given)), ginfo) for g, ginfo in _groups(names, edges, given)]
    order = sorted(range(len(groups)), key=lambda k: (not (given and k == 0), -len(groups[k][0]),
                                                      set(groups[k][0]) <= featureless,
                                                      min(names.index(n) for n in groups[k][0])))
    poses, info = dict(groups[order[0]][0]), dict(groups[order[0]][1])
    waiting = [groups[k] for k in order[1:]]
    reasons: dict[str, str] = {}
    while waiting:
        best = None
        for k, (g, _) in enumerate(waiting):
            T, used, why = _place(g, poses, edges, o)
            reasons[min(g)] = why
            if T is not None and (best is None or sum(e.inliers for e in used) > best[2]):
                best = (k, T, sum(e.inliers for e in used), used)
        if best is None:
            break
        k, T, _, used = best
        g, ginfo = waiting.pop(k)
        parents = sorted({n for e in used for n in (e.a, e.b) if n in poses})
        for n, P in g.items():
            poses[n] = T @ P
            info[n] = {**ginfo[n], "joined_by": "direction", "joined_to": parents,
                       "direction_inliers": [e.inliers for e in used]}
    for g, _ in waiting:
        for n in g:
            info[n] = {"registered": False, "source": None, "parent": None,
                       "reason": reasons.get(min(g)) or "not joined to the registered panoramas", "group": sorted(g)}
    return poses, info
