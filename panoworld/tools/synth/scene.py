"""SynthScene: exact ERP rendering (RGB + metric ray depth) and the on-disk ground-truth format."""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import trimesh

from panoworld.core.conventions import (
    GLTF_FROM_WORLD,
    check_erp_shape,
    check_pose,
    erp_dirs,
    pinhole_dirs,
    quat_wxyz_from_rotmat,
    quat_xyzw_from_wxyz,
)
from panoworld.geometry.raycast import Raycaster
from panoworld.tools.synth.appearance import Light, Material, MaterialKind, albedo, srgb_uint8
from panoworld.tools.synth.tracks import Track

GT_FORMAT = "panoworld-synth-gt"
GT_VERSION = 1


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
