"""The register artifact: panoramas.json ({NAME: 4x4 world_from_cam}, first registered panorama's frame) and
registration.json (per-panorama quality and every pair tried)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.core.errors import InputError
from panoworld.io.home import PANORAMAS_JSON, RIG_MASK_PNG, first_few, to_levelled
from panoworld.io.images import read_rig_mask
from panoworld.io.jsonio import read_json, write_json
from panoworld.register.inputs import REGISTRATION_JSON, find_multi_scene, read_poses
from panoworld.register.options import RegisterOptions
from panoworld.register.registration import Registration


def register_scene(scene: Path, options: RegisterOptions, out_dir: Path) -> dict:
    """Register the panoramas of scene and write the artifact files into out_dir -> manifest info."""
    ms = find_multi_scene(scene)
    given = read_poses(ms.poses, ms.names) if ms.poses else {}
    missing = [n for n in ms.names if n not in given and n not in ms.depths]
    if missing:
        raise InputError(f"{Path(scene) / 'depths'}: no depth for {missing}; give depths/NAME.npy (metric ray depth, "
                         "metres) for every panorama without a pose in poses.json")
    from panoworld.io.depth import read_depth, read_panorama  # cv2: the runner's registration_note needs neither
    from panoworld.register.solve import register_panoramas  # cv2, torch, pycolmap

    need_pixels = len(given) < len(ms.names)
    rgbs = {n: read_panorama(ms.panoramas[n]) for n in ms.names} if need_pixels else {}
    depths = {n: read_depth(ms.depths[n]) for n in ms.names if n in ms.depths} if need_pixels else {}
    rigs = {n: read_rig_mask(p) for n, p in ms.rig_masks.items()} if need_pixels else {}
    reg = register_panoramas(ms.names, rgbs, depths, given=given, options=options, rig_masks=rigs)
    write_registration(out_dir, reg)
    return _summary(ms.names, given, reg)


def register_depth_dirs(dirs: dict[str, Path] | None, poses_file: Path | None, options: RegisterOptions,
                        out_dir: Path, *, levelled: dict[str, np.ndarray] | None = None) -> dict:
    """Register the cleaned panoramas and depths of a home's depth artifact ({NAME: dir of depth.npy, valid.png,
    panorama.png}; the pipeline's path); None (a single panorama) is one capture point at the identity. levelled:
    {NAME: (3, 3) level_from_cam} of the panoramas the depth stage levelled, whose given poses (of the camera as
    taken) are turned into the levelled camera's. -> info."""
    from panoworld.io.depth import load_depth_artifact

    if dirs is None:
        if poses_file is not None:
            raise InputError(f"{poses_file}: poses are for a home (SCENE/panoramas/); this scene has one panorama, "
                             "remove poses.json")
        reg = Registration(world_from_cam={"panorama": np.eye(4)},
                           panoramas={"panorama": {"registered": True, "source": "single", "parent": None}})
        write_registration(out_dir, reg)
        return {"num_panoramas": 1, "num_registered": 1, "num_given": 0, "unregistered": [], "pairs_accepted": 0,
                "pairs_tried": 0}
    from panoworld.core.parallel import map_ahead
    from panoworld.register.solve import pair_threads, register_panoramas  # cv2, torch, pycolmap: not for one panorama

    def load(d: Path):
        depth, valid, rgb = load_depth_artifact(d)
        rig = Path(d) / RIG_MASK_PNG
        return rgb, np.where(valid, depth, 0.0).astype(np.float32), read_rig_mask(rig) if rig.is_file() else None

    names = list(dirs)
    given = to_levelled(read_poses(poses_file, names) if poses_file is not None else {}, levelled or {})
    rgbs, depths, rigs = {}, {}, {}
    if len(given) < len(names):  # decoding releases the GIL: the panoramas on the pairs' threads
        for n, (rgbs[n], depths[n], rig) in zip(names, map_ahead(load, [dirs[n] for n in names], workers=pair_threads())):
            if rig is not None:
                rigs[n] = rig
    from panoworld.core.progress import bar as progress_bar
    from panoworld.register.pair_select import candidate_pairs

    total = len(candidate_pairs(names, given=given, all_up_to=options.all_pairs_up_to)) \
        if len(names) <= options.all_pairs_up_to else None  # beyond: the pairs tried depend on what the first ones join
    with progress_bar(total=total, desc="register pairs", unit="pair", leave=False) as bar:
        reg = register_panoramas(names, rgbs, depths, given=given, options=options, rig_masks=rigs,
                                 progress=lambda a, b, pair: bar.update(1))
    write_registration(out_dir, reg)
    return _summary(names, given, reg)


def _summary(names: list[str], given: dict, reg: Registration) -> dict:
    n_reg = sum(p["registered"] for p in reg.panoramas.values())
    levelled = {n: p["levelled_tilt_deg"] for n, p in reg.panoramas.items() if "levelled_tilt_deg" in p}
    return {"num_panoramas": len(names), "num_registered": n_reg, "num_given": len(given),
            "unregistered": [n for n, p in reg.panoramas.items() if not p["registered"]],
            "pairs_accepted": sum(p.get("edge") is not None for p in reg.pairs), "pairs_tried": len(reg.pairs),
            **({"levelled_tilt_deg": levelled} if levelled else {})}


def write_registration(out_dir: Path, reg: Registration) -> None:
    """panoramas.json and registration.json into out_dir."""
    write_json(out_dir / PANORAMAS_JSON, {n: T.round(9).tolist() for n, T in reg.world_from_cam.items()},
               sort_keys=True)
    write_json(out_dir / REGISTRATION_JSON, {"frame": "world_from_cam (OpenCV camera axes, metres) in the frame of the "
                                             "first registered panorama", "panoramas": reg.panoramas,
                                             "pairs": reg.pairs})


def read_registration(artifact_dir: Path) -> tuple[dict, dict]:
    """(panoramas.json, registration.json) of a register artifact."""
    return read_json(Path(artifact_dir) / PANORAMAS_JSON), read_json(Path(artifact_dir) / REGISTRATION_JSON)


def unplaced_groups(panoramas: dict) -> list[list[str]]:
    """The groups of the panoramas a registration left unplaced (registration.json's "panoramas": each unplaced one's
    "group", itself and the panoramas joined to it), each once, in the order they first appear."""
    groups: list[list[str]] = []
    for n, p in panoramas.items():
        group = p.get("group") or [n]
        if not p.get("registered") and group not in groups:
            groups.append(group)
    return groups


def registration_note(artifact_dir: Path, root: Path | None = None) -> str | None:
    """"home: 1 of 3 panoramas registered (not placed: ...; see artifacts/register/registration.json; ...)" when a
    register artifact placed fewer than all its panoramas, with the remedies (a pose in the scene's poses.json for one
    panorama of each group that no pair joins places that group; `runner.py split` makes each group a home of its
    own), and the panoramas registration levelled (taken with the camera not level); None when it placed all, level
    (or there is no readable artifact)."""
    info = read_json(Path(artifact_dir) / "manifest.json", default={})
    info = info.get("info") if isinstance(info, dict) else None
    if not isinstance(info, dict):
        return None
    parts = []
    if info.get("num_registered") != info.get("num_panoramas"):
        left = [str(n) for n in info.get("unregistered") or []]
        shown = Path(artifact_dir) / REGISTRATION_JSON
        shown = shown.relative_to(root) if root is not None and shown.is_relative_to(root) else shown
        parts.append(f"{info.get('num_registered')} of {info.get('num_panoramas')} panoramas registered (not placed: "
                     f"{first_few(left)}; see {shown}; a pose in poses.json for one panorama of each group "
                     "places it, `runner.py split` makes each group a home of its own)")
    tilted = info.get("levelled_tilt_deg")
    if isinstance(tilted, dict) and tilted:
        listed = first_few([f"{n} {float(d):.1f}°" for n, d in tilted.items()])
        parts.append(f"taken with the camera not level: {listed}; levelled for registration, the scene is built "
                     "as taken (docs/multi.md)")
    return "home: " + "; ".join(parts) if parts else None
