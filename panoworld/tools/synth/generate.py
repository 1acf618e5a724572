"""Procedural scene generation: floor plan, furniture, materials, lights and camera tracks from a seed."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
import trimesh

from panoworld.core.errors import PanoWorldError
from panoworld.tools.synth.appearance import Light, Material, MaterialKind
from panoworld.tools.synth.furniture import FurnitureKind, PlacementError, Placer, Role
from panoworld.tools.synth.layout import FloorPlan, LayoutError, architecture_quads, generate_floor_plan, quads_to_mesh
from panoworld.tools.synth.params import Preset, SynthParams, params_for
from panoworld.tools.synth.scene import Node, SynthScene
from panoworld.tools.synth.tracks import TrackError, TrackPlanner


class SceneGenerationError(PanoWorldError, RuntimeError):
    """No walkable scene could be generated for the requested seed and parameters."""


def derive_seed(seed: int, *path: int) -> int:
    """Deterministic 32-bit child seed of seed along an integer path (scene attempts, dataset scenes)."""
    return int(np.random.SeedSequence([seed, *path]).generate_state(1, np.uint32)[0])


def _check_seed(seed: int) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"{seed=} but expected a non-negative integer seed")


def _random_material(rng: np.random.Generator, kind: MaterialKind) -> Material:
    def col(lo, hi):
        return tuple(float(v) for v in rng.uniform(lo, hi, 3))

    seed = int(rng.integers(1 << 31))
    axis = int(rng.choice([0, 2]))
    if kind == MaterialKind.PLASTER:
        base = np.array(col(0.55, 0.85))
        return Material(kind=kind, color=tuple(base.tolist()), color2=tuple((base * rng.uniform(0.7, 0.85)).tolist()),
                        scale=float(rng.uniform(0.15, 0.5)), seed=seed)
    if kind in (MaterialKind.WOOD, MaterialKind.PLANKS):
        tone = float(rng.uniform(0.25, 1.0))
        c1 = tuple(float(v) for v in np.array([0.55, 0.36, 0.2]) * tone + 0.05)
        c2 = tuple(float(v) for v in np.array([0.3, 0.17, 0.08]) * tone)
        scale = float(rng.uniform(0.12, 0.2)) if kind == MaterialKind.PLANKS else float(rng.uniform(0.1, 0.3))
        return Material(kind=kind, color=c1, color2=c2, scale=scale, seed=seed, axis=axis)
    if kind == MaterialKind.TILES:
        return Material(kind=kind, color=col(0.45, 0.9), color2=col(0.2, 0.6), scale=float(rng.choice([0.3, 0.4, 0.6])),
                        seed=seed)
    if kind == MaterialKind.FABRIC:
        return Material(kind=kind, color=col(0.08, 0.7), color2=col(0.08, 0.7), scale=float(rng.uniform(0.05, 0.15)),
                        seed=seed)
    if kind == MaterialKind.PAINT:
        return Material(kind=kind, color=col(0.1, 0.85), color2=col(0.1, 0.85), scale=0.2, seed=seed)
    if kind == MaterialKind.PICTURE:
        return Material(kind=kind, color=(0.5, 0.5, 0.5), color2=(0.5, 0.5, 0.5), scale=float(rng.uniform(0.03, 0.08)),
                        seed=seed)
    if kind == MaterialKind.BOOKS:
        return Material(kind=kind, color=(0.5, 0.5, 0.5), color2=(0.5, 0.5, 0.5), scale=float(rng.uniform(0.025, 0.04)),
                        seed=seed)
    return Material(kind=kind, color=(1.0, 0.96, 0.88), color2=(1.0, 0.96, 0.88), scale=1.0, seed=seed)


_ROLE_KIND = {
    Role.WOOD: MaterialKind.WOOD, Role.FABRIC: MaterialKind.FABRIC, Role.FABRIC2: MaterialKind.FABRIC,
    Role.PAINT: MaterialKind.PAINT, Role.METAL: MaterialKind.PAINT, Role.STONE: MaterialKind.PLASTER,
    Role.BOOKS: MaterialKind.BOOKS, Role.PICTURE: MaterialKind.PICTURE, Role.LIGHT: MaterialKind.LIGHT,
}


def _build(scene_seed: int, params: SynthParams) -> tuple[SynthScene, FloorPlan]:
    rng_plan, rng_furn, rng_mat, rng_track = (np.random.default_rng(s) for s in
                                              np.random.SeedSequence(scene_seed).spawn(4))
    plan = generate_floor_plan(rng_plan, params.layout)
    placer = Placer(plan, params.furniture, params.tracks.clearance_m)
    placer.furnish(rng_furn)

    materials: dict[str, Material] = {}
    nodes: list[Node] = []

    def add_material(name: str, kind: MaterialKind) -> str:
        materials[name] = _random_material(rng_mat, kind)
        return name

    def add_node(name, obj, kind, room, material, meshes):
        mesh = trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]
        nodes.append(Node(name=name, object=obj, kind=kind, room=room, material=material,
                          vertices=np.asarray(mesh.vertices, np.float32), faces=np.asarray(mesh.faces, np.int64)))

    quads = architecture_quads(plan)
    for r in range(plan.n_rooms):
        floor_kind = MaterialKind.PLANKS if rng_mat.random() < 0.6 else MaterialKind.TILES
        surface_mat = {
            "floor": add_material(f"room{r}_floor", floor_kind),
            "walls": add_material(f"room{r}_walls", MaterialKind.PLASTER),
            "ceiling": add_material(f"room{r}_ceiling", MaterialKind.PLASTER),
        }
        for part in ("floor", "walls", "ceiling"):
            q = quads[part]
            sel = q.owner == r
            if not sel.any():
                continue
            v, f = quads_to_mesh(q.corners[sel], q.normal[sel])
            add_node(f"room{r}.{part}", f"room{r}", part, r, surface_mat[part], [trimesh.Trimesh(v, f, process=False)])
    palette = {
        Role.WOOD: [add_material(f"wood_{k}", MaterialKind.WOOD) for k in range(3)],
        Role.FABRIC: [add_material(f"fabric_{k}", MaterialKind.FABRIC) for k in range(3)],
        Role.FABRIC2: [add_material(f"fabric_{k}", MaterialKind.FABRIC) for k in range(3, 5)],
        Role.PAINT: [add_material(f"paint_{k}", MaterialKind.PAINT) for k in range(2)],
        Role.METAL: [add_material(f"metal_{k}", MaterialKind.PAINT) for k in range(2)],
        Role.STONE: [add_material("stone_0", MaterialKind.PLASTER)],
        Role.BOOKS: [add_material(f"books_{k}", MaterialKind.BOOKS) for k in range(2)],
        Role.LIGHT: [add_material("light_0", MaterialKind.LIGHT)],
    }
    lights = []
    for obj in placer.placed:
        roles = sorted({p.role for p in obj.parts})
        for role in roles:
            if role == Role.PICTURE:
                mat = add_material(f"{obj.name}_picture", MaterialKind.PICTURE)
            else:
                options = palette[role]
                mat = options[int(rng_mat.integers(len(options)))]
            add_node(f"{obj.name}.{role}", obj.name, str(obj.kind), obj.room, mat,
                     [p.mesh for p in obj.parts if p.role == role])
        if obj.light_at is not None:
            ceiling = obj.kind == FurnitureKind.CEILING_LIGHT
            tint = np.array([1.0, 0.93, 0.82]) if ceiling else np.array([1.0, 0.8, 0.55])
            lights.append(Light(position=tuple(float(v) for v in obj.light_at),
                                intensity=tuple(float(v) for v in tint * (1.0 if ceiling else 0.4)),
                                falloff=2.5 if ceiling else 1.5))

    meta = {
        "ceiling_height_m": plan.ceiling, "door_height_m": plan.door_height, "cell_m": plan.cell,
        "origin_x": plan.origin_x, "origin_z": plan.origin_z, "n_rooms": plan.n_rooms,
        "fps": params.tracks.fps, "step_m": params.tracks.step_m,
    }
    floorplan = {"label": plan.label, "top": plan.top, "door": plan.door, "occupied": placer.occ}
    scene = SynthScene(nodes=nodes, materials=materials, lights=lights, ambient=0.26, tracks=[],
                       clearance=params.tracks.clearance_m, meta=meta, floorplan=floorplan)
    planner = TrackPlanner(plan, placer.occ, scene.triangles, params.tracks, margin=params.furniture.walk_margin_m)
    scene.tracks = [planner.plan_track(rng_track, params.tracks.frames) for _ in range(params.tracks.n_tracks)]
    return scene, plan


def generate_scene(
    seed: int, preset: Preset | str = Preset.DEFAULT, *, params: SynthParams | None = None, frames: int | None = None
) -> SynthScene:
    """Generate a scene deterministically from seed; failed draws retry with derived seeds, then SceneGenerationError."""
    _check_seed(seed)
    if params is None:
        params = params_for(preset, frames=frames)
        preset = Preset(preset)
    if params.tracks.n_tracks < 1 or params.tracks.frames < 1:
        raise ValueError(f"{params.tracks.n_tracks=} and {params.tracks.frames=} must both be >= 1")
    errors = []
    for attempt in range(params.max_scene_attempts):
        scene_seed = derive_seed(int(seed), 0, attempt)
        try:
            scene, _ = _build(scene_seed, params)
        except (LayoutError, PlacementError, TrackError) as e:
            errors.append(f"attempt {attempt} (scene seed {scene_seed}): {e}")
            continue
        scene.meta.update(seed=int(seed), scene_seed=scene_seed, attempt=attempt, preset=str(preset),
                          params=asdict(params))
        return scene
    raise SceneGenerationError(
        f"seed {seed} with preset {preset!s} produced no walkable scene in {params.max_scene_attempts} attempts:\n  "
        + "\n  ".join(errors)
    )
