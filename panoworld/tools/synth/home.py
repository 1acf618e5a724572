"""Several panoramas of one multi-room home with exact poses: SCENE/panoramas/, SCENE/depths/ and gt/poses.json."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from panoworld.geometry.raycast import Raycaster
from panoworld.tools.synth.generate import SceneGenerationError, derive_seed, generate_scene
from panoworld.tools.synth.layout import SOLID, FloorPlan, architecture_quads, quads_to_mesh
from panoworld.tools.synth.params import Preset, SynthParams, params_for
from panoworld.tools.synth.scene import SynthScene
from panoworld.tools.synth.tracks import Track, TrackPlanner, distance_to_mesh, pose_from_xz_heading

MIN_ROOMS = 3
MAX_PANORAMAS = 32
MAX_SPACING_M = 3.5
"""A capture point is at most this far from an earlier one it sees (real-estate tours: every few metres)."""
DEPTH_KINDS = ("scene", "layout")
"""What depths/NAME.npy holds: the rendered scene's depth, or its capture room's layout alone (layout_depth)."""


@dataclass(kw_only=True)
class HomeCapture:
    """A synthetic home and the capture poses of its panoramas."""

    scene: SynthScene
    """The home (tracks[0] holds the capture poses in order, so gt.json's canonical frame is the first panorama)."""
    names: list[str]
    """Panorama names (file stems), in capture order."""
    world_from_cam: np.ndarray
    """(K, 4, 4) capture poses in the scene's world frame, OpenCV camera axes, metres."""
    rooms: list[int]
    """Room id of each capture point."""


def tour_rooms(n_panoramas: int) -> tuple[int, int]:
    """The range of room counts of a home captured by n_panoramas: MIN_ROOMS to 4 up to 8 panoramas, then about one
    room per 3 panoramas (a real-estate tour: a few panoramas in the large rooms, one in each small one)."""
    return (MIN_ROOMS, 4) if n_panoramas <= 8 else (n_panoramas // 3, n_panoramas // 3 + 2)


def home_params(preset: Preset | str, n_rooms: tuple[int, int] = (MIN_ROOMS, 4)) -> SynthParams:
    """The preset's generator settings with at least MIN_ROOMS rooms and no dense tracks (captures are placed later)."""
    p = params_for(preset)
    layout = replace(p.layout, n_rooms=n_rooms)
    if Preset(preset) is Preset.CI_TINY:
        layout = replace(layout, room_size_m=(3.0, 4.5))
    return replace(p, layout=layout, tracks=replace(p.tracks, n_tracks=1, frames=1),
                   render=replace(p.render, write_frames=False))


def floor_plan(scene: SynthScene) -> FloorPlan:
    """The grid floor plan a generated scene was built from (rooms, doorways, ceiling and door heights)."""
    m, fp = scene.meta, scene.floorplan
    return FloorPlan(label=fp["label"], top=fp["top"], door=fp["door"], cell=m["cell_m"], origin_x=m["origin_x"],
                     origin_z=m["origin_z"], ceiling=m["ceiling_height_m"], door_height=m["door_height_m"],
                     n_rooms=m["n_rooms"])


def _place_captures(scene: SynthScene, params: SynthParams, k: int, rng: np.random.Generator
                    ) -> tuple[np.ndarray, list[int]]:
    """k upright capture poses, each in line of sight of an earlier one 1.5 m to MAX_SPACING_M away, preferring rooms not yet
    captured (a tour through the doorways); raises SceneGenerationError when the home has no room for them."""
    plan = floor_plan(scene)
    tp = params.tracks
    planner = TrackPlanner(plan, scene.floorplan["occupied"], scene.triangles, tp, margin=params.furniture.walk_margin_m)
    cells = planner.cells
    xz_all = plan.cell_centers(cells)
    room_all = plan.label[tuple(cells.T)]
    clear = planner.dist[tuple(cells.T)]
    h_max = min(plan.door_height, plan.ceiling) - tp.clearance_m - 0.05
    height = float(rng.uniform(tp.camera_height_m[0], max(tp.camera_height_m[0], min(tp.camera_height_m[1], h_max))))
    first = np.flatnonzero(room_all == room_all[np.argmax(clear)])
    w = clear[first] ** 4
    chosen = [int(first[rng.choice(len(first), p=w / w.sum())])]
    while len(chosen) < k:
        pts = xz_all[chosen]
        d = np.linalg.norm(xz_all[:, None] - pts[None], axis=2)
        ok = (d.min(1) >= 1.2) & ((d >= 1.5) & (d <= MAX_SPACING_M)).any(1)
        cand = np.flatnonzero(ok)
        if len(cand) == 0:
            raise SceneGenerationError(f"no capture point {len(chosen)} of {k} fits 1.2-{MAX_SPACING_M} m from the others")
        covered = {int(room_all[c]) for c in chosen}
        new_room = cand[~np.isin(room_all[cand], list(covered))]
        order = rng.permutation(new_room) if len(new_room) else np.array([], int)
        order = np.concatenate([order, rng.permutation(np.setdiff1d(cand, new_room))]).astype(int)
        for c in order[:600]:
            # Line of sight at camera height to an earlier capture point 1.5 m to MAX_SPACING_M away.
            near = [j for j in chosen if 1.5 <= d[c, chosen.index(j)] <= MAX_SPACING_M]
            a = np.array([xz_all[c][0], -height, xz_all[c][1]])
            seen = False
            for j in near:
                b = np.array([xz_all[j][0], -height, xz_all[j][1]])
                dist = float(np.linalg.norm(b - a))
                hit = scene.raycaster.cast(a[None], ((b - a) / dist)[None])
                if hit.distance[0] >= dist - 1e-3:
                    seen = True
                    break
            if seen:
                chosen.append(int(c))
                break
        else:
            raise SceneGenerationError(f"no capture point {len(chosen)} of {k} in line of sight of the others")
    yaw = rng.uniform(-np.pi, np.pi, k)
    poses = pose_from_xz_heading(xz_all[chosen], np.stack([np.sin(yaw), np.cos(yaw)], 1), height)
    if (distance_to_mesh(poses[:, :3, 3], scene.triangles, 2 * tp.clearance_m) < tp.clearance_m).any():
        raise SceneGenerationError("a capture point is closer than the clearance to the geometry")
    return poses, [int(room_all[c]) for c in chosen]


def generate_home(seed: int, n_panoramas: int, preset: Preset | str = Preset.DEFAULT, *,
                  params: SynthParams | None = None, attempts: int = 8) -> HomeCapture:
    """A home of >= 3 rooms (tour_rooms) and n_panoramas (2 to MAX_PANORAMAS) capture poses, deterministic in seed;
    then SceneGenerationError."""
    if not 2 <= n_panoramas <= MAX_PANORAMAS:
        raise ValueError(f"{n_panoramas=} but expected 2..{MAX_PANORAMAS} panoramas of one home")
    params = params or home_params(preset, tour_rooms(n_panoramas))
    errors = []
    for attempt in range(attempts):
        home_seed = derive_seed(int(seed), 7, attempt)
        try:
            scene = generate_scene(home_seed, preset, params=params)
            poses, rooms = _place_captures(scene, params, n_panoramas, np.random.default_rng(derive_seed(home_seed, 1)))
        except SceneGenerationError as e:
            errors.append(f"attempt {attempt}: {str(e).splitlines()[0]}")
            continue
        if n_panoramas >= MIN_ROOMS and len(set(rooms)) < MIN_ROOMS:
            errors.append(f"attempt {attempt}: captures cover only rooms {sorted(set(rooms))}")
            continue
        scene.tracks = [Track(world_from_cam=poses, camera_height=float(-poses[0, 1, 3]))]
        scene.meta.update(seed=int(seed), home_attempt=attempt)
        return HomeCapture(scene=scene, names=[f"pano_{i:02d}" for i in range(n_panoramas)], world_from_cam=poses,
                           rooms=rooms)
    raise SceneGenerationError(f"seed {seed}: no home with {n_panoramas} capture points in {attempts} attempts:\n  "
                               + "\n  ".join(errors))


def layout_depth(plan: FloorPlan, room: int, world_from_cam: np.ndarray, height: int, width: int) -> np.ndarray:
    """(height, width) float32 ray depth of one room's layout as a room-layout annotation (ZInD) gives it: the walls
    of room (a label of plan) with every doorway closed, its floor and a flat ceiling; no furniture, no other room."""
    own = plan.label == room
    solo = replace(plan, label=np.where(own, 0, SOLID).astype(np.int32), top=np.where(own, plan.ceiling, 0.0),
                   door=np.zeros_like(plan.door), n_rooms=1)
    quads = list(architecture_quads(solo).values())
    vertices, faces = quads_to_mesh(np.concatenate([q.corners for q in quads]), np.concatenate([q.normal for q in quads]))
    return Raycaster(vertices, faces).render_erp(world_from_cam, height, width).distance.astype(np.float32)


def write_home(home: HomeCapture, out_dir: str | os.PathLike, params: SynthParams, *, depth: str = "scene") -> Path:
    """Render and write SCENE/panoramas/NAME.png, SCENE/depths/NAME.npy and gt/ (with gt/poses.json) atomically; depth
    (DEPTH_KINDS) "layout" writes each capture room's layout_depth, as real-estate tours annotate it."""
    if depth not in DEPTH_KINDS:
        raise ValueError(f"{depth=} but expected one of {DEPTH_KINDS}")
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"{out} already exists and is not an empty directory; refusing to overwrite it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        for sub in ("gt", "panoramas", "depths"):
            (tmp / sub).mkdir(parents=True)
        h = params.render.pano_height
        plan = floor_plan(home.scene)
        for name, pose, room in zip(home.names, home.world_from_cam, home.rooms):
            rgb, d = home.scene.render(pose, h, 2 * h, supersample=params.render.supersample)
            cv2.imwrite(str(tmp / "panoramas" / f"{name}.png"), rgb[..., ::-1])
            np.save(tmp / "depths" / f"{name}.npy", layout_depth(plan, room, pose, h, 2 * h) if depth == "layout" else d)
        pano_rel = {"rgb": f"../panoramas/{home.names[0]}.png", "depth": f"../depths/{home.names[0]}.npy", "height": h,
                    "width": 2 * h, "track": 0, "frame": 0, "supersample": params.render.supersample}
        home.scene.save_gt(tmp / "gt", pano_rel=pano_rel)
        poses = {n: T.tolist() for n, T in zip(home.names, home.world_from_cam)}
        (tmp / "gt" / "poses.json").write_text(json.dumps(poses, indent=1, sort_keys=True) + "\n")
        rooms = {n: r for n, r in zip(home.names, home.rooms)}
        (tmp / "gt" / "capture_rooms.json").write_text(json.dumps(rooms, indent=1, sort_keys=True) + "\n")
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
