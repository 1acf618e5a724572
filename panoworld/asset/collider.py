"""The collision mesh: the scene mesh's valid faces, welded, quadric-decimated to a budget grown while it strays."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.core.parallel import cpu_threads
from panoworld.geometry.erp_mesh import ErpMesh, compact_faces

MAX_PASSES = 3
"""Decimation passes at most for the budget alone (max_error_m 0; with the error bound one pass per budget)."""
STALL_MARGIN = 1.25
"""A decimation that strayed while it stalled above its budget (at F faces) tries again with this times F: it could
not get below F without collapsing whole corners, and a budget a little above F it reaches with small errors (one
that reached its budget and strayed tries twice the budget)."""
WELD_M = 0.01
"""Vertices in one cell of this grid (m) are welded before decimation (_weld; 0: none)."""
SURFACE_SAMPLES = 50_000
"""Points surface_error spreads over a decimated collider."""
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
    """faces_in, faces_valid, faces_welded, faces_out, decimated, passes, simplify_s; with the error bound budgets,
    faces, error_m (one each per decimation tried) and own_error_m."""


def _compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The referenced vertices (float64) in their order and the faces (int64) renumbered into them."""
    used, new_faces = compact_faces(np.asarray(faces, np.int64).reshape(-1, 3), len(vertices))
    return np.asarray(vertices, np.float64)[used], new_faces.astype(np.int64, copy=False)


def _face_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) (b - a) x (c - a) of each face (a, b, c), twice its area along its normal: np.cross written out, to the
    bit, in a twentieth of the time."""
    a, b, c = (np.take(vertices, faces[:, k], axis=0) for k in range(3))
    b -= a
    c -= a
    return np.stack([b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1], b[:, 2] * c[:, 0] - b[:, 0] * c[:, 2],
                     b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]], axis=1)


def _drop_degenerate(vertices: np.ndarray, faces: np.ndarray, min_area_m2: float = 1e-12) -> np.ndarray:
    x, y, z = _face_cross(vertices, faces).T
    area2 = np.sqrt(x * x + y * y + z * z)
    distinct = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return faces[distinct & (area2 > 2 * min_area_m2)]


def collision_mesh(mesh: ErpMesh, max_triangles: int, max_error_m: float = 0.0) -> Collider:
    """Valid faces only (the stretched faces across depth edges are no real surface), welded (_weld, WELD_M),
    unreferenced vertices and degenerate faces removed, then decimated with fast-simplification's quadric edge
    collapse to at most `max_triangles` (open borders kept in place, so holes at depth edges do not grow). The budget
    is a target: a mesh with many borders may keep more faces (info["faces_out"]). max_error_m > 0: while the
    decimated surface strays from the mesh (surface_error) by more than the mesh's own surface does (its noise and
    curvature, info["own_error_m"]) plus max_error_m, the mesh is decimated again from the start with STALL_MARGIN
    times the faces a stalled decimation kept (else twice the budget), up to keeping every face (info["budgets"],
    info["faces"], info["error_m"]: each budget tried, the faces it kept, their error)."""
    import time

    v0, f0 = _compact(mesh.vertices, mesh.faces[mesh.face_valid])
    info = {"faces_in": int(len(mesh.faces)), "faces_valid": int(mesh.face_valid.sum()), "decimated": False}
    v0, f0 = _weld(v0, f0, WELD_M)
    f0 = _drop_degenerate(v0, f0)
    v0, f0 = _compact(v0, f0)
    info["faces_welded"] = int(len(f0))
    t0 = time.perf_counter()
    v, f, budget, tree = v0, f0, int(max_triangles), None
    while max_triangles > 0 and len(f0) > budget:
        v, f, passes = _decimate(v0, f0, budget, 1 if max_error_m > 0 else MAX_PASSES)
        info.update(decimated=True, passes=passes)
        if max_error_m <= 0:
            break
        if tree is None:
            from scipy.spatial import cKDTree

            tree = cKDTree(v0, balanced_tree=False, compact_nodes=False)  # built 3x faster, queried as fast
            normals = vertex_normals(v0, f0)
            info["own_error_m"] = round(surface_error(v0, f0, tree, normals), 4)  # its noise and curvature
        err = surface_error(v, f, tree, normals)
        info.setdefault("budgets", []).append(budget)
        info.setdefault("error_m", []).append(round(err, 4))
        info.setdefault("faces", []).append(int(len(f)))
        if err <= info["own_error_m"] + max_error_m:
            break
        budget = int(STALL_MARGIN * len(f)) if len(f) > budget else 2 * budget
        if len(f0) <= budget:  # no decimation left to try: the mesh itself
            v, f = v0, f0
            info.update(decimated=False, passes=0)
    info["simplify_s"] = time.perf_counter() - t0
    info["faces_out"] = int(len(f))
    return Collider(np.asarray(v, np.float64), np.asarray(f, np.int64), info)


def _weld(v: np.ndarray, f: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) in one cell of a cell_m grid merged into their mean (a vertex alone in its cell keeps its exact
    position), faces (F, 3) renumbered, those left with a repeated vertex or repeating another face dropped. The ERP
    mesh's rows near the poles are slivers a fraction of a millimetre wide by millimetres long: quadric decimation
    refuses every collapse among them (each would leave a needle), and without the weld they keep half of a collider's
    budget in the few centimetres below the camera."""
    if cell_m <= 0:
        return v, f
    q = np.floor(v / cell_m).astype(np.int64)
    q -= q.min(axis=0)
    dims = q.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0**62:  # one int64 key per cell
        _, cell = np.unique((q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2], return_inverse=True)
    else:  # a mesh kilometres across
        _, cell = np.unique(q, axis=0, return_inverse=True)
    cell = cell.reshape(-1)
    count = np.bincount(cell)
    if count.max() == 1:
        return v, f
    merged = np.stack([np.bincount(cell, v[:, j]) for j in range(3)], axis=1) / count[:, None]
    f = cell[f]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    moved = (count[f] > 1).any(axis=1)  # only faces at a welded vertex can repeat another
    _, first = np.unique(np.sort(f[moved], axis=1), axis=0, return_index=True)
    keep = ~moved
    keep[np.flatnonzero(moved)[first]] = True
    return merged, f[keep]


def _decimate(v: np.ndarray, f: np.ndarray, budget: int, max_passes: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(vertices, faces, passes) of the quadric edge collapse of (v, f) towards `budget` faces (collision_mesh)."""
    import fast_simplification

    passes = 0
    for _ in range(max_passes):  # one pass stalls short of large reductions; a second one gets most of the rest
        n = len(f)
        v, f = fast_simplification.simplify(v, f.astype(np.int32), target_count=int(budget), preserve_border=True)
        f = _drop_degenerate(np.asarray(v, np.float64), np.asarray(f, np.int64))
        v, f = _compact(v, f)
        passes += 1
        if len(f) <= MORE_PASSES_ABOVE * budget or len(f) > 0.95 * n:
            break
    return v, f, passes


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit normals, the area-weighted sum of the normals of the faces around each vertex (zero where none)."""
    fn = _face_cross(vertices, faces)
    n = np.stack([sum(np.bincount(faces[:, k], fn[:, j], len(vertices)) for k in range(3)) for j in range(3)], 1)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def surface_error(vertices: np.ndarray, faces: np.ndarray, tree, normals: np.ndarray,
                  samples: int = SURFACE_SAMPLES) -> float:
    """How far (m) a decimated surface (vertices (V, 3), faces (F, 3)) strays from the mesh it was decimated from:
    the 99th percentile, over points spread over it by area (a fixed seed), of the distance along the normal to the
    plane of the original's nearest vertex (tree: scipy cKDTree of those vertices, normals: theirs, vertex_normals)."""
    area = np.linalg.norm(_face_cross(vertices, faces), axis=1)
    rng = np.random.default_rng(0)
    pick = faces[rng.choice(len(faces), size=samples, p=area / area.sum())]
    a, b, c = (vertices[pick[:, k]] for k in range(3))
    r1, r2 = np.sqrt(rng.random(samples)), rng.random(samples)
    pts = (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c
    _, k = tree.query(pts, workers=cpu_threads(2))
    off = np.abs(np.einsum("ij,ij->i", pts - tree.data[k], normals[k]))
    return float(np.percentile(off, 99))


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, header: str) -> None:
    """Wavefront OBJ (v / f lines, 1-based) that every physics engine's loader reads; the text trimesh's export_obj
    writes (8 decimals), formatted in one pass without importing trimesh (1.7 s of the asset stage)."""
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    f = np.asarray(faces, np.int64).reshape(-1, 3) + 1
    text = ("v %.8f %.8f %.8f\n" * len(v)) % tuple(v.ravel().tolist())
    text += ("f %d %d %d\n" * len(f)) % tuple(f.ravel().tolist())
    Path(path).write_text(f"# {header}\n{text}\n")
