"""The scene report's home section: every capture panorama, how registration joined it or why it did not."""

from __future__ import annotations

import html
import math

import numpy as np

from panoworld.register.artifact import unplaced_groups
from panoworld.tools.report import encode as enc
from panoworld.tools.report.page import Page, Section, figure, fmt, missing, slider, svg_figure, table
from panoworld.tools.report.scene_data import ReportParams, SceneData, subsample
from panoworld.tools.report.topdown import PlanView

TITLE = "Home: capture points and registration"
EDGE_COLORS = {"depth": "#1f6fd1", "floor": "#e07b00", "bearing": "#8e44ad", "layout": "#16a085",
               "direction": "#7f8c8d"}
"""Stroke of a registration tree edge by kind (register/graph.py); a direction edge is drawn dashed."""
LABEL_MERGE_M = 0.3
"""Capture points this close share one name label on the plan."""


def is_home(scene: SceneData) -> bool:
    """Whether the scene is a home (its registration lists two or more panoramas)."""
    reg = scene.registration()
    return bool(reg) and len(reg.get("panoramas") or {}) >= 2


def fit_psnr(scene: SceneData) -> tuple[dict[str, float], int | None]:
    """({NAME: PSNR dB of the gaussians stage's colour-fit render at that capture pose against its panorama},
    the fit's render height) from the gaussians manifest's color_fit; ({}, None) where no fit ran."""
    fit = scene.info("gaussians").get("color_fit") or {}
    rmse = fit.get("rmse_after") or {}
    return ({n: 20 * math.log10(1 / r) for n, r in rmse.items() if isinstance(r, (int, float)) and r > 0},
            fit.get("height"))


def _status(p: dict) -> tuple[str, str]:
    """(HTML status cell, plain text) of one panorama's registration entry."""
    if not p.get("registered"):
        return '<span class="bad">not registered</span>', "not registered"
    src = p.get("source") or "estimated"
    return f'<span class="ok">{html.escape(src)}</span>', src


def _joined_by(p: dict) -> str:
    """What placed one panorama: its parent in the registration tree by which edge, poses.json, or the world frame."""
    if not p.get("registered"):
        return "-"
    if p.get("parent") is None:
        return "poses.json" if p.get("source") == "given" else "world frame"
    return f"{p['parent']} ({p.get('edge', '?')}, {p.get('inliers', '?')} inliers)"


def _plan(scene: SceneData, reg: dict, poses: dict[str, np.ndarray]) -> tuple[str, str]:
    """(SVG figure, legend HTML) of the capture points from above: NavMesh, registration tree edges, names."""
    nav = scene.navmesh()
    xz = {n: np.asarray(T)[[0, 2], 3] for n, T in poses.items()}
    pts = list(xz.values()) + ([nav.vertices] if nav is not None and len(nav.vertices) else [])
    view = PlanView(np.concatenate([np.reshape(p, (-1, 2)) for p in pts]) if pts else np.zeros((1, 2)), margin_m=0.8)
    view.items.append(f'<rect x="0" y="0" width="{view.w}" height="{view.h}" fill="#1d2733"/>')
    legend = []
    if nav is not None:
        view.polygon_rings(nav.rings, "rgba(40,200,120,0.28)", "#3ee08f", "NavMesh (walkable, eroded by the agent radius)")
        legend.append('<span><i class="sw" style="background:#3ee08f"></i>NavMesh</span>')
    kinds = set()
    for name, p in (reg.get("panoramas") or {}).items():
        parent = p.get("parent")
        if name in xz and parent in xz:
            kind = p.get("edge", "")
            kinds.add(kind)
            view.polyline(np.stack([xz[parent], xz[name]]), EDGE_COLORS.get(kind, "#cccccc"), 3.0,
                          dash="6 4" if kind == "direction" else "")
    legend += [f'<span><i class="sw" style="background:{EDGE_COLORS.get(k, "#cccccc")}"></i>{html.escape(k)} edge</span>'
               for k in sorted(kinds)]
    view.headings(np.stack([np.asarray(T, np.float64) for T in poses.values()]), 0.5, "#ffb020")
    for name, p in xz.items():
        view.star(p, "#ffb020", title=f"capture point {name}")
    for group in _close_groups(xz, LABEL_MERGE_M):
        view.label(xz[group[0]], ", ".join(group))
    legend.append('<span style="color:#ffb020">&#9733;</span><span>registered capture points (a tick: where the '
                  "panorama's centre looks)</span>")
    return svg_figure(view.svg(), "registered capture points from above (x right, z up), joined by the edges that "
                      "placed them"), "".join(legend)


def _pair_matrix(reg: dict, names: list[str], max_px: int = 640) -> str:
    """An SVG figure of every pair tried: a cell per pair coloured by the edge it gave (EDGE_COLORS), grey by its floor
    inliers where it gave none, the registration tree's edges outlined; each cell's title holds the pair's figures."""
    at = {n: i for i, n in enumerate(names)}
    k = len(names)
    c = max(6, min(22, (max_px - 90) // max(k, 1)))
    m = 90  # room for the names
    tree = {frozenset((n, p["parent"])) for n, p in (reg.get("panoramas") or {}).items() if p.get("parent")}
    items = []
    for r in reg.get("pairs") or []:
        if r.get("a") not in at or r.get("b") not in at:
            continue
        i, j = sorted((at[r["a"]], at[r["b"]]))
        fl = int(r.get("floor_inliers") or 0)
        fill = EDGE_COLORS.get(r.get("edge") or "", "")
        if not fill:
            g = int(235 - 150 * min(fl, 12) / 12)  # chance floor fits keep up to about 8 inliers
            fill = f"rgb({g},{g},{g})"
        why = r.get("floor_refused") or r.get("depth_refused") or ""
        title = (f"{r['a']} - {r['b']}: {'edge ' + r['edge'] if r.get('edge') else 'no edge'}; depth-backed "
                 f"{r.get('inliers')} inliers at {fmt(r.get('consistency'))} consistency, floor {fl} inliers, bearing "
                 f"{r.get('bearing_inliers')} inliers" + (f"; refused: {why}" if why else ""))
        stroke = ' stroke="#000" stroke-width="2"' if frozenset((r["a"], r["b"])) in tree else ""
        for x, y in ((j, i), (i, j)):
            items.append(f'<rect x="{m + x * c}" y="{m + y * c}" width="{c - 1}" height="{c - 1}" fill="{fill}"{stroke}>'
                         f"<title>{html.escape(title)}</title></rect>")
            if c >= 16:
                items.append(f'<text x="{m + x * c + c / 2 - 0.5:.1f}" y="{m + y * c + c * 0.68:.1f}" font-size="9" '
                             f'text-anchor="middle" fill="#000">{fl}</text>')
    for n, i in at.items():
        items.append(f'<text x="{m - 4}" y="{m + i * c + c * 0.7:.1f}" font-size="11" text-anchor="end">{html.escape(n)}</text>')
        items.append(f'<text transform="translate({m + i * c + c * 0.7:.1f},{m - 4}) rotate(-60)" font-size="11">'
                     f"{html.escape(n)}</text>")
    size, wide = m + k * c + 2, m + k * c + 50  # the last column's slanted name runs past the grid
    svg = (f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {wide} {size}" width="{wide}" height="{size}">'
           f'<rect x="0" y="0" width="{wide}" height="{size}" fill="#fff"/>' + "".join(items) + "</svg>")
    return svg_figure(svg, "every pair tried: coloured by the edge it gave, else grey by its floor inliers (the number; "
                      "darker = more), the edges that placed a panorama outlined; hover a cell for its figures")


def _close_groups(xz: dict[str, np.ndarray], radius_m: float) -> list[list[str]]:
    """The names of capture points within radius_m of the first of their group (one label for points that stand
    together), in name order."""
    groups: list[list[str]] = []
    for n in xz:
        g = next((g for g in groups if np.linalg.norm(xz[g[0]] - xz[n]) <= radius_m), None)
        if g is None:
            groups.append([n])
        else:
            g.append(n)
    return groups


def _slider(scene: SceneData, page: Page, params: ReportParams, names: list[str], status: dict[str, str]) -> str:
    """A slider over the capture panoramas as the pipeline uses them (rig removed) and their depths."""
    dirs = scene.home_depth_dirs() or {}
    shown = [names[i] for i in subsample(len(names), params.max_frames)]
    w = params.image_width
    pano, depth, text = [], [], []
    for n in shown:
        d = dirs.get(n)
        img = enc.read_rgb(d / "panorama.png", w) if d is not None else None
        pano.append(enc.data_uri(img) if img is not None else "")
        try:
            dimg, lo, hi = enc.depth_image(d / "depth.npy", w)
            depth.append(enc.data_uri(dimg))
            rng = f"depth {lo:.2f}-{hi:.2f} m"
        except (OSError, ValueError, TypeError):
            depth.append("")
            rng = "no depth"
        text.append(f"{n}: {status[n]} · {rng}")
    if not any(pano):
        return '<p class="note">the depth artifact holds no capture panorama to show</p>'
    page.data["home"] = {"images": {"panorama": pano, "depth": depth}, "text": {"label": text}}
    more = (f'<p class="note">{len(shown)} of {len(names)} panoramas on the slider (--max-frames to change)</p>'
            if len(shown) < len(names) else "")
    return (slider("home", len(shown), "label", what="panorama")
            + '<div class="row">' + figure(pano[0], "capture panorama (rig removed, as the pipeline uses it)",
                                            slot="home:panorama")
            + figure(depth[0], "its depth (turbo, 2nd-98th percentile; black = invalid)", slot="home:depth")
            + "</div>" + more)


def section_home(scene: SceneData, page: Page, params: ReportParams) -> Section:
    reg = scene.registration()
    if not reg:
        return missing("home", TITLE, "the register stage has not run yet")
    pans: dict = reg.get("panoramas") or {}
    names = list(pans)
    poses = {n: T for n, T in scene.capture_points().items() if (pans.get(n) or {}).get("registered")}
    info = scene.info("register")
    depth_info = (scene.info("depth").get("home") or {}).get("panoramas") or {}
    nav_info = scene.info("navmesh")
    on_nav = nav_info.get("capture_points_on_navmesh") or {}
    comp = nav_info.get("capture_components") or {}
    psnr, fit_height = fit_psnr(scene)
    status = {n: _status(p)[1] for n, p in pans.items()}
    rows = []
    for n, p in pans.items():
        d = depth_info.get(n) or {}
        rig = d.get("rig") or {}
        masked = (d.get("plausibility") or {}).get("masked_sphere_fraction")
        reason = str(p.get("reason") or "")
        short = reason if len(reason) <= 240 else reason[:237] + "..."
        where = f" (component {comp[n]})" if comp.get(n) is not None else ""
        nav = "-" if n not in on_nav else ("yes" if on_nav[n] else "off it, snapped") + where
        rows.append([n, _status(p)[0], _joined_by(p),
                     f"{rig.get('kind')} ({100 * (rig.get('mask') or {}).get('sphere_fraction', 0):.2f} % of the sphere)"
                     if rig.get("found") else "none found",
                     "-" if masked is None else f"{100 * masked:.1f} %", nav,
                     f"{psnr[n]:.2f}" if n in psnr else "-",
                     f'<span title="{html.escape(reason)}">{html.escape(short)}</span>' if reason else ""])
    header = ["panorama", "placed", "joined to (edge, inliers)", "capture rig removed", "layout masked as implausible (of the sphere)",
              "on NavMesh", f"capture pose PSNR dB ({fit_height} rows)" if fit_height else "capture pose PSNR dB",
              "why not registered"]
    n_reg = sum(bool(p.get("registered")) for p in pans.values())
    summary = (f"{n_reg} of {len(names)} panoramas registered ({sum(p.get('source') == 'given' for p in pans.values())} "
               f"given in poses.json); {fmt(info.get('pairs_accepted'))} of {fmt(info.get('pairs_tried'))} pairs tried "
               "were accepted as edges.")
    groups = unplaced_groups(pans)
    notes = [summary]
    if groups:
        notes.append("Not placed, by group (panoramas joined to each other but to no registered one): "
                     + "; ".join(", ".join(g) for g in groups) + ". A pose in SCENE/poses.json for one panorama of "
                     "each group places that group; `runner.py split SCENE` makes each group a home of its own "
                     "(docs/multi.md).")
    tilted = {n: p["levelled_tilt_deg"] for n, p in pans.items() if p.get("levelled_tilt_deg") is not None}
    if tilted:
        notes.append("Taken with the camera not level, levelled for registration (the tilt its floor shows; its pose "
                     "holds it, the scene is built as taken): " + ", ".join(f"{n} {d:.1f}°" for n, d in tilted.items())
                     + " (docs/multi.md).")
    built_level = {n: (d.get("level") or {}).get("tilt_deg") for n, d in depth_info.items()
                   if isinstance(d, dict) and (d.get("level") or {}).get("level_from_cam")}
    if built_level:
        listed = ", ".join(f"{n} {float(d):.1f}°" for n, d in built_level.items())
        notes.append("Taken off level, levelled by the depth stage (the tilt its vertical lines read, its floor agreeing "
                     f"where it shows one; the scene is built level): {listed} (docs/conventions.md).")
    if psnr:
        notes.append("Capture pose PSNR: the gaussians stage's colour-fit render at each capture pose against that "
                     "panorama (cleaned), from its manifest's color_fit.")
    plan, legend = _plan(scene, reg, poses) if poses else ("", "")
    body = ("".join(f'<p class="note">{html.escape(x)}</p>' for x in notes)
            + (f'<div class="legend">{legend}</div><div class="row">{plan}</div>' if plan else "")
            + table(header, rows, {6}, {1, 7}) + f'<div class="row">{_pair_matrix(reg, names)}</div>'
            + _slider(scene, page, params, names, status))
    return Section("home", TITLE, body)
