"""Depth maps resized like the colour beside them (area or bilinear on smooth surfaces, nearest at edges)."""

from __future__ import annotations

import math

import cv2
import numpy as np

DEPTH_EDGE_REL = 0.1
"""resize_depth treats a neighbourhood whose depths span more than this fraction as a depth edge."""


def resize_depth(depth: np.ndarray, height: int, width: int, edge_rel: float = DEPTH_EDGE_REL) -> np.ndarray:
    """Depth (h, w) metres (NaN/0/inf = none) resized to (height, width) like the colour beside it: on smooth surfaces
    (every source pixel the target pixel reads valid and their depths within edge_rel of each other) area-averaged
    when shrinking and bilinear when enlarging, nearest at depth edges and next to invalid pixels (no depth between two
    surfaces, none made up). Nearest everywhere would put the pixels of a smooth surface on an uneven grid (720 -> 512
    rows skips every third row or column; 512 -> 1024 rows repeats each one, a terrace every other row), which opens
    cracks between per-pixel Gaussians seen from aside."""
    import cv2

    h, w = depth.shape
    d = np.asarray(depth, np.float32)
    valid = np.isfinite(d) & (d > 0)
    nearest = cv2.resize(np.where(valid, d, np.nan).astype(np.float32), (width, height),
                         interpolation=cv2.INTER_NEAREST)
    k = 2 * math.ceil(max(h / height, w / width, 1.0) / 2) + 1  # holds every source pixel a target pixel reads
    kernel = np.ones((k, k), np.uint8)
    hi = cv2.dilate(np.where(valid, d, 0).astype(np.float32), kernel)
    lo = cv2.erode(np.where(valid, d, np.inf).astype(np.float32), kernel)
    full = cv2.erode(valid.astype(np.uint8), kernel)
    hi, lo, full = (cv2.resize(a, (width, height), interpolation=cv2.INTER_NEAREST) for a in (hi, lo, full))
    enlarge = height > h or width > w  # INTER_AREA enlarges as nearest does
    area = cv2.resize(np.where(valid, d, 0).astype(np.float32), (width, height),
                      interpolation=cv2.INTER_LINEAR if enlarge else cv2.INTER_AREA)
    with np.errstate(invalid="ignore", over="ignore"):
        smooth = (full > 0) & (hi <= lo * (1.0 + edge_rel))
    return np.where(smooth, area, nearest).astype(np.float32)


def rgbd_at_height(rgb: np.ndarray, depth: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray]:
    """rgb (area) and depth (resize_depth; 0 = unknown) at `height` rows when they are taller (never upsampled; 0 = as
    given): a panorama resized as the video frames are (ContextSource)."""
    if height and depth.shape[0] > height:
        rgb = cv2.resize(rgb, (2 * height, height), interpolation=cv2.INTER_AREA)
        depth = np.nan_to_num(resize_depth(depth, height, 2 * height), nan=0.0, posinf=0.0)
    return rgb, depth
