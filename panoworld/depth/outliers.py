"""Implausible far depth (isolated spikes, values far beyond the room) masked as invalid, with a record of what was masked."""

from __future__ import annotations

import numpy as np

from panoworld.core.conventions import erp_pixel_solid_angle

SPIKE_RATIO = 3.0
"""A pixel is a spike when its depth exceeds this multiple of all but at most one of its valid 8-neighbours."""
FAR_FACTOR = 8.0
"""In a broken depth (BROKEN_FACTOR), depth beyond this multiple of the median depth over the sphere (solid-angle
weighted) is beyond the room."""
BROKEN_FACTOR = 30.0
"""Depth beyond this multiple of the median is beyond any room; where it covers more than BROKEN_SHARE of the sphere
the depth is broken (a layout seen from outside its polygon, whose floor rays run hundreds of metres; a sky) and
FAR_FACTOR applies, else only this: a narrow hallway seen from its end reaches 10-20x its median."""
BROKEN_SHARE = 1e-4
"""Share of the sphere's solid angle beyond BROKEN_FACTOR x the median that makes a depth broken (a gap in one wall of
a 1 m hallway's layout sends 0.1 % of the sphere there; fewer such pixels are lone values, masked all the same)."""


def weighted_median(depth: np.ndarray, valid: np.ndarray) -> float:
    """Median of the valid depth over the sphere, each pixel weighted by its solid angle."""
    w = np.broadcast_to(erp_pixel_solid_angle(depth.shape[0], depth.shape[1]), depth.shape)[valid]
    d = depth[valid]
    order = np.argsort(d)
    cum = np.cumsum(w[order])
    return float(d[order][np.searchsorted(cum, 0.5 * cum[-1])])


def spike_mask(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Isolated far values: valid pixels more than SPIKE_RATIO x as deep as all but at most one of their valid
    8-neighbours (seam wrapped), with at least 3 valid neighbours. At a depth edge the far side has far neighbours
    along the edge, so only lone (1-2 px) spikes qualify."""
    d = np.where(valid, depth, 0).astype(np.float32)
    padded = np.pad(np.concatenate([d[:, -1:], d, d[:, :1]], axis=1), ((1, 1), (0, 0)))
    H, W = d.shape
    n_valid = np.zeros((H, W), np.int8)
    n_alike = np.zeros((H, W), np.int8)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                n = padded[1 + dy:1 + dy + H, 1 + dx:1 + dx + W]
                n_valid += n > 0
                n_alike += (n > 0) & (SPIKE_RATIO * n >= d)
    return valid & (n_valid >= 3) & (n_alike <= 1)


def mask_depth_outliers(depth: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, dict]:
    """Valid mask with implausible far depth removed, and a record for the depth manifest.

    Spikes: depth > SPIKE_RATIO x all but one of its valid 8-neighbours (a lone far value among near ones).
    Beyond the room: depth > FAR_FACTOR x the sphere's solid-angle weighted median depth where the depth is broken
    (more than BROKEN_SHARE of the sphere beyond BROKEN_FACTOR x that median), else > BROKEN_FACTOR x it. The
    camera's room dominates the sphere, so its median is a robust room size even when a whole wall is wrong. Both tests are
    relative: depth (H, W) may be in any unit (they run before the floor-based metric rescale, whose floor fit
    outliers would spoil). valid (H, W) bool.
    """
    valid = valid & np.isfinite(depth) & (depth > 0)
    if not valid.any():
        return valid, {"spike_px": 0, "far_px": 0}
    med = weighted_median(depth, valid)
    omega = np.broadcast_to(erp_pixel_solid_angle(depth.shape[0], depth.shape[1]), depth.shape)
    broken_share = float(omega[valid & (depth > BROKEN_FACTOR * med)].sum() / omega.sum())
    factor = FAR_FACTOR if broken_share > BROKEN_SHARE else BROKEN_FACTOR
    far_at = factor * med
    far = valid & (depth > far_at)
    spikes = spike_mask(depth, valid & ~far)
    out = valid & ~far & ~spikes
    record = {
        "median_depth": med,
        "broken_share": broken_share,
        "far_factor": factor,
        "far_threshold": float(far_at),
        "far_px": int(far.sum()),
        "spike_px": int(spikes.sum()),
        "spike_ratio": SPIKE_RATIO,
        "masked_fraction": float((far | spikes).mean()),
        "max_depth_before": float(depth[valid].max()),
        "max_depth_after": float(depth[out].max()) if out.any() else None,
    }
    return out, record


def mask_and_record(depth: np.ndarray, valid: np.ndarray, info: dict, notes: list[str], unit: str = "units") -> np.ndarray:
    """mask_depth_outliers for the depth stage: the record goes to info["outliers"], a line to notes when any."""
    valid, record = mask_depth_outliers(depth, valid)
    info["outliers"] = record
    line = describe(record, unit)
    if line:
        notes.append(line)
    return valid


def describe(record: dict, unit: str = "units") -> str | None:
    """One line for the depth manifest's decisions, or None when nothing was masked."""
    if not (record.get("far_px") or record.get("spike_px")):
        return None
    return (f"depth outliers masked: {record['far_px']} px beyond the room (> {record['far_threshold']:.1f} {unit}, "
            f"{record['far_factor']:g}x the median depth {record['median_depth']:.2f} {unit}; max was "
            f"{record['max_depth_before']:.0f} {unit}) and {record['spike_px']} isolated spikes "
            f"(> {SPIKE_RATIO:g}x their neighbours)")

