"""Triangle mesh of an ERP depth map (seam closed, pole fans, depth discontinuities flagged) and its PLY/glTF I/O."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.core.conventions import GLTF_FROM_WORLD, check_erp_shape, erp_dirs, transform_points
from panoworld.core.shapes import check_shape

MESH_FILE = "mesh.ply"


@dataclass
class ErpMesh:
    """Grid mesh of an ERP depth map in the canonical frame (view 0), metres.

    Vertex layout: vertex i * w + j is grid pixel (i, j) of the (possibly strided) h x w grid, vertex h * w is the
    top pole (up, -Y) and h * w + 1 the bottom pole. Vertices of invalid pixels sit at the origin, unreferenced
    (in memory only: save_erp_mesh writes the referenced vertices alone).
    Faces face the camera (counter-clockwise seen from the origin).
    """

    vertices: np.ndarray  # (V, 3) float32, canonical frame (view 0), metres
    faces: np.ndarray  # (F, 3) int32
    colors: np.ndarray  # (V, 3) uint8 RGB
    face_valid: np.ndarray  # (F,) bool: False = stretched triangle across a depth discontinuity (kept only as an occluder)

    def __post_init__(self):
        dims = check_shape("vertices", self.vertices, "V 3")
        check_shape("faces", self.faces, "F 3", dims=dims)
        check_shape("colors", self.colors, "V 3", dims=dims)
        check_shape("face_valid", self.face_valid, "F", dims=dims)

    def valid_only(self) -> ErpMesh:
        """The same vertices with only the valid (non-stretched) faces."""
        keep = self.face_valid
        return ErpMesh(self.vertices, self.faces[keep], self.colors, np.ones(int(keep.sum()), bool))


def grid_faces(h: int, w: int) -> np.ndarray:
    """Two triangles per grid quad, the last column joined to the first, shape (2 * (h - 1) * w, 3)."""
    i, j = np.meshgrid(np.arange(h - 1), np.arange(w), indexing="ij")
    j1 = (j + 1) % w
    a, b, c, d = i * w + j, (i + 1) * w + j, (i + 1) * w + j1, i * w + j1
    # (a, b, c) and (a, c, d) run counter-clockwise as seen from the camera (image x right, y down).
    return np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], axis=2).reshape(-1, 3)


def _pole_faces(h: int, w: int) -> np.ndarray:
    """Fans joining the first row to the top pole and the last row to the bottom pole, shape (2 * w, 3)."""
    j = np.arange(w)
    j1 = (j + 1) % w
    top = np.stack([np.full(w, h * w), j, j1], -1)
    last = (h - 1) * w
    bottom = np.stack([np.full(w, h * w + 1), last + j1, last + j], -1)
    return np.concatenate([top, bottom])


def erp_mesh_from_depth(
    depth: np.ndarray,
    rgb: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    max_edge_ratio: float = 12.0,
    stride: int = 1,
) -> ErpMesh:
    """ERP depth (H, W) float32 metres + rgb (H, W, 3) uint8 [+ valid (H, W) bool] -> ErpMesh.

    Vertices are exactly `points_from_depth(depth)` at the grid pixels; with `stride` s > 1 only pixels
    (s * i + s // 2, s * j + s // 2) become vertices (exact points, a coarser grid) and their colour is the mean
    of their s x s block. Pixels with depth <= 0, NaN or inf (or valid False) make no faces.
    A face is flagged invalid (a stretched occluder across a depth discontinuity) when one of its edges is longer
    than `max_edge_ratio` times that edge's pixel footprint at its nearer end (nearer depth x angle between the
    two rays): a surface seen at grazing angle alpha stretches by about 1 / sin(alpha), so 12 flags surfaces
    seen at under ~5 degrees, whatever the resolution.
    """
    depth = np.asarray(depth)
    dims = check_shape("depth", depth, "H W")
    H, W = depth.shape
    check_erp_shape(H, W, "depth")
    check_shape("rgb", rgb, "H W 3", dims=dims)
    if valid is not None:
        check_shape("valid", valid, "H W", dims=dims)
    if stride < 1 or H // stride < 2:
        raise ValueError(f"{stride=} must be >= 1 and leave at least 2 grid rows of {H}")

    rows = np.arange(stride // 2, H, stride)
    cols = np.arange(stride // 2, W, stride)
    h, w = len(rows), len(cols)
    d = depth[np.ix_(rows, cols)].astype(np.float32)
    ok = np.isfinite(d) & (d > 0)
    if valid is not None:
        ok &= valid[np.ix_(rows, cols)].astype(bool)
    d = np.where(ok, d, 0.0).astype(np.float32)
    dirs = erp_dirs(H, W, dtype=np.float32)[np.ix_(rows, cols)]
    pts = dirs * d[..., None]
    if stride == 1:
        col = rgb
    else:
        hb, wb = H // stride, W // stride
        col = rgb[: hb * stride, : wb * stride].reshape(hb, stride, wb, stride, 3).mean(axis=(1, 3))
        col = np.pad(col, ((0, h - hb), (0, w - wb), (0, 0)), mode="edge")
    col = np.asarray(np.rint(col), dtype=np.uint8).reshape(-1, 3)

    # Pole vertices: straight up / down at the median height of the first / last row (exact for a flat ceiling).
    poles = np.zeros((2, 3), np.float32)
    pole_ok = np.zeros(2, bool)
    pole_col = np.zeros((2, 3), np.uint8)
    for k, r in enumerate((0, h - 1)):
        m = ok[r]
        if m.any():
            poles[k, 1] = np.median(pts[r, m, 1])
            pole_ok[k] = True
            pole_col[k] = np.rint(col.reshape(h, w, 3)[r, m].mean(axis=0))
    pole_ok &= np.sign(poles[:, 1]) == np.array([-1.0, 1.0])
    vertices = np.concatenate([pts.reshape(-1, 3), np.where(pole_ok[:, None], poles, 0.0)]).astype(np.float32)
    v_depth = np.concatenate([d.reshape(-1), np.abs(poles[:, 1]) * pole_ok]).astype(np.float32)
    v_ok = np.concatenate([ok.reshape(-1), pole_ok])
    colors = np.concatenate([col, pole_col])

    faces = np.concatenate([grid_faces(h, w), _pole_faces(h, w)]).astype(np.int32)
    keep = v_ok[faces].all(axis=1)
    stretch = _grid_face_stretch(pts, dirs, d, vertices[-2:], v_depth[-2:])[keep]
    faces = faces[keep]
    return ErpMesh(vertices, faces, colors, stretch <= max_edge_ratio)


def face_stretch(vertices: np.ndarray, dirs: np.ndarray, depth: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Reference stretch of faces (F, 3): the largest ratio over their edges of edge length to the edge's pixel
    footprint at its nearer end (nearer depth x chord between the two unit rays). vertices (V, 3), their unit ray
    directions dirs (V, 3) and depths (V,) -> (F,) float32."""
    stretch = np.zeros(len(faces), np.float32)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        va, vb = faces[:, a], faces[:, b]
        length = np.linalg.norm(vertices[va] - vertices[vb], axis=1)
        chord = np.linalg.norm(dirs[va] - dirs[vb], axis=1)
        near = np.minimum(depth[va], depth[vb])
        np.maximum(stretch, length / np.maximum(near * chord, 1e-12), out=stretch)
    return stretch


def _edge_stretch(pa, pb, chord, da, db) -> np.ndarray:
    diff = pa - pb
    length = np.sqrt(np.einsum("...k,...k->...", diff, diff))
    return length / np.maximum(np.minimum(da, db) * chord, 1e-12)


def _grid_face_stretch(pts: np.ndarray, dirs: np.ndarray, d: np.ndarray, poles: np.ndarray, pole_d: np.ndarray) -> np.ndarray:
    """face_stretch of all grid and pole faces in grid_faces/_pole_faces order, computed once per grid edge.

    pts, dirs (h, w, 3), d (h, w); poles (2, 3) and their depths pole_d (2,) -> (2 * (h - 1) * w + 2 * w,)."""
    h, w = d.shape
    nxt = lambda a: np.roll(a, -1, axis=1)  # (column j + 1, seam wrapped)
    # Chords between rays depend on the rows only (the grid is symmetric in longitude): take them from column 0.
    c0, c1 = dirs[:, 0], dirs[:, 1 % w]
    chord_h = np.linalg.norm(c0 - c1, axis=-1)[:, None]
    chord_v = np.linalg.norm(c0[:-1] - c0[1:], axis=-1)[:, None]
    chord_d = np.linalg.norm(c0[:-1] - c1[1:], axis=-1)[:, None]
    horiz = _edge_stretch(pts, nxt(pts), chord_h, d, nxt(d))  # (i, j)-(i, j+1)
    vert = _edge_stretch(pts[:-1], pts[1:], chord_v, d[:-1], d[1:])  # (i, j)-(i+1, j)
    diag = _edge_stretch(pts[:-1], nxt(pts[1:]), chord_d, d[:-1], nxt(d[1:]))  # (i, j)-(i+1, j+1)
    tri_a = np.maximum(np.maximum(vert, horiz[1:]), diag)
    tri_b = np.maximum(np.maximum(diag, nxt(vert)), horiz[:-1])
    pole_dirs = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]], np.float32)
    fans = []
    for k, r in enumerate((0, h - 1)):
        spoke = _edge_stretch(poles[k], pts[r], np.linalg.norm(pole_dirs[k] - c0[r]), pole_d[k], d[r])
        fans.append(np.maximum(np.maximum(spoke, nxt(spoke[None])[0]), horiz[r]))
    return np.concatenate([np.stack([tri_a, tri_b], axis=-1).reshape(-1), *fans]).astype(np.float32)


GRID_COMMENT = "erp_vertices"
"""PLY header comment `erp_vertices N`: the vertices written are a subset of an N-vertex ErpMesh, each with its
index in the property `pixel`."""


def compact_faces(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """(used, new_faces): the vertex indices faces (F, 3) reference, ascending, and the faces re-indexed into them;
    np.unique(faces, return_inverse=True) by a mark and a prefix sum (O(V + F), not a sort or hash of 3F indices)."""
    mark = np.zeros(num_vertices, bool)
    mark[faces.ravel()] = True
    used = np.flatnonzero(mark)
    rank = np.cumsum(mark, dtype=np.int64) - 1
    return used, rank[faces].astype(np.intp, copy=False)


QUADS_COMMENT = "face_quads"
"""PLY header comment `face_quads ...`: every face is a quad (a, b, c, d) standing for the mesh's consecutive
triangles (a, b, c), (a, c, d) of one `valid`, or (a, b, c, c) for a lone triangle (a, b, c); readers split a quad
the usual way, into (a, b, c) and (a, c, d), the second one empty for a lone triangle."""


def quad_pairs(faces: np.ndarray, face_valid: np.ndarray) -> np.ndarray:
    """(F,) bool: face k starts a quad with face k + 1, i.e. they are (a, b, c), (a, c, d) with d != c and one
    validity; in a run of such links every other face starts one (a fan (p, 0, 1), (p, 1, 2), (p, 2, 3), (p, 3, 4)
    gives the quads (p, 0, 1, 2) and (p, 2, 3, 4))."""
    F = len(faces)
    link = np.zeros(F, bool)
    if F > 1:
        link[:-1] = ((faces[:-1, 0] == faces[1:, 0]) & (faces[:-1, 2] == faces[1:, 1]) & (faces[1:, 2] != faces[1:, 1])
                     & (face_valid[:-1] == face_valid[1:]))
    idx = np.arange(F)
    run_start = np.maximum.accumulate(np.where(link, 0, idx + 1))  # the first face of the run of links holding k
    return link & ((idx - run_start) % 2 == 0)


def quads_from_triangles(faces: np.ndarray, face_valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(quads (Q, 4), valid (Q,)) of triangles (F, 3) in order: pairs as quad_pairs, lone triangles as (a, b, c, c)."""
    start = quad_pairs(faces, face_valid)
    lone = np.ones(len(faces), bool)
    lone[1:] = ~start[:-1]  # not the second triangle of a quad
    keep = np.flatnonzero(lone)
    quads = np.concatenate([faces[keep], faces[keep, 2:]], axis=1)
    paired = start[keep]
    quads[paired, 3] = faces[keep[paired] + 1, 2]
    return quads, face_valid[keep]


def triangles_from_quads(quads: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of quads_from_triangles: (faces (F, 3), face_valid (F,)) in the quads' order."""
    both = np.stack([quads[:, :3], quads[:, [0, 2, 3]]], axis=1).reshape(-1, 3)
    keep = np.ones((len(quads), 2), bool)
    keep[:, 1] = quads[:, 3] != quads[:, 2]
    keep = keep.reshape(-1)
    return both[keep], np.repeat(valid, 2)[keep]


def save_erp_mesh(mesh: ErpMesh, path: Path) -> None:
    """Binary little-endian PLY: vertex x, y, z float32 + red, green, blue uint8 (+ pixel int32); face vertex_indices
    (quads, see QUADS_COMMENT: a grid cell's two triangles in 18 bytes instead of 28) + uint8 valid.

    Only vertices that a face references are written (invalid pixels never reach the file); when some are left out,
    `pixel` is each written one's index in the ErpMesh layout (grid pixel i * w + j, then the two poles), so
    load_erp_mesh restores the layout; when none are, the file's vertex order is the layout and `pixel` is omitted.
    plyfile writes the header; the bodies go out as numpy records (plyfile writes list properties row by row,
    about 15 s for 2M faces).
    """
    from plyfile import PlyData, PlyElement

    used, faces = compact_faces(mesh.faces, len(mesh.vertices))
    subset = len(used) < len(mesh.vertices)
    v = np.empty(len(used), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                                   ("blue", "u1")] + ([("pixel", "<i4")] if subset else []))
    for k, name in enumerate("xyz"):
        v[name] = mesh.vertices[used, k]
    for k, name in enumerate(("red", "green", "blue")):
        v[name] = mesh.colors[used, k]
    if subset:
        v["pixel"] = used
    quads, valid = quads_from_triangles(faces, np.asarray(mesh.face_valid, bool))
    f = np.empty(len(quads), dtype=[("n", "u1"), ("vertex_indices", "<i4", (4,)), ("valid", "u1")])
    f["n"] = 4
    f["vertex_indices"] = quads
    f["valid"] = valid
    face_desc = np.empty(0, dtype=[("vertex_indices", "O"), ("valid", "u1")])
    header = PlyData(
        [PlyElement.describe(v, "vertex"),
         PlyElement.describe(face_desc, "face", len_types={"vertex_indices": "u1"}, val_types={"vertex_indices": "i4"})],
        text=False, byte_order="<",
        comments=["PanoWorld ERP mesh: canonical frame (view 0, OpenCV axes, up = -Y), metres",
                  "face valid = 0: stretched across a depth discontinuity, an occluder only",
                  f"{QUADS_COMMENT}: quad (a, b, c, d) = triangles (a, b, c), (a, c, d); d = c: one triangle"]
        + ([f"{GRID_COMMENT} {len(mesh.vertices)}"] if subset else []),
    ).header.replace("element face 0", f"element face {len(f)}")
    with open(path, "wb") as fh:
        fh.write((header + "\n").encode("ascii"))
        v.tofile(fh)
        f.tofile(fh)


def load_erp_mesh(path_or_artifact_dir: Path) -> ErpMesh:
    """Read a mesh artifact directory (its mesh.ply) or a .ply path written by save_erp_mesh.

    A file with the `erp_vertices N` comment and vertex property `pixel` is expanded back to the N-vertex ErpMesh
    layout (unwritten vertices at the origin, unreferenced); quads (comment `face_quads`) are split back into the
    mesh's triangles. Any triangle-mesh PLY loads too: without the face property `valid` every face is valid; no
    colours -> grey.
    """
    from plyfile import PlyData, PlyParseError

    path = Path(path_or_artifact_dir)
    if path.is_dir():
        path = path / MESH_FILE
    try:  # fast, memory-mapped paths for triangle or quad lists
        ply = PlyData.read(str(path), known_list_len={"face": {"vertex_indices": 3}})
    except (PlyParseError, ValueError):
        try:
            ply = PlyData.read(str(path), known_list_len={"face": {"vertex_indices": 4}})
        except (PlyParseError, ValueError):
            ply = None
    quads = ply is not None and any(c.startswith(QUADS_COMMENT) for c in ply.comments)
    if ply is None or (ply["face"].data["vertex_indices"].shape[1:] == (4,) and not quads):
        ply = PlyData.read(str(path), mmap=False)
        idx = ply["face"].data["vertex_indices"]
        if any(len(a) != 3 for a in idx):
            raise ValueError(f"{path}: only triangle faces (or save_erp_mesh's quads) are supported") from None
        faces = np.stack(idx).astype(np.int32).reshape(-1, 3)
    else:
        faces = np.array(ply["face"].data["vertex_indices"], np.int32)  # a copy, not a map
    f = ply["face"].data
    face_valid = np.asarray(f["valid"]).astype(bool) if "valid" in f.dtype.names else np.ones(len(faces), bool)
    if quads:
        faces, face_valid = triangles_from_quads(faces, face_valid)
    faces = faces.reshape(-1, 3)
    v, comments = ply["vertex"].data, ply.comments
    vertices = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    names = v.dtype.names
    if all(c in names for c in ("red", "green", "blue")):
        colors = np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.uint8)
    else:
        colors = np.full((len(vertices), 3), 128, np.uint8)
    n_layout = next((int(c.split()[1]) for c in comments if c.startswith(GRID_COMMENT + " ")), None)
    if n_layout is not None and "pixel" in names:
        pixel = np.asarray(v["pixel"], np.int64)
        if len(pixel) and (pixel.min() < 0 or pixel.max() >= n_layout):
            raise ValueError(f"{path}: vertex property pixel outside 0..{n_layout - 1}")
        full_v = np.zeros((n_layout, 3), np.float32)
        full_c = np.zeros((n_layout, 3), np.uint8)
        full_v[pixel], full_c[pixel] = vertices, colors
        vertices, colors, faces = full_v, full_c, pixel[faces].astype(np.int32)
    return ErpMesh(vertices, faces, colors, face_valid)


def save_erp_mesh_glb(mesh: ErpMesh, path: Path) -> None:
    """glTF binary of the valid faces with vertex colours, in glTF's Y-up frame (conventions.GLTF_FROM_WORLD)."""
    import trimesh

    valid = mesh.valid_only()
    tm = trimesh.Trimesh(
        transform_points(GLTF_FROM_WORLD, valid.vertices.astype(np.float64)),
        valid.faces,
        vertex_colors=np.concatenate([valid.colors, np.full((len(valid.colors), 1), 255, np.uint8)], axis=1),
        process=False,
    )
    tm.remove_unreferenced_vertices()
    tm.export(str(path), file_type="glb")
