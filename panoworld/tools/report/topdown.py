"""Top-down (plan) views in SVG: a raster of the mesh seen from above with vector overlays (NavMesh, paths, poses).

Plan coordinates: world X to the right and world Z (the source panorama's forward direction) up the page,
i.e. the scene seen from above (up = -Y); see docs/conventions.md.
"""

from __future__ import annotations

import html
import math

import cv2
import numpy as np

from panoworld.tools.report.encode import colors_for, data_uri

MAX_PX = 640


class PlanView:
    """Maps world XZ to SVG pixels over a fixed extent; collects overlay elements."""

    def __init__(self, xz_points: np.ndarray, margin_m: float = 0.3, max_px: int = MAX_PX):
        xz = np.asarray(xz_points, np.float64).reshape(-1, 2)
        if len(xz) == 0:
            xz = np.zeros((1, 2))
        lo, hi = xz.min(0) - margin_m, xz.max(0) + margin_m
        span = np.maximum(hi - lo, 1.0)
        self.cell = float(span.max() / max_px)
        self.x0, self.z1 = float(lo[0]), float(lo[1] + span[1])
        self.w, self.h = int(math.ceil(span[0] / self.cell)), int(math.ceil(span[1] / self.cell))
        self.items: list[str] = []

    def px(self, xz: np.ndarray) -> np.ndarray:
        xz = np.asarray(xz, np.float64).reshape(-1, 2)
        return np.stack([(xz[:, 0] - self.x0) / self.cell, (self.z1 - xz[:, 1]) / self.cell], 1)

    def _pts(self, xz: np.ndarray) -> str:
        return " ".join(f"{x:.1f},{y:.1f}" for x, y in self.px(xz))

    def background(self, rgb: np.ndarray) -> None:
        self.items.insert(0, f'<image href="{data_uri(rgb)}" x="0" y="0" width="{self.w}" height="{self.h}" '
                             'preserveAspectRatio="none"/>')

    def polygon_rings(self, rings: list[np.ndarray], fill: str, stroke: str, title: str) -> None:
        d = " ".join("M" + " L".join(f"{x:.1f},{y:.1f}" for x, y in self.px(r)) + " Z" for r in rings if len(r) >= 3)
        if d:
            self.items.append(f'<path d="{d}" fill="{fill}" fill-rule="evenodd" stroke="{stroke}" stroke-width="1.5">'
                              f"<title>{html.escape(title)}</title></path>")

    def triangles(self, vertices: np.ndarray, tris: np.ndarray, stroke: str) -> None:
        p = self.px(vertices)
        d = " ".join(f"M{p[a, 0]:.1f},{p[a, 1]:.1f} L{p[b, 0]:.1f},{p[b, 1]:.1f} L{p[c, 0]:.1f},{p[c, 1]:.1f} Z"
                     for a, b, c in np.asarray(tris, int))
        if d:
            self.items.append(f'<path d="{d}" fill="none" stroke="{stroke}" stroke-width="0.5"/>')

    def polyline(self, xz: np.ndarray, stroke: str, width: float = 2.0, dash: str = "", closed: bool = False) -> None:
        tag = "polygon" if closed else "polyline"
        extra = f' stroke-dasharray="{dash}"' if dash else ""
        self.items.append(f'<{tag} points="{self._pts(xz)}" fill="none" stroke="{stroke}" stroke-width="{width}"'
                          f' stroke-linejoin="round"{extra}/>')

    def dots(self, xz: np.ndarray, colors: list[str] | str, r: float = 4.0, titles: list[str] | None = None,
             stroke: str = "#000") -> None:
        p = self.px(xz)
        for i, (x, y) in enumerate(p):
            c = colors if isinstance(colors, str) else colors[i]
            t = f"<title>{html.escape(titles[i])}</title>" if titles else ""
            self.items.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="{r}" fill="{c}" stroke="{stroke}" stroke-width="0.8">{t}</circle>')

    def rings(self, xz: np.ndarray, stroke: str, r: float = 8.0, title: str = "") -> None:
        for x, y in self.px(xz):
            self.items.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="{r}" fill="none" stroke="{stroke}" stroke-width="2">'
                              f"<title>{html.escape(title)}</title></circle>")

    def crosses(self, xz: np.ndarray, stroke: str, r: float = 6.0, titles: list[str] | None = None) -> None:
        for i, (x, y) in enumerate(self.px(xz)):
            t = f"<title>{html.escape(titles[i])}</title>" if titles else ""
            self.items.append(f'<path d="M{x - r:.1f},{y - r:.1f} L{x + r:.1f},{y + r:.1f} M{x - r:.1f},{y + r:.1f} '
                              f'L{x + r:.1f},{y - r:.1f}" stroke="{stroke}" stroke-width="2.5">{t}</path>')

    def star(self, xz: np.ndarray, fill: str, r: float = 9.0, title: str = "") -> None:
        (x, y), = self.px(xz)
        pts = []
        for k in range(10):
            a = -math.pi / 2 + k * math.pi / 5
            rr = r if k % 2 == 0 else r * 0.45
            pts.append(f"{x + rr * math.cos(a):.1f},{y + rr * math.sin(a):.1f}")
        self.items.append(f'<polygon points="{" ".join(pts)}" fill="{fill}" stroke="#000" stroke-width="1">'
                          f"<title>{html.escape(title)}</title></polygon>")

    def label(self, xz: np.ndarray, text: str, fill: str = "#ffffff", dy: float = -12.0) -> None:
        """text centred dy pixels above the point xz (2,), outlined so it reads on any background."""
        (x, y), = self.px(xz)
        self.items.append(f'<text x="{x:.1f}" y="{y + dy:.1f}" font-size="12" fill="{fill}" stroke="#000" '
                          f'stroke-width="0.35" text-anchor="middle">{html.escape(text)}</text>')

    def headings(self, poses: np.ndarray, length_m: float, stroke: str) -> None:
        """Short lines along each camera's forward axis (world_from_cam column z) projected on the floor."""
        poses = np.asarray(poses, np.float64)
        a = poses[:, [0, 2], 3]
        fwd = poses[:, [0, 2], 2]
        fwd = fwd / np.maximum(np.linalg.norm(fwd, axis=1, keepdims=True), 1e-9)
        pa, pb = self.px(a), self.px(a + length_m * fwd)
        d = " ".join(f"M{x0:.1f},{y0:.1f} L{x1:.1f},{y1:.1f}" for (x0, y0), (x1, y1) in zip(pa, pb))
        self.items.append(f'<path d="{d}" stroke="{stroke}" stroke-width="1.2"/>')

    def sector_rays(self, start_xz: np.ndarray, n: int, length_m: float, stroke: str = "#ffd400") -> None:
        """The boundaries between n sectors around start (sector k centred on lon = k 2pi/n, lon 0 = +Z)."""
        s = np.asarray(start_xz, np.float64).reshape(2)
        for k in range(n):
            lon = (k + 0.5) * 2 * math.pi / n
            e = s + length_m * np.array([math.sin(lon), math.cos(lon)])
            self.polyline(np.stack([s, e]), stroke, width=1.2, dash="6 4")
        for k in range(n):
            lon = k * 2 * math.pi / n
            (x, y), = self.px(s + 0.6 * length_m * np.array([math.sin(lon), math.cos(lon)]))
            self.items.append(f'<text x="{x:.1f}" y="{y:.1f}" font-size="13" fill="{stroke}" stroke="#000" '
                              f'stroke-width="0.4" text-anchor="middle">{k}</text>')

    def svg(self) -> str:
        return (f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {self.w} {self.h}" '
                f'width="{self.w}" height="{self.h}">' + "".join(self.items) + "</svg>")


def mesh_from_above(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, view: PlanView, ceiling_cut_y: float,
                    max_samples: int = 3_000_000, seed: int = 0) -> np.ndarray:
    """(h, w, 3) RGB of the mesh seen from above, ignoring faces with a vertex higher than ceiling_cut_y.

    Faces inside the view are sampled (about two points per plan pixel they cover) and each plan cell shows its
    highest sample (smallest y: up = -Y) with the barycentric vertex colour; isolated empty cells take a
    neighbour's colour, the rest stays dark grey.
    """
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.int64)
    m = 0.5  # faces with a vertex within 0.5 m of the view count as inside it
    x, z = v[:, 0], v[:, 2]
    v_ok = (v[:, 1] > ceiling_cut_y) & (np.abs(v).sum(1) > 1e-6)
    v_in = (x >= view.x0 - m) & (x <= view.x0 + view.w * view.cell + m) & (z <= view.z1 + m) & (z >= view.z1 - view.h * view.cell - m)
    keep = v_ok[f].all(1) & v_in[f].any(1)
    f = f[keep]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area_px = 0.5 * np.abs((b[:, 0] - a[:, 0]) * (c[:, 2] - a[:, 2]) - (b[:, 2] - a[:, 2]) * (c[:, 0] - a[:, 0])) / view.cell**2
    rng = np.random.default_rng(seed)
    # about two samples per covered plan pixel; a face smaller than half a pixel gets one with that probability
    k = np.minimum(np.floor(2 * area_px + rng.random(len(f), np.float32)), 4000).astype(np.int64)
    if k.sum() > max_samples:
        k = np.floor(k * (max_samples / k.sum()) + rng.random(len(f), np.float32)).astype(np.int64)
    idx = np.repeat(f, k, axis=0)  # (N, 3) vertex ids of each sample's face
    r1, r2 = np.sqrt(rng.random(len(idx), np.float32)), rng.random(len(idx), np.float32)
    w = (1 - r1, r1 * (1 - r2), r1 * r2)  # uniform barycentric samples

    def interp(values: np.ndarray) -> np.ndarray:
        return w[0] * values[idx[:, 0]] + w[1] * values[idx[:, 1]] + w[2] * values[idx[:, 2]]

    x, y, z = interp(v[:, 0]), interp(v[:, 1]), interp(v[:, 2])
    j = np.floor((x - view.x0) / view.cell).astype(np.int64)
    i = np.floor((view.z1 - z) / view.cell).astype(np.int64)
    inside = (i >= 0) & (i < view.h) & (j >= 0) & (j < view.w)
    order = np.flatnonzero(inside)[np.argsort(-y[inside])]  # the smallest y (highest point) is written last and wins
    cols = np.asarray(colors, np.float32)
    img = np.full((view.h, view.w, 3), 40, np.uint8)
    filled = np.zeros((view.h, view.w), np.uint8)
    idx = idx[order]
    w = tuple(t[order] for t in w)
    for ch in range(3):
        img[i[order], j[order], ch] = interp(cols[:, ch]).astype(np.uint8)
    filled[i[order], j[order]] = 255
    hole = (filled == 0) & (cv2.dilate(filled, np.ones((3, 3), np.uint8)) > 0)
    img[hole] = cv2.dilate(img * (filled > 0)[..., None], np.ones((3, 3), np.uint8))[hole]
    return (img.astype(np.float32) * 0.8).astype(np.uint8)  # dimmed so overlays stand out


def clearance_colors(clearance: np.ndarray, cap: float) -> list[str]:
    return colors_for(np.asarray(clearance, np.float64), 0.0, max(cap, 1e-6))


def footprint_rings(vertices: np.ndarray, faces: np.ndarray, view: PlanView, y_min: float,
                    y_max: float) -> list[np.ndarray]:
    """Outlines (world XZ rings) of the faces that reach into the height band y_min <= y <= y_max, rasterised on the
    view's grid: what an agent of that height collides with, seen from above."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    y = v[f, 1]
    f = f[(y.max(1) >= y_min) & (y.min(1) <= y_max)]
    mask = np.zeros((view.h, view.w), np.uint8)
    if len(f):
        tris = np.round(view.px(v[:, [0, 2]])[f]).astype(np.int32)  # (F, 3, 2) pixel corners
        cv2.fillPoly(mask, list(tris), 255)
        cv2.polylines(mask, list(tris), True, 255)  # faces seen edge-on (walls) still mark their line ...
        mask = cv2.dilate(mask, np.ones((3, 3), np.uint8))  # ... as an area, so that it has an outline
    contours, _ = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    return [np.stack([view.x0 + c[:, 0, 0] * view.cell, view.z1 - c[:, 0, 1] * view.cell], 1)
            for c in contours if len(c) >= 3]
