"""Capture-rig removal (the floor filled, the shadow relit, depth from the floor plane), the depth stage's rig step and the nadir measures (docs/rig.md)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from panoworld.core.conventions import erp_dirs64, erp_pixel_solid_angle
from panoworld.depth.rig.detect import detect_rig
from panoworld.depth.rig.face import (
    erp_mask_to_face,
    face_to_erp,
    nadir_view,
)
from panoworld.depth.rig.inpaint import RING_WIDTH_DEG, inpaint_plane, matte_rim, ring_fill
from panoworld.depth.rig.nadir import (
    RING_DEG,
    RigDetection,
)
from panoworld.geometry.cube_views import render_view
from panoworld.io.images import read_rig_mask
from panoworld.room.floor import column_reach
from panoworld.room.light import apply_gain


def remove_rig(rgb: np.ndarray, det: RigDetection) -> np.ndarray:
    """The panorama with the rig inpainted and its shadow relit on the downward face, changed only inside the
    masks (H, W, 3) uint8. The rig: Telea inpainting for the low frequencies plus the texture of the best-matching
    floor patch elsewhere on the face (the floor is a plane there, so its texture repeats under translation); the
    mask's rim is matted between the rig's colour and the fill (rig_inpaint.matte_rim)."""
    H, W = rgb.shape[:2]
    view = nadir_view(H)
    face = render_view(rgb, view).astype(np.float32)
    obj = erp_mask_to_face(det.mask, view)  # not grown further: a wider hole replaces seen floor by a guess
    lin = (face / 255.0) ** 2.2
    if det.shadow_gain is not None:
        lin = lin * det.shadow_gain[..., None]
    source = det.source if det.source is not None and det.source.shape == obj.shape else np.ones_like(obj)
    lit_face = np.clip(lin, 0, 1) ** (1 / 2.2) * 255.0
    if det.fill == "ring":
        clean = ring_fill(lit_face, obj, source, view.focal * np.deg2rad(RING_WIDTH_DEG))
    else:
        clean = inpaint_plane(lit_face, obj, source)
    back = face_to_erp(clean, view, H, W)
    lit = rgb
    if det.shadow_gain is not None:  # the rim's floor is matted in the relit panorama
        lit = apply_gain(rgb, face_to_erp(det.shadow_gain, view, H, W, 1.0))
    out = rgb.copy()
    out[det.mask] = np.clip(np.rint(matte_rim(lit, back, det.mask)[det.mask]), 0, 255).astype(np.uint8)
    if det.shadow is not None and det.shadow_gain is not None:  # relit where it is: the texture is not resampled
        sh = det.shadow & ~det.mask
        out[sh] = lit[sh]
    return out


def floor_depth(H: int, W: int, floor_m: float) -> np.ndarray:
    """Ray distance (H, W) to the horizontal floor floor_m below the camera (0 where a ray does not look down)."""
    down = erp_dirs64(H, W)[..., 1]
    return np.where(down > 1e-3, floor_m / np.maximum(down, 1e-3), 0.0).astype(np.float32)


def floor_within_walls(plane: np.ndarray, depth: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """The floor plane's ray distance plane (H, W) cut at each column's wall: no farther horizontally than the
    farthest point of depth (H, W) at the pixels seen (H, W) bool in that column (a mask reaching a wall's base looks
    at the wall there, not at floor behind it); columns with nothing seen keep the plane."""
    dirs = erp_dirs64(*depth.shape)
    flat = np.hypot(dirs[..., 0], dirs[..., 2])
    reach = column_reach(np.where(seen, depth, 0.0))
    wall = np.where(reach[None, :] > 0, reach[None, :] / np.maximum(flat, 1e-9), np.inf)
    return np.minimum(plane, wall).astype(np.float32)


def area_stats(mask: np.ndarray) -> dict:
    """Solid-angle share of the sphere and the cap (degrees from the nadir) holding 98 % of a mask's pixels."""
    H, W = mask.shape
    omega = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W))
    frac = float(omega[mask].sum() / (4 * np.pi))
    rows = np.nonzero(mask.any(1))[0]
    cap = float(180.0 - (rows.min() + 0.5) / H * 180.0) if len(rows) else 0.0
    return {"sphere_fraction": frac, "cap_deg": cap, "pixels": int(mask.sum())}


def rig_step(rgb: np.ndarray, depth: np.ndarray, valid: np.ndarray, floor_m: float | None, *,
             user_mask: Path | np.ndarray | None = None, detect=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, RigDetection]:
    """Detect with detect(rgb, depth, valid, floor_m) (default detect_rig), or take the user's mask, and remove the
    rig: (rgb, depth, valid, info, detection). Inside the rig mask depth comes from the floor plane floor_m below the
    camera, never past its column's wall (floor_within_walls; invalid when no floor was found); outside the masks
    nothing changes (no rig: the very same arrays)."""
    H, W = rgb.shape[:2]
    if user_mask is not None:
        m = user_mask if isinstance(user_mask, np.ndarray) else read_rig_mask(user_mask, (H, W))
        det = RigDetection(bool(m.any()), "user mask" if isinstance(user_mask, np.ndarray) else
                           f"user mask {Path(user_mask).name}", "user", m, np.zeros_like(m))
    else:
        det = (detect or detect_rig)(rgb, depth, valid, floor_m)
    info = {"found": det.found, "reason": det.reason, "kind": det.kind,
            "stats": {k: (round(v, 4) if isinstance(v, float) else v) for k, v in det.stats.items()}}
    if not det.found:
        return rgb, depth, valid, info, det
    rgb = remove_rig(rgb, det)
    info["mask"] = area_stats(det.mask)
    info["shadow"] = area_stats(det.shadow)
    depth, valid = depth.copy(), valid.copy()
    if floor_m:
        plane = floor_within_walls(floor_depth(H, W, floor_m), depth, valid & ~det.mask)
        put = det.mask & (plane > 0)
        depth[put], valid[put] = plane[put], True
        valid[det.mask & ~put] = False
        info["depth"] = f"floor plane {floor_m:.3f} m below the camera"
    else:
        valid[det.mask] = False
        info["depth"] = "no floor found: depth under the rig made invalid"
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    return rgb, depth, valid, info, det


def nadir_luminance_gap(rgb: np.ndarray, cap_deg: float = 15.0) -> float:
    """Relative difference of the mean luminance (solid-angle weighted) of the cap within cap_deg of the nadir and
    of the floor ring RING_DEG around it: (cap - ring) / ring, e.g. -0.5 for a cap half as bright (a dark mount)."""
    H, W = rgb.shape[:2]
    theta = (np.arange(H) + 0.5) / H * 180.0  # degrees from the zenith
    from_nadir = 180.0 - theta
    lum = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float64).mean(1)
    w = erp_pixel_solid_angle(H, W)[:, 0]
    cap = from_nadir < cap_deg
    ring = (from_nadir >= RING_DEG[0]) & (from_nadir < RING_DEG[1])
    lc = float((lum * w)[cap].sum() / w[cap].sum())
    lr = float((lum * w)[ring].sum() / w[ring].sum())
    return (lc - lr) / max(lr, 1e-6)


def nadir_cap_psnr(a: np.ndarray, b: np.ndarray, deg: float = 15.0) -> float:
    """Solid-angle weighted PSNR (dB) of two ERP images (H, W, 3) uint8 over the cap within deg of the nadir."""
    h, w = a.shape[:2]
    r0 = int(h * (1.0 - deg / 180.0))
    wt = np.broadcast_to(erp_pixel_solid_angle(h, w)[r0:], (h - r0, w))[..., None]
    mse = float((wt * (a[r0:].astype(np.float64) - b[r0:]) ** 2).sum() / (3 * wt.sum()))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))
