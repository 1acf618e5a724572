"""Shared pieces of `runner.py eval`: params, 'unavailable' results, targets, per-metric helpers, LPIPS."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from panoworld.core.errors import InputError
from panoworld.core.shapes import check_shape

GT_DIRNAME = "gt"


class EvalInputError(InputError):
    """The scene or an option cannot be evaluated at all (no ground truth, unusable weights): exit code 2."""


class LpipsNet(enum.StrEnum):
    ALEX = "alex"
    """AlexNet features (the LPIPS default)."""
    VGG = "vgg"
    """VGG16 features."""


@dataclass(kw_only=True)
class EvalParams:
    """What `runner.py eval` measures and at which sizes."""

    max_frames: int = 16
    """Frames evaluated per sequence (conditions, video), uniformly spaced over frames 1..N-1; 0 = all of them."""
    views: int = 4
    """N of the N@N protocol for Gaussians: N context views and N novel views are rendered."""
    video_height: int = 0
    """ERP height at which video frames are compared (frames resized with INTER_AREA, ground truth rendered at that
    size; the paper compares at 720 and at 480); 0 = the video's own size."""
    gs_height: int = 128
    """ERP height of the Gaussian renders and of their ground truth (width = 2 x height)."""
    disocclusion_tol: float = 0.015
    """Relative tolerance of the true-disocclusion test: a point counts as seen from the source camera when
    nothing lies nearer than (1 - tol) times its distance along the source ray."""
    surface_samples: int = 20000
    """Mesh vertices (uniformly sampled) whose distance to the ground-truth surface is measured."""
    navmesh_samples: int = 2000
    """Points sampled on the NavMesh to check that the agent's column there is really free."""
    seed: int = 0
    """Seed of the NavMesh and mesh-vertex sampling."""
    lpips_weights: str | None = None
    """LPIPS backbone weights: a torchvision AlexNet/VGG16 state dict (.pth); needs --lpips-lin-weights too."""
    lpips_lin_weights: str | None = None
    """LPIPS v0.1 linear-head weights for --lpips-net (alex.pth or vgg.pth of the official lpips package)."""
    lpips_net: LpipsNet = LpipsNet.ALEX
    """Backbone architecture of --lpips-weights."""
    fid_weights: str | None = None
    """FID InceptionV3 weights: pytorch-fid's pt_inception-2015-12-05-6726825d.pth (dataset evaluation only)."""
    fvd_weights: str | None = None
    """FVD I3D weights: i3d_torchscript.pt (the Kinetics-400 I3D of the FVD paper; dataset evaluation only)."""
    pose_tol_m: float = 1e-3
    """Frames + poses scenes: a pipeline pose matches a ground-truth track frame when their camera centres lie within
    this distance (metres) and their orientations within 0.1 degree."""
    reference_supersample: int = 4
    """Synthetic references are anti-aliased: ray cast at this factor x the scored rows and columns and
    area-downsampled in linear RGB (1 = one ray per pixel, the aliased reference of earlier rounds)."""
    reference_max_rows: int = 1536
    """The supersampling factor is lowered so that a supersampled reference has at most this many rows (a 720-row
    reference is cast at 2x, a 256-row one at 4x)."""
    reference_cache_mb: float = 512.0
    """Memory bound of the cache of reference renders (least recently used renders are dropped)."""
    roam_views: int = 0
    """Roam protocol: random upright poses per distance bucket (0 = 2, or 1 on a ci-tiny scene)."""
    roam_height: int = 0
    """Roam protocol: ERP height of the renders (width 2 x; 0 = 256, or 64 on a ci-tiny scene)."""
    roam_pinhole: int = 0
    """Roam protocol: side in pixels of the square pinhole view rendered at every roam pose (horizontal, facing the
    pose's random yaw); 0 = 256, or 64 on a ci-tiny scene; -1 = no pinhole views."""
    roam_fov_deg: float = 90.0
    """Roam protocol: field of view of the pinhole views in degrees."""


# ---------------------------------------------------------------- results and targets


def unavailable(reason: str) -> dict:
    """The value of a metric (or a whole stage) that could not be computed, with the reason why."""
    return {"available": False, "reason": reason}


def is_unavailable(value: Any) -> bool:
    return isinstance(value, dict) and value.get("available") is False


@dataclass(frozen=True)
class Target:
    """A pass mark: value op bound (the targets of docs/evaluation.md, and collision-freeness for trajectories)."""

    op: str
    """'>=' or '<='."""
    bound: float
    unit: str = ""

    def met(self, value: Any) -> bool | None:
        if not isinstance(value, (int, float)) or isinstance(value, bool) or math.isnan(value):
            return None
        return value >= self.bound if self.op == ">=" else value <= self.bound

    def text(self) -> str:
        return f"{self.op} {self.bound:g}{self.unit}"


TARGETS: dict[str, dict[str, Target]] = {
    "register": {"registered_fraction": Target(">=", 1.0), "misplaced": Target("<=", 0),
                 "trans_cm_max": Target("<=", 5.0, " cm"), "rot_deg_max": Target("<=", 1.0, " deg")},
    "trajectory": {"clear_fraction": Target(">=", 1.0), "path_collisions": Target("<=", 0)},
    "conditions": {"psnr_valid": Target(">=", 28.0, " dB"), "mask_iou": Target(">=", 0.75)},
    "poses": {"ate_over_path": Target("<=", 0.005)},
    "gaussians": {"context_psnr": Target(">=", 26.0, " dB"), "novel_psnr": Target(">=", 22.0, " dB"),
                  "capture_psnr_min": Target(">=", 28.0, " dB")},
    "roam": {"d0_erp_psnr": Target(">=", 32.0, " dB"), "d1_erp_psnr": Target(">=", 28.0, " dB"),
             "d2_erp_psnr": Target(">=", 25.0, " dB"), "d2_erp_coverage": Target(">=", 0.995)},
}



# ---------------------------------------------------------------- per-metric helpers


def depth_errors(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """AbsRel = mean |p - g| / g, RMSE (metres), delta1 = share with max(p/g, g/p) < 1.25, and the median of g / p,
    over pixels where mask (H, W) is set, p > 0 and g are finite and positive; pred, gt (H, W) metres."""
    check_shape("pred", pred, "H W", dims=check_shape("gt", gt, "H W"))
    sel = np.isfinite(pred) & np.isfinite(gt) & (pred > 0) & (gt > 0)
    if mask is not None:
        sel &= mask.astype(bool)
    if not sel.any():
        return {"abs_rel": float("nan"), "rmse_m": float("nan"), "delta1": float("nan"), "scale_median": float("nan")}
    p, g = pred[sel].astype(np.float64), gt[sel].astype(np.float64)
    return {
        "abs_rel": float(np.mean(np.abs(p - g) / g)),
        "rmse_m": float(np.sqrt(np.mean((p - g) ** 2))),
        "delta1": float(np.mean(np.maximum(p / g, g / p) < 1.25)),
        "scale_median": float(np.median(g / p)),
    }


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks; nan when both are empty."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else float("nan")


def interpolate_pose(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """Pose (4, 4) at fraction t from a to b: linear camera centre, slerp rotation."""
    from scipy.spatial.transform import Rotation, Slerp

    out = np.eye(4)
    out[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))(t).as_matrix()
    out[:3, 3] = (1.0 - t) * a[:3, 3] + t * b[:3, 3]
    return out


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


class Lpips:
    """LPIPS on uint8 images when weights were passed, else the reason it is unavailable."""

    def __init__(self, params: EvalParams):
        self.params = params

    @cached_property
    def model(self):
        from panoworld.models.lpips import LPIPS

        return LPIPS.from_files(self.params.lpips_weights, self.params.lpips_lin_weights, net=self.params.lpips_net)

    @property
    def enabled(self) -> bool:
        return bool(self.params.lpips_weights or self.params.lpips_lin_weights)

    def reason(self) -> dict:
        return unavailable("pass --lpips-weights BACKBONE.pth and --lpips-lin-weights LIN.pth (torchvision "
                           f"{'AlexNet' if self.params.lpips_net == LpipsNet.ALEX else 'VGG16'} state dict and the "
                           "official lpips v0.1 linear weights)")

    def distance(self, a: np.ndarray, b: np.ndarray) -> float:
        return self.model.distance_uint8(a, b)


def fid_fvd_per_scene() -> dict[str, dict]:
    return {k: unavailable(f"a distribution metric: computed over a whole dataset by `runner.py eval DATASET --all "
                           f"--{k}-weights FILE`, never for one scene") for k in ("fid", "fvd")}


# ---------------------------------------------------------------- artifact readers


def _read_gray(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2:
        raise ValueError(f"{path}: missing or not a single-channel PNG")
    return img

