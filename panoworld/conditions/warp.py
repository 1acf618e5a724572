"""Geometry-warped ERP conditions along a trajectory: render every pose from the scene mesh, write PNGs, load them back."""

from __future__ import annotations

import contextlib
import enum
import json
import time
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.core.conventions import check_erp_shape, check_poses, depth_to_mm
from panoworld.core.shapes import check_shape
from panoworld.geometry.erp_mesh import ErpMesh
from panoworld.io.conditions import CONDITIONS_JSON, DEPTH_SCALE, WarpedFrame
from panoworld.io.depth_png import encode_depth_png
from panoworld.io.png import encode_png
from panoworld.io.rgb_image import RgbFormat, encode_rgb, rgb_file_name

PREVIEW_MP4 = "preview.mp4"


class Backend(enum.StrEnum):
    """How condition frames are rendered."""

    RASTER = "raster"
    """Numba ERP triangle rasteriser (exact per-pixel coverage, fast)."""
    RAYCAST = "raycast"
    """Embree ray cast per pixel (the reference; several times slower)."""


SPLIT_MIN_JUMP = 0.05
"""Relative depth jump above which split_stretched_faces cuts an edge between two stretched faces."""


def split_stretched_faces(mesh: ErpMesh, min_jump: float = SPLIT_MIN_JUMP) -> ErpMesh:
    """Split the stretched faces of a depth mesh at their silhouettes: fore- and background extend half a pixel.

    mesh (an ErpMesh in the frame of the camera whose depth built it) has stretched faces (face_valid False)
    spanning depth discontinuities from the last foreground to the first background pixel centre; the true
    silhouette lies between them. Every edge shared by two stretched faces whose end depths differ by more than
    min_jump (relative) is cut at its angular midpoint into a copy at each end's depth; each face becomes valid
    pieces on both sides plus an invalid 'curtain' along the source rays through the midpoints. Seen from the
    source nothing changes; from a novel pose the predicted hole shrinks to the true shadow of the silhouette.
    Both faces at a cut edge cut it identically, so the result stays watertight.
    """
    V = mesh.vertices.astype(np.float64)
    r = np.linalg.norm(V, axis=1)
    inv = np.flatnonzero(~mesh.face_valid)
    if len(inv) == 0:
        return mesh
    F = mesh.faces[inv].astype(np.int64)
    a = F
    b = np.roll(F, -1, axis=1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo * len(V) + hi
    uniq, inverse, counts = np.unique(key.ravel(), return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1, 3)
    ra, rb = r[a], r[b]
    with np.errstate(divide="ignore", invalid="ignore"):
        jump = (np.maximum(ra, rb) / np.minimum(ra, rb) - 1.0) > min_jump
    J = jump & (counts[inverse] == 2) & (np.minimum(ra, rb) > 0)  # cut edges, shape (n, 3)
    eid_all = np.full(len(uniq), -1, np.int64)
    used = np.unique(inverse[J])
    eid_all[used] = np.arange(len(used))
    ue_lo, ue_hi = uniq[used] // len(V), uniq[used] % len(V)
    m = V[ue_lo] / r[ue_lo, None] + V[ue_hi] / r[ue_hi, None]
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    new_v = np.concatenate([m * r[ue_lo, None], m * r[ue_hi, None]])  # copies at the lower / higher end's depth
    new_c = np.concatenate([mesh.colors[ue_lo], mesh.colors[ue_hi]])
    base, ne = len(V), len(used)
    eid = eid_all[inverse]
    Cs = np.where(a == lo, base + eid, base + ne + eid)  # copy on edge k (F[:, k] -> F[:, k + 1]) at its start's depth
    Ce = np.where(b == lo, base + eid, base + ne + eid)  # ... at its end's depth
    nj = J.sum(1)
    # Triangulate each face by its number of cut edges, in rim order (vertex, its cut copies, next vertex...).
    valid_out, invalid_out = [], []
    for k in range(3):
        k1, k2 = (k + 1) % 3, (k + 2) % 3
        V0, V1, V2 = F[:, k], F[:, k1], F[:, k2]
        s = (nj == 1) & J[:, k]
        valid_out += [np.stack([V0, Cs[:, k], V2], 1)[s], np.stack([Ce[:, k], V1, V2], 1)[s]]
        invalid_out += [np.stack([Cs[:, k], Ce[:, k], V2], 1)[s]]
        s = (nj == 2) & J[:, k] & J[:, k2]  # lone vertex V0 between edges k2 (V2 -> V0) and k (V0 -> V1)
        valid_out += [np.stack([Ce[:, k2], V0, Cs[:, k]], 1)[s], np.stack([Ce[:, k], V1, V2], 1)[s],
                      np.stack([Ce[:, k], V2, Cs[:, k2]], 1)[s]]
        invalid_out += [np.stack([Cs[:, k], Ce[:, k], Cs[:, k2]], 1)[s],
                        np.stack([Cs[:, k], Cs[:, k2], Ce[:, k2]], 1)[s]]
    s = nj == 3
    for k in range(3):
        valid_out.append(np.stack([Ce[:, (k + 2) % 3], F[:, k], Cs[:, k]], 1)[s])
    h = [Cs[:, 0], Ce[:, 0], Cs[:, 1], Ce[:, 1], Cs[:, 2], Ce[:, 2]]
    for k in range(1, 5):
        invalid_out.append(np.stack([h[0], h[k], h[k + 1]], 1)[s])
    keep = np.ones(len(mesh.faces), bool)
    keep[inv[nj > 0]] = False
    vo, io = np.concatenate(valid_out), np.concatenate(invalid_out)
    faces = np.concatenate([mesh.faces[keep], vo, io]).astype(np.int32)
    valid = np.concatenate([mesh.face_valid[keep], np.ones(len(vo), bool), np.zeros(len(io), bool)])
    return ErpMesh(np.concatenate([mesh.vertices, new_v.astype(np.float32)]), faces,
                   np.concatenate([mesh.colors, new_c]), valid)


def make_renderer(mesh, backend: Backend | str = Backend.RASTER):
    """ErpRasterizer or RaycastRenderer of an ErpMesh-like object (vertices, faces, colors, face_valid)."""
    from panoworld.render.rasterize import ErpRasterizer, RaycastRenderer  # numba: imported when a renderer is made

    cls = {Backend.RASTER: ErpRasterizer, Backend.RAYCAST: RaycastRenderer}[Backend(backend)]
    return cls(mesh.vertices, mesh.faces, mesh.colors, mesh.face_valid)


def iter_conditions(
    mesh: ErpMesh,
    poses: np.ndarray,
    height: int,
    width: int,
    *,
    backend: Backend | str = Backend.RASTER,
    split_silhouettes: bool = True,
    progress: bool = False,
) -> Iterator[WarpedFrame]:
    """Render poses (N, 4, 4) world_from_cam (mesh frame) one by one -> WarpedFrame per pose (fresh arrays each).

    split_silhouettes: render split_stretched_faces(mesh) (tighter disocclusion masks) instead of mesh itself.
    Arguments are checked before the first frame is rendered (ValueError), so a bad call produces nothing.
    """
    poses = check_poses(poses)
    check_erp_shape(height, width, "conditions size")
    renderer = make_renderer(split_stretched_faces(mesh) if split_silhouettes else mesh, backend)
    return _iter_frames(renderer, poses, height, width, progress)


def _iter_frames(renderer, poses, height, width, progress) -> Iterator[WarpedFrame]:
    from panoworld.core.progress import bar

    for pose in bar(poses, desc="conditions", unit="frame", on=progress):
        yield renderer.render(pose, height, width)


def render_conditions(mesh: ErpMesh, poses: np.ndarray, height: int, width: int, **options) -> list[WarpedFrame]:
    """All condition frames of poses (N, 4, 4) world_from_cam in the mesh's frame (options as iter_conditions)."""
    return list(iter_conditions(mesh, poses, height, width, **options))


# ---------------------------------------------------------------------------------------------- ground truth


class MeshReference:
    """An exact mesh as the reference of true_disocclusion: depth renders and ray casts, poses in the mesh's frame."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        from panoworld.geometry.raycast import Raycaster

        self.raycaster = Raycaster(vertices, faces)

    def depth(self, pose: np.ndarray, height: int, width: int) -> np.ndarray:
        """Exact ERP ray distance (H, W) at world_from_cam pose (inf = no surface)."""
        return self.raycaster.render_erp(pose, height, width).distance

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance (N,) along unit rays origins (N | 1, 3) + t dirs (N, 3) to the first surface (inf = none)."""
        return self.raycaster.cast(origins, dirs).distance


def true_disocclusion(
    reference, source_pose: np.ndarray, pose: np.ndarray, height: int, width: int, tol: float = 0.02
) -> np.ndarray:
    """(H, W) bool: pixels of the view at `pose` whose ground-truth surface point the camera at `source_pose` does not
    see (something lies nearer than (1 - tol) x its distance along the source ray), or where there is no surface.

    reference: exact geometry with depth(pose, H, W) -> (H, W) ray distances (inf = none) and cast(origins, dirs) ->
    (N,) distances, e.g. MeshReference or the evaluation's GroundTruth; poses are world_from_cam (4, 4) in its frame.
    This is the projection test 'project the point into the source ERP, compare with the source depth' with the
    source depth taken exactly along the point's own ray (a ray cast), so it has no source-resolution error.
    """
    from panoworld.core.conventions import points_from_depth

    check_erp_shape(height, width, "true_disocclusion size")
    depth = reference.depth(pose, height, width)
    hole = ~(np.isfinite(depth) & (depth > 0))
    pts = points_from_depth(np.where(hole, 1.0, depth), np.asarray(pose, np.float64))[~hole]
    centre = np.asarray(source_pose, np.float64)[:3, 3]
    ray = pts - centre
    dist = np.linalg.norm(ray, axis=1)
    seen = reference.cast(centre[None], ray / np.maximum(dist, 1e-12)[:, None]) >= (1.0 - tol) * dist
    out = hole.copy()
    out[~hole] = ~seen
    return out


@dataclass
class WarpQuality:
    """A warped frame scored against the exact render at its pose."""

    psnr: float
    """PSNR (dB, uint8 range) of warped vs true RGB on pixels the mask marks valid and that are truly visible."""
    iou: float
    """IoU of the 'must be generated' sets: mask == 0 vs true_disocclusion."""
    valid_fraction: float
    """Fraction of pixels with mask == 1."""
    true_hole_fraction: float
    """Fraction of pixels truly disoccluded."""


def warp_quality(frame: WarpedFrame, rgb_true: np.ndarray, disoccluded: np.ndarray) -> WarpQuality:
    """Score a WarpedFrame against the true rgb (H, W, 3) uint8 and true_disocclusion (H, W) at its pose."""
    from panoworld.render.metrics import psnr

    dims = {"H": frame.mask.shape[0], "W": frame.mask.shape[1]}
    check_shape("rgb_true", rgb_true, "H W 3", dims=dims)
    check_shape("disoccluded", disoccluded, "H W", dims=dims)
    hole = ~frame.mask
    union = (hole | disoccluded).sum()
    iou = float((hole & disoccluded).sum() / union) if union else 1.0
    score = psnr(frame.rgb, rgb_true, mask=frame.mask & ~disoccluded)
    return WarpQuality(score, iou, float(frame.mask.mean()), float(disoccluded.mean()))


# ---------------------------------------------------------------------------------------------- storage


def frame_files(k: int, write_depth: bool = True, rgb_format: RgbFormat | str = RgbFormat.PNG) -> dict[str, str]:
    """Relative file names of frame k inside a conditions directory."""
    files = {"rgb": f"rgb/{rgb_file_name(k, rgb_format)}", "mask": f"mask/{k:06d}.png"}
    if write_depth:
        files["depth"] = f"depth/{k:06d}.png"
    return files


def _write_frame(out_dir: Path, files: dict[str, str], frame: WarpedFrame, compression: int, rgb_format: RgbFormat | str,
                 rgb_quality: int) -> None:
    pngs = {"rgb": encode_rgb(frame.rgb, rgb_format, quality=rgb_quality, compression=compression),
            "mask": encode_png(frame.mask.astype(np.uint8) * 255, compression=compression)}
    if "depth" in files:
        pngs["depth"] = encode_depth_png(depth_to_mm(frame.depth))
    for key, data in pngs.items():
        try:
            (out_dir / files[key]).write_bytes(data)
        except OSError as e:
            raise OSError(f"{out_dir}: could not write the images of {files['rgb']}: {e}") from e


def _preview_frame(frame: WarpedFrame, max_height: int) -> np.ndarray:
    """Side-by-side rgb | mask (H', 2W', 3) uint8 at most max_height rows, sizes multiples of 16."""
    import cv2

    h = frame.mask.shape[0]
    scale = min(1.0, max_height / h)
    ph = max(16, round(h * scale / 16) * 16)
    pw = 2 * ph
    rgb = cv2.resize(frame.rgb, (pw, ph), interpolation=cv2.INTER_AREA)
    mask = cv2.resize(frame.mask.astype(np.uint8) * 255, (pw, ph), interpolation=cv2.INTER_AREA)
    return np.concatenate([rgb, np.repeat(mask[..., None], 3, axis=2)], axis=1)


def _append_preview(writer, frame: WarpedFrame, max_height: int) -> None:
    writer.append_data(_preview_frame(frame, max_height))


def write_conditions(
    out_dir: Path,
    frames: Iterable[WarpedFrame],
    poses: np.ndarray,
    *,
    write_depth: bool = True,
    preview_mp4: bool = False,
    preview_fps: float = 16.0,
    preview_height: int = 360,
    workers: int = 2,
    compression: int = 1,
    rgb_format: RgbFormat | str = RgbFormat.PNG,
    rgb_quality: int = 95,
) -> dict:
    """Write frames (one per pose of poses (N, 4, 4)) into out_dir; conditions.json is written last.

    Layout: conditions.json {"height", "width", "num_frames", "depth_scale", "frames": [{"rgb", "mask"[, "depth"]}],
    "poses"}; rgb/%06d.png uint8 RGB (0 where mask is 0; .jpg of rgb_quality with rgb_format jpeg), mask/%06d.png uint8 0/255 (255 = valid geometry seen),
    depth/%06d.png uint16 millimetres (0 = nothing); optional preview.mp4 (rgb | mask side by side, H.264).
    frames may be a lazy iterator: PNG encoding overlaps with rendering in a pool of `workers` threads (0 = encode in
    the calling thread, for callers that parallelise over processes).
    Returns facts for the manifest: sizes, frame count, valid fractions, seconds spent.
    """
    poses = check_poses(poses)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for sub in ("rgb", "mask") + (("depth",) if write_depth else ()):
        (out_dir / sub).mkdir(exist_ok=True)
    writer = None
    if preview_mp4:
        import imageio.v2 as imageio

        from panoworld.io.video_writer import PREVIEW_CRF

        writer = imageio.get_writer(
            str(out_dir / PREVIEW_MP4), fps=preview_fps, codec="libx264", quality=None, macro_block_size=16,
            output_params=["-preset", "veryfast", "-crf", PREVIEW_CRF], ffmpeg_log_level="error",
        )
    entries: list[dict[str, str]] = []
    valid: list[float] = []
    size = None
    t_render = 0.0
    t0 = time.perf_counter()
    pending: deque = deque()
    previews: deque = deque()
    # preview.mp4 frames are resized and piped to ffmpeg by a thread of their own, in order, while the next renders
    preview_pool = ThreadPoolExecutor(max_workers=1) if writer is not None else None
    try:
        with ThreadPoolExecutor(max_workers=workers) if workers > 0 else contextlib.nullcontext() as pool:
            it = iter(frames)
            while True:
                t1 = time.perf_counter()
                frame = next(it, None)
                t_render += time.perf_counter() - t1
                if frame is None:
                    break
                k = len(entries)
                if size is None:
                    size = frame.mask.shape
                    check_erp_shape(*size, "condition frame")
                if frame.mask.shape != size or frame.rgb.shape != (*size, 3) or frame.depth.shape != size:
                    raise ValueError(
                        f"frame {k}: {frame.rgb.shape=}, {frame.mask.shape=}, {frame.depth.shape=} but expected "
                        f"{(*size, 3)}, {size}, {size} like frame 0"
                    )
                files = frame_files(k, write_depth, rgb_format)
                entries.append(files)
                valid.append(float(frame.mask.mean()))
                if pool is None:
                    _write_frame(out_dir, files, frame, compression, rgb_format, rgb_quality)
                else:
                    pending.append(pool.submit(_write_frame, out_dir, files, frame, compression, rgb_format, rgb_quality))
                while len(pending) > 2 * max(1, workers):
                    pending.popleft().result()
                if preview_pool is not None:
                    previews.append(preview_pool.submit(_append_preview, writer, frame, preview_height))
                    while len(previews) > 2:
                        previews.popleft().result()
            while pending:
                pending.popleft().result()
            while previews:
                previews.popleft().result()
    finally:
        if preview_pool is not None:
            preview_pool.shutdown(cancel_futures=True)
        if writer is not None:
            writer.close()
    if len(entries) != len(poses):
        raise ValueError(f"got {len(entries)} frames for {len(poses)} poses; expected one frame per pose")
    if not entries:
        raise ValueError("no frames to write (empty trajectory)")
    height, width = size
    doc = {
        "height": height,
        "width": width,
        "num_frames": len(entries),
        "depth_scale": DEPTH_SCALE,
        "frames": entries,
        "poses": poses.tolist(),
        "mask": "255 = pixel sees valid mesh geometry; 0 = no geometry or a stretched occluder face (to be generated)",
        "convention": "ERP, world_from_cam 4x4 in the mesh's canonical frame, OpenCV camera axes, depth = ray distance",
    }
    (out_dir / CONDITIONS_JSON).write_text(json.dumps(doc))
    return {
        "height": height,
        "width": width,
        "num_frames": len(entries),
        "valid_fraction_mean": float(np.mean(valid)),
        "valid_fraction_min": float(np.min(valid)),
        "render_s": round(t_render, 3),
        "total_s": round(time.perf_counter() - t0, 3),
        "preview": PREVIEW_MP4 if preview_mp4 else None,
    }
