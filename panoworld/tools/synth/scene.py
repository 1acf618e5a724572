"""SynthScene: generation, exact ERP rendering (RGB + metric ray depth), and the on-disk ground-truth format."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import trimesh
from tqdm import tqdm

from panoworld.core.conventions import (
    GLTF_FROM_WORLD,
    check_erp_shape,
    check_pose,
    erp_dirs,
    pinhole_dirs,
    quat_wxyz_from_rotmat,
    quat_xyzw_from_wxyz,
)
from panoworld.core.errors import PanoWorldError
from panoworld.geometry.raycast import Raycaster
from panoworld.tools.synth.appearance import Light, Material, MaterialKind, albedo, srgb_uint8
from panoworld.tools.synth.furniture import FurnitureKind, PlacementError, Placer, Role
from panoworld.tools.synth.layout import FloorPlan, LayoutError, architecture_quads, generate_floor_plan, quads_to_mesh
from panoworld.tools.synth.params import Preset, SynthParams, params_for
from panoworld.tools.synth.rig import RigKind, render_with_rig
from panoworld.tools.synth.tracks import Track, TrackError, TrackPlanner

GT_FORMAT = "panoworld-synth-gt"
GT_VERSION = 1


class SceneGenerationError(PanoWorldError, RuntimeError):
    """No walkable scene could be generated for the requested seed and parameters."""


@dataclass(kw_only=True)
class Node:
    """One named mesh node of the scene (one object's faces sharing one material)."""

    name: str
    """Unique node name '<object>.<role>', also the node and mesh name in the .glb."""
    object: str
    """Object name, e.g. 'room0' or 'table_03'."""
    kind: str
    """'floor' / 'walls' / 'ceiling' for architecture, else the FurnitureKind."""
    room: int
    """Room id."""
    material: str
    """Key into SynthScene.materials."""
    vertices: np.ndarray
    """(V, 3) float32 world vertices."""
    faces: np.ndarray
    """(F, 3) int64 vertex indices."""


def derive_seed(seed: int, *path: int) -> int:
    """Deterministic 32-bit child seed of seed along an integer path (scene attempts, dataset scenes)."""
    return int(np.random.SeedSequence([seed, *path]).generate_state(1, np.uint32)[0])


def _check_seed(seed: int) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"{seed=} but expected a non-negative integer seed")


@dataclass(kw_only=True)
class SynthScene:
    """A procedural indoor scene with exact geometry, procedural appearance, lights and GT camera tracks."""

    nodes: list[Node]
    """Mesh nodes; their concatenation (in this order) is the ray-cast mesh."""
    materials: dict[str, Material]
    """Material specs by name."""
    lights: list[Light]
    """Point lights used by the baked shading."""
    ambient: float
    """Ambient light level (linear)."""
    tracks: list[Track]
    """GT camera tracks; tracks[0].world_from_cam[0] is the panorama pose and world_from_canonical."""
    clearance: float
    """Minimum distance in metres from every track pose to the geometry."""
    meta: dict = field(default_factory=dict)
    """Seed, preset, parameters and floor-plan facts (JSON-serialisable)."""
    floorplan: dict[str, np.ndarray] = field(default_factory=dict)
    """Grids 'label', 'top', 'door', 'occupied' (Hz, Wx) of the floor plan (see docs/synth.md)."""

    def __post_init__(self):
        self.vertices = np.concatenate([n.vertices for n in self.nodes]).astype(np.float32)
        offsets = np.cumsum([0] + [len(n.vertices) for n in self.nodes[:-1]])
        self.faces = np.concatenate([n.faces + o for n, o in zip(self.nodes, offsets)]).astype(np.int64)
        self.face_node = np.concatenate([np.full(len(n.faces), k, np.int32) for k, n in enumerate(self.nodes)])
        self.material_names = sorted(self.materials)
        mat_index = {m: k for k, m in enumerate(self.material_names)}
        self.face_material = np.array([mat_index[n.material] for n in self.nodes], np.int32)[self.face_node]
        tri = self.vertices.astype(np.float64)[self.faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.face_normals = normal / np.linalg.norm(normal, axis=1, keepdims=True)
        self.raycaster = Raycaster(self.vertices, self.faces)

    @property
    def world_from_canonical(self) -> np.ndarray:
        """(4, 4) pose of the first camera of track 0 (the pipeline's canonical frame)."""
        return self.tracks[0].world_from_cam[0].copy()

    @property
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) float64 world triangles."""
        return self.vertices.astype(np.float64)[self.faces]

    def node_faces(self, *, kind: str | None = None, name: str | None = None) -> np.ndarray:
        """Indices of faces belonging to nodes of the given kind and/or name."""
        keep = [(kind is None or n.kind == kind) and (name is None or n.name == name) for n in self.nodes]
        return np.flatnonzero(np.asarray(keep)[self.face_node])

    def render(
        self, world_from_cam: np.ndarray, height: int, width: int, *, supersample: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """ERP render -> (rgb (H, W, 3) uint8, depth (H, W) float32 ray distance in metres, inf where nothing is hit).

        supersample=s shades an (sH, sW) ERP grid and box-filters it down in linear RGB; depth is always the exact
        distance along each pixel's centre ray.
        """
        check_pose(world_from_cam, "world_from_cam")
        check_erp_shape(height, width)
        if supersample < 1:
            raise ValueError(f"{supersample=} but expected an integer >= 1")
        hits = self.raycaster.render_erp(world_from_cam, height, width)
        depth = hits.distance.astype(np.float32)
        if supersample == 1:
            linear = self._shade(world_from_cam, hits.distance, hits.face)
        else:
            hs, ws = height * supersample, width * supersample
            fine = self.raycaster.render_erp(world_from_cam, hs, ws)
            linear = self._shade(world_from_cam, fine.distance, fine.face)
            linear = cv2.resize(linear.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
        return srgb_uint8(linear), depth

    def render_pinhole(
        self, world_from_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float, height: int, width: int, *,
        supersample: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pinhole (OpenCV) render -> (rgb (H, W, 3) uint8, depth (H, W) float32 ray distance, inf = nothing hit);
        supersample as in render(): an (sH, sW) image of the same camera box-filtered down in linear RGB."""
        check_pose(world_from_cam, "world_from_cam")
        if supersample < 1:
            raise ValueError(f"{supersample=} but expected an integer >= 1")
        pose = np.asarray(world_from_cam, np.float64)

        def cast(s: int):
            dirs = pinhole_dirs(fx * s, fy * s, cx * s, cy * s, height * s, width * s, np.float64)
            hits = self.raycaster.cast(pose[:3, 3][None], dirs.reshape(-1, 3) @ pose[:3, :3].T)
            return dirs, hits.distance.reshape(dirs.shape[:2]), hits.face.reshape(dirs.shape[:2])

        dirs, dist, face = cast(1)
        depth = dist.astype(np.float32)
        if supersample > 1:
            dirs, dist, face = cast(supersample)
        linear = self._shade(pose, dist, face, dirs)
        if supersample > 1:
            linear = cv2.resize(linear.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
        return srgb_uint8(linear), depth

    def render_frame(self, track: int, frame: int, height: int, *, supersample: int = 1):
        """Render frame `frame` of track `track` at (height, 2 * height) -> (rgb, depth) as in render()."""
        return self.render(self.tracks[track].world_from_cam[frame], height, 2 * height, supersample=supersample)

    def _shade(self, world_from_cam: np.ndarray, distance: np.ndarray, face: np.ndarray,
               dirs_cam: np.ndarray | None = None) -> np.ndarray:
        """Baked shading (H, W, 3) linear RGB: albedo * (ambient + shadowed lambert point lights); emitters unlit.
        dirs_cam (H, W, 3): the pixels' unit rays in the camera frame (default: the ERP grid's)."""
        h, w = distance.shape
        pose = np.asarray(world_from_cam, np.float64)
        if dirs_cam is None:
            dirs_cam = erp_dirs(h, w, np.float64)
        dirs = dirs_cam.reshape(-1, 3) @ pose[:3, :3].T
        face = face.reshape(-1)
        valid = np.flatnonzero(face >= 0)
        f = face[valid]
        d = dirs[valid]
        p = pose[:3, 3] + d * distance.reshape(-1)[valid, None].astype(np.float64)
        n = self.face_normals[f]
        n = np.where((np.einsum("ij,ij->i", n, d) > 0)[:, None], -n, n)
        mat = self.face_material[f]
        base = np.zeros((len(valid), 3))
        emissive = np.zeros(len(valid), bool)
        for m in np.unique(mat):
            sel = mat == m
            spec = self.materials[self.material_names[m]]
            base[sel] = albedo(spec, p[sel], n[sel])
            emissive[sel] = spec.kind == MaterialKind.LIGHT
        key = np.array([0.48, -0.6, 0.64])
        light = np.repeat((self.ambient * (0.75 + 0.15 * -n[:, 1] + 0.1 * (n @ key)))[:, None], 3, 1)
        # Lighting runs in float32 (it only feeds 8-bit colour); shadow rays start 2 mm off the surface.
        p32, n32 = p.astype(np.float32), n.astype(np.float32)
        origin = p32 + np.float32(2e-3) * n32
        not_emissive = ~emissive
        for L in self.lights:
            to_l = np.asarray(L.position, np.float32) - p32
            dl = np.sqrt(np.einsum("ij,ij->i", to_l, to_l))
            ndl = np.einsum("ij,ij->i", n32, to_l) / dl
            lit = np.flatnonzero((ndl > 0) & not_emissive)
            if len(lit) == 0:
                continue
            hit = self.raycaster.cast(origin[lit], to_l[lit] / dl[lit, None])
            lit = lit[hit.distance >= dl[lit] - 5e-3]
            gain = ndl[lit] / (1.0 + (dl[lit] / L.falloff) ** 2)
            light[lit] += gain[:, None] * np.asarray(L.intensity, np.float32)[None, :]
        rgb = base * light
        rgb[emissive] = base[emissive]
        out = np.zeros((h * w, 3))
        out[valid] = rgb
        return out.reshape(h, w, 3)

    # ---------------------------------------------------------------- on-disk format
    def save_gt(self, gt_dir: str | os.PathLike, *, pano_rel: dict | None = None, frames_rel: list | None = None) -> None:
        """Write glb, materials.json, floorplan.npz, tracks and gt.json into gt_dir (which must exist)."""
        gt = Path(gt_dir)
        glb = trimesh.Scene()
        for node in self.nodes:
            v = node.vertices.astype(np.float64) @ GLTF_FROM_WORLD[:3, :3].T
            mesh = trimesh.Trimesh(v, node.faces, process=False)
            normals = mesh.vertex_normals @ GLTF_FROM_WORLD[:3, :3]
            colour = srgb_uint8(albedo(self.materials[node.material], node.vertices.astype(np.float64), normals))
            mesh.visual.vertex_colors = np.concatenate([colour, np.full((len(colour), 1), 255, np.uint8)], 1)
            glb.add_geometry(mesh, geom_name=node.name, node_name=node.name)
        (gt / "scene.glb").write_bytes(glb.export(file_type="glb"))
        materials = {
            "ambient": self.ambient,
            "lights": [asdict(L) for L in self.lights],
            "materials": {k: self.materials[k].to_json() for k in self.material_names},
            "nodes": [
                {"name": n.name, "object": n.object, "kind": n.kind, "room": n.room, "material": n.material,
                 "n_faces": len(n.faces)}
                for n in self.nodes
            ],
        }
        _write_json(gt / "materials.json", materials)
        np.savez_compressed(gt / "floorplan.npz", **self.floorplan)
        (gt / "tracks").mkdir(exist_ok=True)
        tracks = []
        for k, tr in enumerate(self.tracks):
            stem = f"tracks/track_{k:02d}"
            _write_json(gt / f"{stem}.json", {"camera_height_m": tr.camera_height,
                                                "world_from_cam": tr.world_from_cam.tolist()}, indent=None)
            (gt / f"{stem}.tum.txt").write_text(_tum_text(tr.world_from_cam, self.meta["fps"]))
            entry = {
                "poses": f"{stem}.json", "tum": f"{stem}.tum.txt", "n_frames": len(tr.world_from_cam),
                "camera_height_m": tr.camera_height, "step_m": self.meta["step_m"], "fps": self.meta["fps"],
                "frames": frames_rel[k] if frames_rel else None,
            }
            tracks.append(entry)
        h0 = self.tracks[0].camera_height
        index = {
            "format": GT_FORMAT,
            "version": GT_VERSION,
            "seed": self.meta["seed"],
            "scene_seed": self.meta["scene_seed"],
            "attempt": self.meta["attempt"],
            "preset": self.meta["preset"],
            "params": self.meta["params"],
            "frame": {"units": "m", "up": [0.0, -1.0, 0.0], "poses": "world_from_cam in the scene world frame, "
                      "OpenCV camera axes; canonical frame = camera 0 of track 0"},
            "floor_y_world": 0.0,
            "floor_y_canonical": h0,
            "ceiling_height_m": self.meta["ceiling_height_m"],
            "door_height_m": self.meta["door_height_m"],
            "camera_height_m": h0,
            "clearance_m": self.clearance,
            "world_from_canonical": self.world_from_canonical.tolist(),
            "glb": "scene.glb",
            "glb_from_world": GLTF_FROM_WORLD.tolist(),
            "materials": "materials.json",
            "floorplan": {"path": "floorplan.npz", "cell_m": self.meta["cell_m"], "origin_x": self.meta["origin_x"],
                          "origin_z": self.meta["origin_z"]},
            "n_rooms": self.meta["n_rooms"],
            "n_triangles": int(len(self.faces)),
            "panorama": pano_rel,
            "tracks": tracks,
        }
        _write_json(gt / "gt.json", index)

    @classmethod
    def load(cls, gt_dir: str | os.PathLike) -> SynthScene:
        """Rebuild the exact scene (geometry, materials, lights, tracks) from a gt/ directory written by save_gt."""
        gt = Path(gt_dir)
        if not (gt / "gt.json").is_file():
            raise FileNotFoundError(f"{gt / 'gt.json'} not found; pass the gt/ directory of a synth scene")
        index = json.loads((gt / "gt.json").read_text())
        if index.get("format") != GT_FORMAT:
            raise ValueError(f"{gt / 'gt.json'} has format {index.get('format')!r} but expected {GT_FORMAT!r}")
        mats = json.loads((gt / index["materials"]).read_text())
        glb = trimesh.load(gt / index["glb"], file_type="glb", force="scene", process=False)
        world_from_glb = np.asarray(index["glb_from_world"], np.float64)[:3, :3].T
        nodes = []
        for spec in mats["nodes"]:
            mesh = glb.geometry[spec["name"]]
            vertices = (np.asarray(mesh.vertices, np.float64) @ world_from_glb.T).astype(np.float32)
            faces = np.asarray(mesh.faces, np.int64)
            if len(faces) != spec["n_faces"]:
                raise ValueError(f"glb node {spec['name']} has {len(faces)} faces but materials.json says {spec['n_faces']}")
            nodes.append(Node(name=spec["name"], object=spec["object"], kind=spec["kind"], room=spec["room"],
                              material=spec["material"], vertices=vertices, faces=faces))
        tracks = []
        for entry in index["tracks"]:
            t = json.loads((gt / entry["poses"]).read_text())
            tracks.append(Track(world_from_cam=np.asarray(t["world_from_cam"], np.float64),
                                camera_height=float(t["camera_height_m"])))
        with np.load(gt / index["floorplan"]["path"]) as fp:
            floorplan = {k: fp[k] for k in fp.files}
        meta = _meta_from_index(index)
        return cls(
            nodes=nodes,
            materials={k: Material.from_json(v) for k, v in mats["materials"].items()},
            lights=[Light(position=tuple(L["position"]), intensity=tuple(L["intensity"]), falloff=L["falloff"])
                    for L in mats["lights"]],
            ambient=float(mats["ambient"]),
            tracks=tracks,
            clearance=float(index["clearance_m"]),
            meta=meta,
            floorplan=floorplan,
        )


def _meta_from_index(index: dict) -> dict:
    tr0 = index["tracks"][0]
    fp = index["floorplan"]
    return {
        "seed": index["seed"], "scene_seed": index["scene_seed"], "attempt": index["attempt"],
        "preset": index["preset"], "params": index["params"], "fps": tr0["fps"], "step_m": tr0["step_m"],
        "ceiling_height_m": index["ceiling_height_m"], "door_height_m": index["door_height_m"],
        "cell_m": fp["cell_m"], "origin_x": fp["origin_x"], "origin_z": fp["origin_z"], "n_rooms": index["n_rooms"],
    }


def _write_json(path: Path, obj, indent: int | None = 1) -> None:
    path.write_text(json.dumps(obj, indent=indent, sort_keys=True) + "\n")


def _tum_text(poses: np.ndarray, fps: float) -> str:
    q = quat_xyzw_from_wxyz(quat_wxyz_from_rotmat(poses[:, :3, :3]))
    t = poses[:, :3, 3]
    lines = ["# timestamp tx ty tz qx qy qz qw (world_from_cam, OpenCV camera axes, metres)"]
    for k in range(len(poses)):
        vals = [k / fps, *t[k], *q[k]]
        lines.append(" ".join(f"{v:.9f}" for v in vals))
    return "\n".join(lines) + "\n"


# -------------------------------------------------------------------- generation
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


def write_scene(scene: SynthScene, out_dir: str | os.PathLike, params: SynthParams, *, progress: bool = True) -> Path:
    """Render and write a scene directory atomically (temporary sibling directory renamed into place); returns it."""
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"{out} already exists and is not an empty directory; refusing to overwrite it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        (tmp / "gt").mkdir(parents=True)
        rp = params.render
        h = rp.pano_height
        rgb, depth, rig_mask = render_with_rig(scene, rp.rig, h, supersample=rp.supersample)
        cv2.imwrite(str(tmp / "panorama.png"), rgb[..., ::-1])
        np.save(tmp / "depth.npy", depth)
        pano_rel = {"rgb": "../panorama.png", "depth": "../depth.npy", "height": h, "width": 2 * h,
                    "track": 0, "frame": 0, "supersample": rp.supersample, "rig": str(rp.rig)}
        if rp.rig != RigKind.NONE:
            clean_rgb, clean_depth = scene.render(scene.world_from_canonical, h, 2 * h, supersample=rp.supersample)
            cv2.imwrite(str(tmp / "gt" / "panorama_clean.png"), clean_rgb[..., ::-1])
            np.save(tmp / "gt" / "depth_clean.npy", clean_depth)
            cv2.imwrite(str(tmp / "gt" / "rig_mask.png"), rig_mask.astype(np.uint8) * 255)
            pano_rel.update(rgb_clean="panorama_clean.png", depth_clean="depth_clean.npy", rig_mask="rig_mask.png")
        frames_rel = None
        if rp.write_frames:
            frames_rel = []
            total = sum(len(t.world_from_cam) for t in scene.tracks)
            bar = tqdm(total=total, desc=f"render {out.name}", disable=not progress, leave=False)
            for k, tr in enumerate(scene.tracks):
                fdir = tmp / "gt" / "frames" / f"track_{k:02d}"
                (fdir / "rgb").mkdir(parents=True)
                (fdir / "depth").mkdir()
                for i in range(len(tr.world_from_cam)):
                    rgb_i, depth_i = scene.render_frame(k, i, rp.frame_height, supersample=rp.supersample)
                    cv2.imwrite(str(fdir / "rgb" / f"{i:06d}.png"), rgb_i[..., ::-1])
                    np.save(fdir / "depth" / f"{i:06d}.npy", depth_i)
                    bar.update()
                frames_rel.append({"rgb": f"frames/track_{k:02d}/rgb/{{:06d}}.png",
                                   "depth": f"frames/track_{k:02d}/depth/{{:06d}}.npy",
                                   "height": rp.frame_height, "width": 2 * rp.frame_height})
            bar.close()
        scene.save_gt(tmp / "gt", pano_rel=pano_rel, frames_rel=frames_rel)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
