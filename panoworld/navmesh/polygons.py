"""Walkable-region polygons from the floor raster: contours simplified into boundary rings."""

from __future__ import annotations

import numpy as np

from panoworld.navmesh.heightfield import FloorGrid


def polygons_from_mask(mask: np.ndarray, grid: FloorGrid, tol_m: float) -> list[np.ndarray]:
    """Boundary rings (K, 2) in world x,z of a raster region (through boundary cell centres), simplified by tol_m."""
    import cv2

    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    rings = []
    for c in contours:
        approx = cv2.approxPolyDP(c, tol_m / grid.cell, True)
        if len(approx) < 3:
            approx = c
        if len(approx) < 3:
            continue
        px = approx.reshape(-1, 2).astype(np.float64)  # (col, row)
        rings.append(grid.xz_of(px[:, ::-1]))
    return rings
