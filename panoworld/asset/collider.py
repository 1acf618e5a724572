"""The collision mesh: the scene mesh's valid (non-stretched) faces, compacted, quadric-decimated to a budget."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.geometry.erp_mesh import ErpMesh, compact_faces

MAX_PASSES = 3
"""Decimation passes at most (each stops when no edge collapse keeps the quadric error low enough)."""
MORE_PASSES_ABOVE = 1.5
"""Another pass runs only while more than this many times the budget remains: a pass that ends near the budget has
stalled on the borders it keeps, and the next one removes little for much time (on a real capture's mesh of millions
of faces, a second pass removes about 0.1-2 % more of them for 40-75 % more time)."""


@dataclass
class Collider:
    """A static triangle mesh (vertices in some frame, faces counter-clockwise seen from the capture point)."""

    vertices: np.ndarray
    """(V, 3) float64 metres."""
    faces: np.ndarray
    """(F, 3) int64."""
    info: dict
    """faces_in, faces_valid, faces_out, decimated, simplify_s."""


def _compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The referenced vertices (float64) in their order and the faces (int64) renumbered into them."""
    used, new_faces = compact_faces(np.asarray(faces, np.int64).reshape(-1, 3), len(vertices))
    return np.asarray(vertices, np.float64)[used], new_faces.astype(np.int64, copy=False)


def _drop_degenerate(vertices: np.ndarray, faces: np.ndarray, min_area_m2: float = 1e-12) -> np.ndarray:
    a, b, c = (np.take(vertices, faces[:, k], axis=0) for k in range(3))
    b -= a
    c -= a
    # |(b - a) x (c - a)| written out: np.linalg.norm(np.cross(...)) to the bit, in a third of the time
    x = b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1]
    y = b[:, 2] * c[:, 0] - b[:, 0] * c[:, 2]
    z = b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]
    area2 = np.sqrt(x * x + y * y + z * z)
    distinct = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return faces[distinct & (area2 > 2 * min_area_m2)]


def collision_mesh(mesh: ErpMesh, max_triangles: int) -> Collider:
    """Valid faces only (the stretched faces across depth edges are no real surface), unreferenced vertices and
    degenerate faces removed, then decimated with fast-simplification's quadric edge collapse to at most
    `max_triangles` (open borders kept in place, so holes at depth edges do not grow). The budget is a target: a
    mesh with many borders may keep more faces (info["faces_out"])."""
    import time

    import fast_simplification

    v, f = _compact(mesh.vertices, mesh.faces[mesh.face_valid])
    f = _drop_degenerate(v, f)
    v, f = _compact(v, f)
    info = {"faces_in": int(len(mesh.faces)), "faces_valid": int(mesh.face_valid.sum()), "decimated": False}
    t0 = time.perf_counter()
    if max_triangles > 0 and len(f) > max_triangles:
        for _ in range(MAX_PASSES):  # one pass stalls short of large reductions; a second one gets most of the rest
            n = len(f)
            v, f = fast_simplification.simplify(v, f.astype(np.int32), target_count=int(max_triangles),
                                                preserve_border=True)
            f = _drop_degenerate(np.asarray(v, np.float64), np.asarray(f, np.int64))
            v, f = _compact(v, f)
            info["passes"] = info.get("passes", 0) + 1
            if len(f) <= MORE_PASSES_ABOVE * max_triangles or len(f) > 0.95 * n:
                break
        info["decimated"] = True
    info["simplify_s"] = time.perf_counter() - t0
    info["faces_out"] = int(len(f))
    return Collider(np.asarray(v, np.float64), np.asarray(f, np.int64), info)


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, header: str) -> None:
    """Wavefront OBJ (v / f lines, 1-based) that every physics engine's loader reads; the text trimesh's export_obj
    writes (8 decimals), formatted in one pass without importing trimesh (1.7 s of the asset stage)."""
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    f = np.asarray(faces, np.int64).reshape(-1, 3) + 1
    text = ("v %.8f %.8f %.8f\n" * len(v)) % tuple(v.ravel().tolist())
    text += ("f %d %d %d\n" * len(f)) % tuple(f.ravel().tolist())
    Path(path).write_text(f"# {header}\n{text}\n")
