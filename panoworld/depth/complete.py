"""Depth missing at the poles or in bands (LiDAR blind zones) completed from the fitted floor and ceiling planes."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from panoworld.core.conventions import erp_dirs64, erp_pixel_solid_angle
from panoworld.room.floor import column_reach, fit_planes

MIN_POLE_LAT_DEG = 30.0
"""Only rays at least this far above (ceiling) or below (floor) the horizon are completed."""


def pole_regions(valid: np.ndarray, min_lat_deg: float = MIN_POLE_LAT_DEG) -> tuple[np.ndarray, np.ndarray]:
    """(floor side, ceiling side) masks (H, W): invalid pixels at least min_lat_deg below / above the horizon that
    are connected (through invalid pixels, seam wrapped) to the nadir / zenith row, or lie in a band of invalid
    pixels spanning at least half the columns. Dropouts enclosed by valid depth (a black screen) are left out."""
    H, W = valid.shape
    lat = 90.0 - (np.arange(H) + 0.5) / H * 180.0
    out = []
    for rows, pole_row in ((lat <= -min_lat_deg, H - 1), (lat >= min_lat_deg, 0)):
        inv = ~valid & rows[:, None]
        wrapped = np.concatenate([inv, inv[:, :1]], axis=1)  # one wrapped column joins components across the seam
        labels, n = ndimage.label(wrapped, structure=np.ones((3, 3)))
        first, last = labels[:, 0], labels[:, -1]
        pairs = {(a, b) for a, b in zip(first, last) if a and b and a != b}
        parent = np.arange(n + 1)
        for a, b in pairs:
            ra, rb = parent[a], parent[b]
            parent[parent == rb] = ra
        labels = parent[labels[:, :W]]
        keep = set(np.unique(labels[pole_row][labels[pole_row] > 0]).tolist())
        for lab in np.unique(labels[labels > 0]):
            if lab not in keep and (labels == lab).any(0).mean() >= 0.5:
                keep.add(int(lab))
        out.append(np.isin(labels, sorted(keep)) & inv)
    return out[0], out[1]


def complete_poles(depth: np.ndarray, valid: np.ndarray, *, min_lat_deg: float = MIN_POLE_LAT_DEG,
                   exclude: np.ndarray | None = None, planes: tuple[float | None, float | None] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Fill pole_regions of depth (H, W, metres) from the horizontal floor / ceiling planes.

    A filled ray must meet its plane no farther out horizontally than the farthest valid depth of its own column
    (the room's extent that way; columns without depth take their neighbours'), so planes never reach past the
    walls. Returns (depth, valid, info): info gives the plane distances (None when not found) and the completed
    share of pixels and of the sphere per side. exclude (H, W): pixels left as they are (unknown); planes: the
    (floor, ceiling) of fit_planes when already fitted on this depth.
    """
    H, W = depth.shape
    floor_m, ceil_m = fit_planes(depth, valid) if planes is None else planes
    dirs = erp_dirs64(H, W)
    extent = column_reach(np.where(valid, depth, 0.0))
    have = extent > 0
    if not have.any():
        return depth, valid, {"floor_m": floor_m, "ceiling_m": ceil_m, "completed_fraction": 0.0}
    cols = np.arange(W)
    extent = np.interp(cols, cols[have], extent[have], period=W)
    down, up = pole_regions(valid, min_lat_deg)
    if exclude is not None:
        down, up = down & ~exclude, up & ~exclude
    omega = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W))
    depth, valid = depth.copy(), valid.copy()
    info: dict = {"floor_m": floor_m, "ceiling_m": ceil_m, "min_lat_deg": min_lat_deg}
    total = np.zeros((H, W), bool)
    for side, region, dist, sign in (("floor", down, floor_m, 1.0), ("ceiling", up, ceil_m, -1.0)):
        fill = np.zeros((H, W), bool)
        if dist is not None and region.any():
            dy = sign * dirs[..., 1]  # cosine to the plane's normal, > 0 towards it
            r = dist / np.maximum(dy, 1e-6)
            reach = r * np.hypot(dirs[..., 0], dirs[..., 2])
            fill = region & (dy > 0) & (reach <= 1.02 * extent[None, :])
            depth[fill] = r[fill].astype(depth.dtype)
            valid |= fill
        info[f"{side}_fraction"] = float(fill.mean())
        info[f"{side}_sphere_fraction"] = float(omega[fill].sum() / (4 * np.pi))
        info[f"{side}_missing_fraction"] = float(region.mean())
        total |= fill
    info["completed_fraction"] = float(total.mean())
    return depth, valid, info


SMOOTH_TOL = 0.03
"""complete_dropouts: where the harmonic fill lies within this relative distance of the nearest valid depth, the
surface is taken to continue smoothly across the dropout; elsewhere it is a depth edge."""
PLANE_TOL = 0.02
"""complete_dropouts: a dropout whose rim lies on one plane within this relative depth (90th percentile) is filled
with that plane."""


def _rim_planes(depth: np.ndarray, valid: np.ndarray, holes: np.ndarray, tol: float) -> tuple[np.ndarray, int]:
    """Depth (H, W) of the plane fitted to each dropout's rim (its valid 8-neighbours), NaN where the rim is not one
    plane within tol, and the number of dropouts so filled. The plane is fitted as 1 / d = a . dir (least squares)."""
    H, W = depth.shape
    dirs = erp_dirs64(H, W)
    out = np.full((H, W), np.nan)
    labels, n = ndimage.label(holes, structure=np.ones((3, 3)))
    planar = 0
    for k, sl in enumerate(ndimage.find_objects(labels), 1):
        sl = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in sl)
        comp = labels[sl] == k
        rim = ndimage.binary_dilation(comp, structure=np.ones((3, 3))) & valid[sl]
        if rim.sum() < 8:
            continue
        A, b = dirs[sl][rim], 1.0 / depth[sl][rim]
        a = np.linalg.lstsq(A, b, rcond=None)[0]
        if np.quantile(np.abs(A @ a - b) / b, 0.9) > tol:
            continue
        inv = dirs[sl][comp] @ a
        if (inv <= 0).any():
            continue
        out[sl][comp] = 1.0 / inv
        planar += 1
    return out, planar


def complete_dropouts(depth: np.ndarray, valid: np.ndarray, *, smooth_tol: float = SMOOTH_TOL,
                      plane_tol: float = PLANE_TOL, exclude: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Fill every invalid pixel of depth (H, W, metres) left after the poles: dropouts inside the scan (glass, dark
    or shiny surfaces, the mixed returns along object silhouettes).

    The prior, per dropout: when its rim lies on one plane (within plane_tol) the dropout is that plane (a window, a
    dark panel). Otherwise each pixel gets the harmonic interpolation of the rim in inverse depth where that lies
    within smooth_tol of the nearest valid pixel's depth (a smooth surface continuing), and elsewhere, where the
    dropout spans a depth edge, the nearest valid pixel's depth (seam wrapped): the edge stays a step between the two
    surfaces instead of a ramp of floating geometry. exclude (H, W): invalid pixels left unknown (no rim, no fill).
    Returns (depth, valid, info).
    """
    from panoworld.depth.depth_map import _harmonic_fill

    holes = ~valid if exclude is None else ~valid & ~exclude
    H, W = depth.shape
    info: dict = {"smooth_tol": smooth_tol, "plane_tol": plane_tol, "completed_fraction": 0.0}
    if not holes.any() or not valid.any():
        return depth, valid, info
    inv = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    harmonic = 1.0 / np.maximum(_harmonic_fill(inv, holes, valid), 1e-12)
    pad = W // 4  # nearest valid pixel with the seam wrapped: pad with wrapped columns
    none = ~valid  # nearest valid pixel (not an excluded one)
    padded = np.concatenate([none[:, -pad:], none, none[:, :pad]], axis=1)
    _, (ii, jj) = ndimage.distance_transform_edt(padded, return_indices=True)
    nearest = depth[ii[:, pad:pad + W], (jj[:, pad:pad + W] - pad) % W]
    plane, n_planar = _rim_planes(depth, valid, holes, plane_tol)
    on_plane = holes & np.isfinite(plane)
    smooth = holes & ~on_plane & (np.abs(harmonic - nearest) <= smooth_tol * nearest)
    fill = np.where(on_plane, plane, np.where(smooth, harmonic, nearest))
    out = np.where(valid, depth, np.where(holes, fill, 0.0)).astype(depth.dtype)
    omega = np.broadcast_to(erp_pixel_solid_angle(H, W), (H, W))
    _, n = ndimage.label(holes, structure=np.ones((3, 3)))
    m = holes.sum()
    info.update(completed_fraction=float(holes.mean()), sphere_fraction=float(omega[holes].sum() / (4 * np.pi)),
                dropouts=int(n), planar_dropouts=n_planar, plane_fraction=float(on_plane.sum() / m),
                smooth_fraction=float(smooth.sum() / m), step_fraction=float((holes & ~on_plane & ~smooth).sum() / m))
    return out, (np.ones_like(valid) if exclude is None else ~exclude), info
