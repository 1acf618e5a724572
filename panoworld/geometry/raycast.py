"""Exact ray casting against triangle meshes with Embree (embreex): the ground-truth and reference renderer."""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from panoworld.core.conventions import check_erp_shape, check_pose, erp_dirs
from panoworld.core.shapes import check_shape

PARALLEL_MIN_RAYS = 1 << 14
"""Raycaster.cast splits at least this many rays over two threads (embreex releases the GIL while it traces)."""

_pool: tuple[int, ThreadPoolExecutor] | None = None  # (the pid that started it, the pool)
_pool_lock = threading.Lock()


def _helper() -> ThreadPoolExecutor | None:
    """One shared helper thread for casts on machines with more than one core (None on one core); a forked child
    starts its own (the parent's thread does not exist there)."""
    global _pool
    if (os.cpu_count() or 1) < 2:
        return None
    with _pool_lock:
        if _pool is None or _pool[0] != os.getpid():
            _pool = (os.getpid(), ThreadPoolExecutor(max_workers=1, thread_name_prefix="raycast"))
        return _pool[1]


@dataclass
class Hits:
    """Per-ray results. distance is inf and face is -1 where nothing was hit."""

    distance: np.ndarray  # (N,) float32, metres along the unit ray
    face: np.ndarray  # (N,) int64
    bary: np.ndarray  # (N, 3) float32 barycentric weights of the face's three vertices


class Raycaster:
    """Embree BVH over a triangle mesh (vertices (V, 3), faces (F, 3)); the BVH is built once, lazily."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        vertices = np.asarray(vertices)
        faces = np.asarray(faces)
        check_shape("vertices", vertices, "V 3")
        check_shape("faces", faces, "F 3")
        if len(faces) == 0:
            raise ValueError("cannot ray cast an empty mesh (0 faces)")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError(f"faces index vertices 0..{len(vertices) - 1} but range over {faces.min()}..{faces.max()}")
        self.vertices = vertices.astype(np.float32)
        self.faces = faces.astype(np.int32)
        self._scene = None

    def _ensure(self):
        if self._scene is None:
            try:
                from embreex import rtcore_scene
                from embreex.mesh_construction import TriangleMesh
            except ImportError as e:  # pragma: no cover - embreex is a core dependency
                raise ImportError("embreex is required for ray casting: pip install embreex") from e
            self._scene = rtcore_scene.EmbreeScene()
            # Indexed (shared vertices) rather than a (F, 3, 3) soup: the same triangles and hits, ~1 CPU-s less per
            # 2.7M-face build.
            TriangleMesh(self._scene, self.vertices, self.faces)
        return self._scene

    def build(self) -> Raycaster:
        """Build the BVH now rather than at the first cast; returns self."""
        scene = self._ensure()
        if not scene.is_committed:  # embreex commits the scene (builds the BVH) at its first query
            scene.run(np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32))
        return self

    def cast(self, origins: np.ndarray, dirs: np.ndarray, chunk: int = 1 << 20) -> Hits:
        """Cast rays origins (N, 3) + t * dirs (N, 3); dirs must be unit length for metric distances.

        From PARALLEL_MIN_RAYS rays on, the second half is traced by a helper thread (each ray's result is the same)."""
        origins = np.ascontiguousarray(np.broadcast_to(origins, dirs.shape), dtype=np.float32)
        dirs = np.ascontiguousarray(dirs, dtype=np.float32)
        n = len(dirs)
        hits = Hits(np.full(n, np.inf, np.float32), np.full(n, -1, np.int64), np.zeros((n, 3), np.float32))
        pool = _helper() if n >= PARALLEL_MIN_RAYS else None
        if pool is None:
            self._cast_into(hits, origins, dirs, 0, n, chunk)
            return hits
        self.build()  # committed before two threads trace it
        half = n // 2
        job = pool.submit(self._cast_into, hits, origins, dirs, half, n, chunk)
        try:
            self._cast_into(hits, origins, dirs, 0, half, chunk)
        finally:
            job.result()
        return hits

    def _cast_into(self, hits: Hits, origins: np.ndarray, dirs: np.ndarray, start: int, stop: int, chunk: int) -> None:
        """Trace rays start:stop into hits (distance inf / face -1 / bary 0 already where nothing is hit)."""
        scene = self._ensure()
        dist, face, bary = hits.distance, hits.face, hits.bary
        for s in range(start, stop, chunk):
            e = min(stop, s + chunk)
            res = scene.run(origins[s:e], dirs[s:e], output=1)
            pid = np.asarray(res["primID"]).astype(np.int64)
            hit = pid >= 0
            t = np.asarray(res["tfar"], np.float32)
            dist[s:e][hit] = t[hit]
            face[s:e][hit] = pid[hit]
            u = np.asarray(res["u"], np.float32)
            v = np.asarray(res["v"], np.float32)
            # Embree's (u, v) weight vertices 1 and 2; vertex 0 gets 1 - u - v.
            bary[s:e, 0] = np.where(hit, 1.0 - u - v, 0.0)
            bary[s:e, 1] = np.where(hit, u, 0.0)
            bary[s:e, 2] = np.where(hit, v, 0.0)

    def render_erp(self, world_from_cam: np.ndarray, height: int, width: int) -> Hits:
        """Cast one ray through every ERP pixel centre from the camera; results reshaped to (H, W[, 3])."""
        check_pose(world_from_cam, "world_from_cam")
        check_erp_shape(height, width)
        d_cam = erp_dirs(height, width, dtype=np.float64).reshape(-1, 3)
        d_world = d_cam @ np.asarray(world_from_cam)[:3, :3].T
        hits = self.cast(np.asarray(world_from_cam)[:3, 3][None, :], d_world)
        return Hits(
            hits.distance.reshape(height, width),
            hits.face.reshape(height, width),
            hits.bary.reshape(height, width, 3),
        )

    def interpolate(self, hits: Hits, vertex_attr: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """Barycentric interpolation of per-vertex attributes (V, C) at the hits -> (..., C)."""
        face = hits.face
        valid = face >= 0
        idx = self.faces[np.where(valid, face, 0)]  # (..., 3)
        # (v0 + v1) + v2: the numbers (and order) of (vertex_attr[idx] * bary[..., None]).sum(axis=-2), ~2x faster
        vals = vertex_attr[idx[..., 0]] * hits.bary[..., 0:1]
        for k in (1, 2):
            vals += vertex_attr[idx[..., k]] * hits.bary[..., k:k + 1]
        return np.where(valid[..., None], vals, fill)
