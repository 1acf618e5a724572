"""A home's registration against its true capture poses (gt/poses.json of `runner.py synth --panoramas K`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.core.conventions import invert_pose
from panoworld.io.home import capture_poses, levelled_panoramas, to_levelled
from panoworld.io.jsonio import read_json
from panoworld.tools.eval.common import unavailable
from panoworld.tools.eval.groundtruth import NoReference

GT_POSES = Path("gt") / "poses.json"
MISPLACED_CM, MISPLACED_DEG = 20.0, 5.0
"""A registered panorama farther than this from its true pose counts as misplaced (a wrong registration)."""


def pose_errors(est: dict[str, np.ndarray], gt: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
    """{NAME: (translation cm, rotation deg)} of est (world_from_cam (4, 4) in the frame of its first panorama by name)
    against gt (world_from_cam in any frame) brought into the frame of that same panorama."""
    anchor = sorted(est)[0]
    cam0_from_world = invert_pose(gt[anchor])
    out = {}
    for n, E in est.items():
        G = cam0_from_world @ gt[n]
        cos = np.clip((np.trace(G[:3, :3].T @ E[:3, :3]) - 1) / 2, -1, 1)
        out[n] = (float(np.linalg.norm(G[:3, 3] - E[:3, 3]) * 100), float(np.degrees(np.arccos(cos))))
    return out


def registered_and_true(register_dir: Path, scene_dir: Path) -> tuple[dict, dict, str]:
    """(true poses {NAME: world_from_cam (4, 4)} of SCENE/gt/poses.json, the registered ones of them (the register
    artifact's panoramas.json, its frame), the anchor: the first registered by name, the home's world frame).
    The true pose of a panorama the depth stage levelled (the depth artifact beside the register artifact) is its
    levelled camera's, as registration places it. NoReference without true poses or when none of them is
    registered."""
    gt_path = Path(scene_dir) / GT_POSES
    if not gt_path.is_file():
        raise NoReference(f"no {GT_POSES.as_posix()}: registration is scored against the true capture poses of a "
                          "synthetic home (runner.py synth OUT --panoramas K)")
    gt = {n: np.asarray(T, np.float64).reshape(4, 4) for n, T in read_json(gt_path).items()}
    depth_dir = Path(register_dir).parent / "depth"  # a variant's register may sit beside no depth artifact
    depth_dir = depth_dir if (depth_dir / "manifest.json").is_file() else Path(scene_dir) / "artifacts" / "depth"
    gt = to_levelled(gt, levelled_panoramas(depth_dir))
    est = {n: T for n, T in capture_poses(register_dir).items() if n in gt}
    if not est:
        raise NoReference(f"none of the registered panoramas is in {GT_POSES.as_posix()}")
    return gt, est, sorted(est)[0]


def registration_metrics(register_dir: Path, scene_dir: Path) -> dict:
    """Registered count and the pose errors of the register artifact against SCENE/gt/poses.json: translation (cm)
    and rotation (degrees) of every registered panorama but the anchor (the first registered by name) relative to
    it, mean and max, and how many are misplaced (MISPLACED_CM, MISPLACED_DEG). NoReference without true poses."""
    gt, est, anchor = registered_and_true(register_dir, scene_dir)
    others = {n: e for n, e in pose_errors(est, gt).items() if n != anchor}
    out = {"num_panoramas": len(gt), "registered": len(est), "registered_fraction": len(est) / len(gt),
           "unregistered": sorted(set(gt) - set(est)), "anchor": anchor}
    if not others:
        none = unavailable(f"only {anchor} registered")
        return {**out, **dict.fromkeys(("trans_cm_mean", "trans_cm_max", "rot_deg_mean", "rot_deg_max", "misplaced"),
                                       none)}
    t = np.array([e[0] for e in others.values()])
    r = np.array([e[1] for e in others.values()])
    return {**out, "trans_cm_mean": float(t.mean()), "trans_cm_max": float(t.max()), "rot_deg_mean": float(r.mean()),
            "rot_deg_max": float(r.max()), "worst": max(others, key=lambda n: others[n][0]),
            "misplaced": int(sum(c > MISPLACED_CM or d > MISPLACED_DEG for c, d in others.values()))}
