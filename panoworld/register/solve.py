"""All panoramas of a home into one frame: pairwise estimates over the candidate pairs (pair_select), a
maximum-inlier spanning tree from the posed (or first) panoramas, and per-panorama quality figures; unconnected
panoramas are reported, not placed."""

from __future__ import annotations

import numpy as np

from panoworld.core.conventions import invert_pose
from panoworld.geometry.resize import rgbd_at_height
from panoworld.register.options import RegisterOptions
from panoworld.register.pair_select import ALL_PAIRS_UP_TO, appearance_descriptor, candidate_pairs
from panoworld.register.pairwise import Features, PairResult, erp_features, register_pair
from panoworld.register.registration import Registration


def register_panoramas(names: list[str], rgbs: dict[str, np.ndarray], depths: dict[str, np.ndarray], *,
                       given: dict[str, np.ndarray] | None = None, options: RegisterOptions | None = None,
                       progress=None) -> Registration:
    """Register panoramas (RGB uint8 and metric ray depth (H, W) each); given poses are kept as they are (and anchor
    the others), otherwise the first panorama is the frame. A pair counts when RANSAC keeps >= min_inliers, the
    refined pose has >= min_consistency free-space consistency and >= min_overlap overlap."""
    o = options or RegisterOptions()
    given = dict(given or {})
    need = [n for n in names if n not in given]
    feats: dict[str, Features] = {}
    pairs: dict[tuple[int, int], PairResult] = {}
    k = len(names)
    if need:
        small = {n: rgbd_at_height(rgbs[n], depths[n], o.height) for n in names}
        feats = {n: erp_features(*small[n], max_features=o.max_features) for n in names}
        looks = {n: appearance_descriptor(small[n][0]) for n in names} if k > ALL_PAIRS_UP_TO else None
        for a, b in candidate_pairs(names, looks, given=given):
            pairs[a, b] = register_pair(feats[names[a]], feats[names[b]], small[names[a]][1], small[names[b]][1],
                                        max_error_m=o.max_error_m, min_inliers=o.min_inliers,
                                        refine_height=o.refine_height, refine_iterations=o.refine_iterations)
            if progress:
                progress(names[a], names[b], pairs[a, b])

    def accepted(p: PairResult) -> bool:
        return (p.i_from_j is not None and p.inliers >= o.min_inliers and p.consistency >= o.min_consistency
                and p.overlap >= o.min_overlap)

    poses: dict[str, np.ndarray] = {n: np.asarray(T, np.float64) for n, T in given.items()}
    info: dict[str, dict] = {n: {"registered": True, "source": "given", "parent": None} for n in given}
    if not poses:
        poses[names[0]] = np.eye(4)
        info[names[0]] = {"registered": True, "source": "estimated", "parent": None}
    # Prim's algorithm on the accepted pairs: always attach the unplaced panorama with the most inliers to a placed one.
    while True:
        best = None
        for (a, b), p in pairs.items():
            if not accepted(p):
                continue
            # i_from_j maps b into a: placing b from a uses it, placing a from b uses its inverse.
            for src, dst, rel in ((a, b, p.i_from_j), (b, a, None)):
                if names[src] in poses and names[dst] not in poses and (best is None or p.inliers > best[0].inliers):
                    best = (p, names[src], names[dst], invert_pose(p.i_from_j) if rel is None else rel)
        if best is None:
            break
        p, src, dst, rel = best
        poses[dst] = poses[src] @ rel
        info[dst] = {"registered": True, "source": "estimated", "parent": src, "inliers": p.inliers,
                     "overlap": round(p.overlap, 4), "consistency": round(p.consistency, 4),
                     "residual": round(p.residual, 5)}
    for n in names:
        if n not in info:
            tried = [p for (a, b), p in pairs.items() if n in (names[a], names[b])]
            best = max(tried, key=lambda p: (p.inliers, p.consistency), default=None)
            info[n] = {"registered": False, "source": None, "parent": None,
                       "inliers": 0 if best is None else best.inliers,
                       "consistency": 0.0 if best is None else round(best.consistency, 4),
                       "reason": "no pair with a registered panorama passed the inlier, overlap and consistency "
                                 f"checks (best: {0 if best is None else best.inliers} inliers, "
                                 f"{0.0 if best is None else best.consistency:.2f} consistency)"}
    anchor = next(n for n in names if n in poses)
    cam_from_world = invert_pose(poses[anchor])
    out = {n: cam_from_world @ poses[n] for n in names if n in poses}
    rows = [{"a": names[a], "b": names[b], "matches": p.matches, "inliers": p.inliers, "overlap": round(p.overlap, 4),
             "consistency": round(p.consistency, 4),
             "residual": None if not np.isfinite(p.residual) else round(p.residual, 5), "accepted": accepted(p)}
            for (a, b), p in sorted(pairs.items())]
    return Registration(world_from_cam=out, panoramas={n: info[n] for n in names}, pairs=rows)
