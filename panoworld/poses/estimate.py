"""Per-frame poses of a panoramic video (COLMAP SfM, the planned trajectory, or PanoVGGT) and their COLMAP/nerfstudio exports."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from panoworld.core.conventions import check_poses, cv_world_from_cam_from_gl, gl_world_from_cam, invert_pose
from panoworld.core.errors import InputError
from panoworld.geometry.align import align_trajectory, apply_sim3, trajectory_metrics
from panoworld.io.depth_png import write_depth_png
from panoworld.io.jsonio import to_jsonable, write_json
from panoworld.io.video import DEPTH_SCALE, VideoFrames, load_frames
from panoworld.poses.colmap_sfm import run_colmap
from panoworld.poses.options import Alignment, ColmapOptions, RenderType

MIN_REGISTERED = 3


# ---------------------------------------------------------------- inputs


def read_planned_trajectory(trajectory_dir: Path) -> np.ndarray:
    """world_from_cam (N, 4, 4) of trajectory.json in a trajectory artifact (panoworld.trajectory.load_trajectory)."""
    from panoworld.io.trajectory import TrajectoryFileError, load_trajectory

    try:
        return load_trajectory(trajectory_dir)
    except TrajectoryFileError as e:
        raise InputError(f"{e}; rerun the trajectory stage") from None


# ---------------------------------------------------------------- estimates


@dataclass
class PoseEstimate:
    """Poses of every frame in the canonical frame plus what the backend knows beyond them."""

    world_from_cam: np.ndarray
    """(N, 4, 4) canonical world_from_cam; unregistered frames hold the planned pose."""
    registered: np.ndarray
    """(N,) bool: the backend recovered this frame's pose."""
    backend: str
    alignment: str = "none"
    """How the estimate was put into the canonical frame (an Alignment value, or 'none')."""
    sim3: tuple[float, np.ndarray, np.ndarray] | None = None
    """canonical_from_estimate (s, R, t) applied to the raw estimate, if aligned."""
    raw: np.ndarray | None = None
    """(N, 4, 4) estimates in the backend's own frame (unregistered rows undefined), for metrics."""
    reconstruction: object | None = None
    """pycolmap.Reconstruction in the canonical frame (colmap backend), images named by frame file name."""
    depth: np.ndarray | None = None
    """(N, h, w) depth in metres predicted by the backend, already in canonical units."""
    info: dict = field(default_factory=dict)


def planned_estimate(planned: np.ndarray) -> PoseEstimate:
    """The planned trajectory as the poses (for generators that follow it exactly)."""
    planned = check_poses(planned, "planned")
    return PoseEstimate(planned.copy(), np.ones(len(planned), bool), "planned", raw=planned.copy())


def _alignment(raw: np.ndarray, planned: np.ndarray, reg: np.ndarray, mode: Alignment):
    if mode == Alignment.NONE:
        return None
    # Orientations help where the centres are nearly collinear (straight corridors); exact data is fitted exactly.
    _, sim = align_trajectory(raw[reg], planned[reg], sim3=mode == Alignment.SIM3, rotation_weight=1.0)
    return sim


def _apply(sim, poses: np.ndarray) -> np.ndarray:
    return poses.copy() if sim is None else apply_sim3(*sim, poses)


def colmap_estimate(
    image_paths: list[Path],
    planned: np.ndarray,
    options: ColmapOptions | None = None,
    *,
    alignment: Alignment = Alignment.SIM3,
    verbose: bool = False,
) -> PoseEstimate:
    """COLMAP panorama SfM on the frames with options (render type, matcher, SfM settings; None = the defaults),
    Sim(3)-aligned to the planned trajectory (N, 4, 4).

    The largest model is kept; frames it lacks are unregistered: flagged, with the planned pose filled in.
    Fewer than 3 registered frames (no alignment possible) -> InputError.
    """
    import pycolmap

    options = options or ColmapOptions()
    planned = check_poses(planned, "planned")
    n = len(image_paths)
    if len(planned) != n:
        raise InputError(f"the planned trajectory has {len(planned)} poses but the video has {n} frames")
    if alignment != Alignment.SIM3:
        raise InputError(f"align={alignment}: COLMAP's frame and scale are arbitrary; use --align sim3")
    t0 = time.perf_counter()
    timings: dict = {}
    with tempfile.TemporaryDirectory(prefix="panoworld-colmap-") as tmp:
        rec, recs = run_colmap(image_paths, Path(tmp), options, verbose=verbose, timings=timings)
    sfm_s = time.perf_counter() - t0
    index = {p.name: i for i, p in enumerate(image_paths)}
    raw = np.repeat(np.eye(4)[None], n, axis=0)
    reg = np.zeros(n, bool)
    if rec is not None:
        for img in rec.images.values():
            if img.has_pose:
                i = index[img.name]
                raw[i] = invert_pose(np.vstack([img.cam_from_world().matrix(), [0, 0, 0, 1]]))
                reg[i] = True
    if reg.sum() < MIN_REGISTERED:
        raise InputError(
            f"COLMAP registered {int(reg.sum())} of {n} frames (at least {MIN_REGISTERED} are needed to align them to "
            "the planned trajectory): the frames lack matchable texture or overlap; try --render-type "
            "perspective_overlapping or --matcher exhaustive, or use --backend planned"
        )
    moving = np.linalg.norm(planned[reg, :3, 3] - planned[reg, :3, 3].mean(0), axis=1).max()
    if moving < 1e-6:
        raise InputError("the planned trajectory does not move, so COLMAP's scale cannot be fixed; use --backend planned")
    sim = _alignment(raw, planned, reg, alignment)
    poses = np.where(reg[:, None, None], _apply(sim, raw), planned)
    s, R, t = sim
    rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t.reshape(3, 1)))
    info = {
        "sfm_s": sfm_s,
        **timings,
        "feature_image_size": None if options.render_type != RenderType.SPHERICAL else options.max_image_size,
        "num_models": len(recs),
        "model_sizes": sorted((m.num_reg_images() for m in recs.values()), reverse=True),
        "num_points3D": rec.num_points3D(),
        "mean_reprojection_error_px": rec.compute_mean_reprojection_error(),
    }
    return PoseEstimate(poses, reg, "colmap", str(alignment), sim3=sim, raw=raw, reconstruction=rec, info=info)


def vggt_estimate(
    image_paths: list[Path],
    model,
    planned: np.ndarray | None,
    *,
    alignment: Alignment = Alignment.SIM3,
    out_hw: tuple[int, int] | None = None,
) -> PoseEstimate:
    """PanoVGGT on all frames at its input size; poses (and depth) optionally aligned to the planned trajectory.

    Depth is resized to out_hw (the video size) and scaled by the alignment scale.
    """
    frames = load_frames(image_paths, model.cfg.image_height)
    t0 = time.perf_counter()
    pred = model.predict(frames)
    infer_s = time.perf_counter() - t0
    raw = pred["world_from_cam"].astype(np.float64)
    n = len(raw)
    reg = np.ones(n, bool)
    sim = None
    if alignment != Alignment.NONE:
        if planned is None:
            raise InputError(f"align={alignment} needs the planned trajectory; give --trajectory or use --align none")
        planned = check_poses(planned, "planned")
        if len(planned) != n:
            raise InputError(f"the planned trajectory has {len(planned)} poses but the video has {n} frames")
        sim = _alignment(raw, planned, reg, alignment)
    scale = 1.0 if sim is None else sim[0]
    depth = pred["depth"] * np.float32(scale)
    if out_hw is not None and depth.shape[1:] != tuple(out_hw):
        depth = np.stack([cv2.resize(d, (out_hw[1], out_hw[0]), interpolation=cv2.INTER_LINEAR) for d in depth])
    info = {"infer_s": infer_s, "input_height": model.cfg.image_height,
            "pose_refine_iters": model.cfg.pose_refine_iters}
    return PoseEstimate(_apply(sim, raw), reg, "vggt", str(alignment), sim3=sim, raw=raw, depth=depth, info=info)


# ---------------------------------------------------------------- exports


def reconstruction_from_poses(names: list[str], world_from_cam: np.ndarray, height: int, width: int):
    """A pycolmap.Reconstruction with one EQUIRECTANGULAR camera and posed images (no points)."""
    import pycolmap

    world_from_cam = check_poses(world_from_cam)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_id(
        camera_id=1, model=pycolmap.CameraModelId.EQUIRECTANGULAR, focal_length=0.0, width=width, height=height
    )
    rec.add_camera_with_trivial_rig(cam)
    for i, (name, T) in enumerate(zip(names, world_from_cam), start=1):
        cam_from_world = invert_pose(T)
        rigid = pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world[:3, :3]), cam_from_world[:3, 3].reshape(3, 1))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=i), rigid)
    return rec


def poses_from_reconstruction(rec) -> dict[str, np.ndarray]:
    """{image name: world_from_cam (4, 4)} of the posed images of a pycolmap.Reconstruction."""
    out = {}
    for img in rec.images.values():
        if img.has_pose:
            out[img.name] = invert_pose(np.vstack([img.cam_from_world().matrix(), [0, 0, 0, 1]]))
    return out


def transforms_json(
    file_paths: list[str], world_from_cam: np.ndarray, height: int, width: int,
    depth_paths: list[str] | None = None, ply_path: str | None = None,
) -> dict:
    """nerfstudio transforms.json for ERP frames: camera_model EQUIRECTANGULAR, OpenGL transform_matrix.

    nerfstudio's equirectangular rays need fl_x = W/2, fl_y = H, cx = W/2, cy = H/2 (its convention), which
    reproduces our ERP mapping. Depth PNGs are millimetres (nerfstudio's default depth_unit_scale_factor 1e-3).
    """
    world_from_cam = check_poses(world_from_cam)
    frames = []
    for i, (fp, T) in enumerate(zip(file_paths, world_from_cam)):
        f = {"file_path": fp, "transform_matrix": gl_world_from_cam(T).tolist()}
        if depth_paths is not None:
            f["depth_file_path"] = depth_paths[i]
        frames.append(f)
    out = {
        "camera_model": "EQUIRECTANGULAR",
        "w": int(width), "h": int(height),
        "fl_x": width / 2.0, "fl_y": float(height), "cx": width / 2.0, "cy": height / 2.0,
        "frames": frames,
    }
    if ply_path is not None:
        out["ply_file_path"] = ply_path
    return out


def poses_from_transforms(d: dict) -> np.ndarray:
    """Inverse of transforms_json: our world_from_cam (N, 4, 4) from the OpenGL transform_matrix entries."""
    return np.stack([cv_world_from_cam_from_gl(np.asarray(f["transform_matrix"], np.float64)) for f in d["frames"]])


def write_poses_artifact(
    out_dir: Path,
    est: PoseEstimate,
    video: VideoFrames,
    planned: np.ndarray | None,
    *,
    depth: list[np.ndarray | Path] | None,
    copy_frames: bool = False,
) -> dict:
    """Write poses.json, depth/%06d.png, sparse/0 (COLMAP), transforms.json (+ points3D.ply); return the facts.

    Frame paths in transforms.json and COLMAP image names refer to the video artifact's frames relative to
    out_dir (e.g. ../video/frames/000000.png), or to images/ in out_dir when copy_frames.
    depth: per frame either a Path to a uint16 mm PNG (the video's: referenced relative to out_dir like the frames,
    copied into depth/ with copy_frames), or an (H, W) array in metres (written to depth/); None for no depth.
    Exports (sparse/0, transforms.json) hold the registered frames only; poses.json holds every frame.
    """
    out_dir = Path(out_dir)
    n = len(est.world_from_cam)
    names = [p.name for p in video.rgb]
    if copy_frames:
        (out_dir / "images").mkdir(parents=True, exist_ok=True)
        for p in video.rgb:
            shutil.copyfile(p, out_dir / "images" / p.name)
        image_dir = "images"
    else:
        # The stage writes into a temporary sibling of the final directory, so paths relative to out_dir hold.
        dirs = {p.parent.resolve() for p in video.rgb}
        if len(dirs) != 1:
            raise InputError("video frames must lie in one directory to be referenced by COLMAP and nerfstudio")
        image_dir = os.path.relpath(dirs.pop(), out_dir.resolve())
    frame_paths = [f"{image_dir}/{name}" for name in names]

    depth_rel = None
    if depth is not None:
        depth_rel = []
        for i, d in enumerate(depth):
            rel = f"depth/{i:06d}.png"
            if isinstance(d, Path) and not copy_frames:  # the video's own depth PNG: referenced like its frames
                rel = os.path.relpath(d.resolve(), out_dir.resolve())
            elif isinstance(d, Path):
                (out_dir / "depth").mkdir(parents=True, exist_ok=True)
                shutil.copyfile(d, out_dir / rel)
            else:
                write_depth_png(out_dir / rel, d)
            depth_rel.append(rel)

    reg = est.registered
    idx = np.flatnonzero(reg)
    if est.reconstruction is not None:
        rec = est.reconstruction
    else:
        rec = reconstruction_from_poses([names[i] for i in idx], est.world_from_cam[idx], video.height, video.width)
    sparse = out_dir / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    rec.write(sparse)
    ply = None
    if rec.num_points3D() > 0:
        rec.export_PLY(str(out_dir / "points3D.ply"))
        ply = "points3D.ply"
    tf = transforms_json(
        [frame_paths[i] for i in idx], est.world_from_cam[idx], video.height, video.width,
        [depth_rel[i] for i in idx] if depth_rel else None, ply,
    )
    (out_dir / "transforms.json").write_text(json.dumps(tf, indent=1))

    metrics = None
    if planned is not None and len(idx) >= 2 and est.raw is not None:
        metrics = trajectory_metrics(est.raw[idx], planned[idx])
    doc = {
        "backend": est.backend,
        "num_frames": n,
        "height": video.height,
        "width": video.width,
        "poses": est.world_from_cam.tolist(),
        "registered": reg.tolist(),
        "unregistered": np.flatnonzero(~reg).tolist(),
        "alignment": est.alignment,
        "sim3": None if est.sim3 is None else {
            "scale": est.sim3[0], "R": np.asarray(est.sim3[1]).tolist(), "t": np.asarray(est.sim3[2]).tolist(),
        },
        "metrics_vs_planned": metrics,
        "frames": [{"rgb": frame_paths[i], "depth": depth_rel[i] if depth_rel else None} for i in range(n)],
        "depth_scale": DEPTH_SCALE,
        "colmap_model": "sparse/0",
        "image_dir": image_dir,
    }
    write_json(out_dir / "poses.json", doc)
    return {
        "backend": est.backend,
        "num_frames": n,
        "num_registered": int(reg.sum()),
        "unregistered": doc["unregistered"],
        "sim3_scale": None if est.sim3 is None else float(est.sim3[0]),
        "metrics_vs_planned": to_jsonable(metrics),
        "has_depth": depth_rel is not None,
        "num_points3D": int(rec.num_points3D()),
        **est.info,
    }


@dataclass
class PosesArtifact:
    """A poses artifact as read back by downstream stages."""

    world_from_cam: np.ndarray
    """(N, 4, 4) canonical world_from_cam of every frame."""
    registered: np.ndarray
    """(N,) bool."""
    rgb: list[Path]
    """Frame image paths (resolved)."""
    depth: list[Path] | None
    """uint16 PNG depth paths (millimetres) or None."""
    height: int
    width: int
    backend: str


def load_poses(poses_dir: Path) -> PosesArtifact:
    """Read poses.json of a poses artifact (paths resolved against the artifact directory)."""
    poses_dir = Path(poses_dir)
    path = poses_dir / "poses.json"
    try:
        d = json.loads(path.read_text())
        T = check_poses(d["poses"], "poses.json poses")
        frames = d["frames"]
        rgb = [(poses_dir / f["rgb"]).resolve() for f in frames]
        depth = [poses_dir / f["depth"] for f in frames] if all(f["depth"] for f in frames) else None
        return PosesArtifact(T, np.asarray(d["registered"], bool), rgb, depth, int(d["height"]), int(d["width"]), d["backend"])
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise InputError(f"{path}: cannot read poses ({e}); rerun the poses stage") from None

