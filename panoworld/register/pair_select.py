"""Which pairs of a home's panoramas registration tries: every pair of a small home, else a bounded set per panorama
(its neighbours in capture order and its nearest by a yaw-invariant appearance descriptor), so the work grows
linearly with the number of panoramas."""

from __future__ import annotations

import numpy as np

ALL_PAIRS_UP_TO = 32
"""Homes of at most this many panoramas (a real-estate tour) try every pair (496 pairs; RegisterOptions.all_pairs_up_to's
default): rooms that join only through a doorway look unlike each other and need not be near in capture order."""
PAIRS_PER_PANORAMA = 8
"""Beyond ALL_PAIRS_UP_TO: pairs tried per panorama, half with the next panoramas in name (capture) order, half with
the most similar ones by appearance_descriptor; at most PAIRS_PER_PANORAMA x panoramas pairs in all."""
BRIDGE_PAIRS_PER_PANORAMA = 8
"""Beyond ALL_PAIRS_UP_TO: pairs between panoramas the first pairs left in different groups, tried next (nearest in
name order first), at most this many times the panoramas."""


def appearance_descriptor(rgb: np.ndarray, rows: int = 32) -> np.ndarray:
    """A yaw-invariant global descriptor of an ERP panorama (H, W, 3): the mean colour of each of `rows` bands of
    latitude and their spread, unit norm (turning the camera about the vertical only rolls the ERP columns)."""
    h = rgb.shape[0]
    edges = np.linspace(0, h, rows + 1).astype(int)
    bands = [rgb[a:max(b, a + 1)].reshape(-1, rgb.shape[2]).astype(np.float32) for a, b in zip(edges[:-1], edges[1:])]
    v = np.concatenate([np.concatenate([b.mean(0), b.std(0)]) for b in bands])
    v = v - v.mean()
    return v / max(float(np.linalg.norm(v)), 1e-9)


def candidate_pairs(names: list[str], descriptors: dict[str, np.ndarray] | None = None, *, given=(),
                    all_up_to: int = ALL_PAIRS_UP_TO, per_panorama: int = PAIRS_PER_PANORAMA) -> list[tuple[int, int]]:
    """Index pairs (a < b) into names to register, sorted; pairs of two given (posed) panoramas are left out. Up to
    all_up_to panoramas: every pair. Beyond: each panorama with its next per_panorama // 2 in name order (the chain
    keeps the graph connected) and its per_panorama - per_panorama // 2 most similar by descriptor (when given)."""
    k = len(names)
    given = set(given)
    if k <= all_up_to:
        pairs = {(a, b) for a in range(k) for b in range(a + 1, k)}
    else:
        chain = max(1, per_panorama // 2)
        pairs = {(a, b) for a in range(k) for b in range(a + 1, min(k, a + 1 + chain))}
        if descriptors:
            d = np.stack([descriptors[n] for n in names])
            sim = d @ d.T
            np.fill_diagonal(sim, -np.inf)
            near = np.argsort(-sim, axis=1)[:, : per_panorama - chain]
            pairs |= {(min(a, int(b)), max(a, int(b))) for a in range(k) for b in near[a]}
    return sorted((a, b) for a, b in pairs if not (names[a] in given and names[b] in given))


def bridge_pairs(names: list[str], group: dict[str, int], tried: set[tuple[int, int]], *,
                 per_panorama: int = BRIDGE_PAIRS_PER_PANORAMA) -> list[tuple[int, int]]:
    """Index pairs (a < b) not yet tried whose panoramas lie in different groups (group: {NAME: group index}), nearest
    in name (capture) order first, at most per_panorama x len(names): rooms joined only through a doorway look
    unlike each other, so appearance does not find those pairs, and a group that does not join the others needs
    every pair across."""
    k = len(names)
    todo = [(a, b) for a in range(k) for b in range(a + 1, k)
            if (a, b) not in tried and group.get(names[a], -1 - a) != group.get(names[b], -1 - b)]
    todo.sort(key=lambda ab: (ab[1] - ab[0], ab[0]))
    return sorted(todo[: per_panorama * k])
