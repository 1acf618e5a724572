"""The scene report's sections, each built from one or a few stage artifacts (missing ones shown as missing)."""

from __future__ import annotations

import html
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.framework.notes import floor_joins
from panoworld.io.jsonio import read_json
from panoworld.tools.report import encode as enc
from panoworld.tools.report.page import Page, Section, figure, fmt, missing, slider, svg_figure, table
from panoworld.tools.report.scene_data import (
    ARTIFACTS,
    ROAM_IMAGES,
    ReportParams,
    SceneData,
    find_eval_json,
    subsample,
)
from panoworld.tools.report.topdown import PlanView, clearance_colors, footprint_rings, mesh_from_above


def _pmap(fn, items, workers: int = 4) -> list:
    with ThreadPoolExecutor(workers) as ex:  # OpenCV decodes and encodes without the GIL
        return list(ex.map(fn, items))


# ---------------------------------------------------------------- stages


def stage_rows(scene: SceneData, out_dir: Path, preset: str | None, run_results: list[dict] | None) -> tuple[list, str]:
    from panoworld.framework import pipeline as pl

    pipe = pl.Pipeline.load()
    note = ""
    states: dict[str, dict] = {}
    try:
        if preset is None:
            best = -1
            present = sum(scene.has(n) for n in pipe.order)
            for cand in [None, *[p for p in getattr(pipe, "presets", []) or []]]:
                rows = pl.status(scene.root, preset=cand, pipeline=pipe)
                n_up = sum(r["state"] == "up-to-date" for r in rows)
                if n_up > best:
                    best, states, preset = n_up, {r["stage"]: r for r in rows}, cand
                if n_up == present:  # the scene's own preset (scene.yaml) already explains every artifact
                    break
            note = (f"states for preset {preset or 'of scene.yaml, else default'} (the preset under which most stages are "
                    "up to date; --preset to choose)")
        else:
            states = {r["stage"]: r for r in pl.status(scene.root, preset=preset, pipeline=pipe)}
            note = f"states for preset {preset}"
    except Exception as e:  # a scene the runner rejects still gets a report
        note = f"stage states unavailable: {e}"
    ran = {r["stage"]: r for r in run_results or []}
    rows = []
    for name in pipe.order:
        m = scene.manifest(name)
        d = scene.dir(name)
        links = []
        if m is not None:
            links.append(f'<a href="{html.escape(_rel(d / "manifest.json", out_dir))}">manifest</a>')
        log = scene.art / "logs" / f"{name}.log"
        if log.is_file():
            links.append(f'<a href="{html.escape(_rel(log, out_dir))}">log</a>')
        st = states.get(name, {})
        if name in ran:
            action, reason = ran[name]["action"], ran[name]["reason"]
        elif m is None:
            action, reason = "missing", st.get("reason", "no artifact yet")
        else:
            action, reason = st.get("state", "present"), st.get("reason", "")
        secs = m.get("wall_s") if m else None
        mem = m.get("peak_rss_mb") if m else None
        cls = "bad" if action in ("failed", "stale") else "na" if action in ("missing", "skipped") else "ok"
        rows.append([name, f'<span class="{cls}">{html.escape(action)}</span>', reason,
                     f"{secs:.2f}" if isinstance(secs, (int, float)) else "-",
                     f"{mem:.0f}" if isinstance(mem, (int, float)) else "-",
                     (m or {}).get("finished", "-"), " ".join(links) or "-"])
    return rows, note


def _rel(path: Path, out_dir: Path) -> str:
    try:
        return Path(os.path.relpath(path, out_dir)).as_posix()
    except ValueError:
        return path.resolve().as_uri()


def section_stages(scene: SceneData, out_dir: Path, params: ReportParams, run_results) -> Section:
    rows, note = stage_rows(scene, out_dir, params.preset, run_results)
    t = table(["stage", "action", "reason", "seconds", "peak MB", "finished", "files"], rows, {3, 4}, {1, 6})
    src = "action and reason of the run that wrote this report" if run_results else note
    return Section("stages", "Stages", f'<p class="note">{html.escape(src)}; seconds and peak memory from each '
                   f"manifest.</p>{t}")


# ---------------------------------------------------------------- depth


def section_depth(scene: SceneData, params: ReportParams) -> Section:
    title = "Panorama and depth"
    if not scene.has("depth"):
        pano = next((scene.root / n for n in ("panorama.png", "panorama.jpg", "panorama.jpeg")
                     if (scene.root / n).is_file()), None)
        img = enc.read_rgb(pano, 2 * params.image_width) if pano else None
        if img is None:
            return missing("depth", title, "the depth stage has not run and the scene has no readable panorama")
        body = figure(enc.data_uri(img), "input panorama") + '<p class="note">depth: stage not run yet</p>'
        return Section("depth", title, body, missing=True)
    d = scene.dir("depth")
    w = 2 * params.image_width
    figs = []
    pano = enc.read_rgb(d / "panorama.png", w)
    if pano is not None:
        figs.append(figure(enc.data_uri(pano), "panorama (as used by the pipeline)"))
    info = scene.info("depth")
    try:
        img, lo, hi = enc.depth_image(d / "depth.npy", w)
        figs.append(figure(enc.data_uri(img), "depth (ray distance; black = invalid)", extra=enc.scale_bar(lo, hi, "m")))
    except (OSError, ValueError) as e:
        figs.append(f'<p class="note">depth.npy unreadable: {html.escape(str(e))}</p>')
    mask = enc.read_gray(d / "valid.png", w)
    if mask is not None:
        frac = float((mask > 0).mean())
        figs.append(figure(enc.data_uri(mask.astype(np.uint8), "png"), f"validity mask (white = valid, {100 * frac:.1f} %)"))
    rig = info.get("rig") or {}
    nadir = enc.read_rgb(d / "nadir_before_after.jpg")
    if nadir is not None:
        area = (rig.get("mask") or {}).get("sphere_fraction", 0.0)
        figs.append(figure(enc.data_uri(nadir), f"nadir before / after capture-rig removal ({rig.get('kind')}, "
                           f"{100 * area:.2f} % of the sphere)", small=True))
    keys = ("backend", "depth_range_m", "valid_fraction", "filled_pixels", "scale_factor", "camera_height_estimated_after")
    rows = [[k, fmt(info.get(k))] for k in keys if k in info]
    if rig:
        rows.append(["capture rig", rig.get("reason", "")])
    poles = info.get("pole_completion") or {}
    if poles.get("completed_fraction"):
        rows.append(["completed from planes", f"{100 * poles['completed_fraction']:.1f} % of pixels (floor "
                     f"{fmt(poles.get('floor_m'))} m below, ceiling {fmt(poles.get('ceiling_m'))} m above the camera)"])
    facts = table(["fact", "value"], rows)
    return Section("depth", title, f'<div class="row">{"".join(figs)}</div>{facts}')


# ---------------------------------------------------------------- plan view


def _plan_extent(scene: SceneData, traj: np.ndarray | None, nav) -> np.ndarray:
    pts = [np.zeros((1, 2))]
    if traj is not None:
        pts.append(traj[:, [0, 2], 3])
    if nav is not None and len(nav.vertices):
        pts.append(nav.vertices)
    return np.concatenate(pts)


def _load_mesh(scene: SceneData):
    """(valid-faces mesh or None, note)."""
    if not scene.has("mesh"):
        return None, "mesh: not run"
    from panoworld.geometry.erp_mesh import load_erp_mesh

    try:
        return load_erp_mesh(scene.dir("mesh")).valid_only(), ""
    except (OSError, ValueError, KeyError) as e:
        return None, f"mesh unreadable: {e}"


def _load_collider(scene: SceneData) -> tuple | None:
    """The asset's collider.obj mapped back to the canonical frame, with the agent it was checked for."""
    doc = scene.asset_doc()
    if not doc:
        return None
    import trimesh

    from panoworld.core.conventions import invert_pose, transform_points

    try:
        m = trimesh.load(scene.dir("asset") / doc["collider"], process=False, force="mesh")
    except (OSError, ValueError, KeyError):
        return None
    c_from_a = invert_pose(np.asarray(doc["asset_from_canonical"], np.float64))
    return transform_points(c_from_a, np.asarray(m.vertices)), np.asarray(m.faces), doc.get("agent", {})


@dataclass
class _PlanLayers:
    mesh: object
    nav: object
    """NavMesh or None."""
    traj: np.ndarray | None
    tdoc: dict
    tinfo: dict
    n_sectors: int
    collider: tuple | None = None
    """(vertices canonical, faces, agent dict) of the asset's collider.obj, when the asset stage ran."""
    captures: dict | None = None
    """A home's capture points {NAME: world_from_cam} (register artifact), None for a single panorama."""
    clips: list | None = None
    """Pose indices of each path of the trajectory (SceneData.clips), None when unreadable."""


def _draw_plan(view: PlanView, L: _PlanLayers, floor_y: float | None, reach_m: float, dot_r: float) -> list[str]:
    """Draw mesh, NavMesh and trajectory layers into view; return the legend entries."""
    legend = []
    if L.mesh is not None:
        cut = -0.2 if floor_y is None else floor_y - 1.9  # drop the ceiling: everything above ~1.9 m over the floor
        view.background(mesh_from_above(L.mesh.vertices, L.mesh.faces, L.mesh.colors, view, cut, max_samples=2_000_000))
    if L.nav is not None:
        if len(L.nav.vertices) and len(L.nav.triangles):
            view.triangles(L.nav.vertices, L.nav.triangles, "rgba(80,255,160,0.35)")
        view.polygon_rings(L.nav.rings, "rgba(40,200,120,0.28)", "#3ee08f", "NavMesh (walkable, eroded by the agent radius)")
        legend.append('<span><i class="sw" style="background:#3ee08f"></i>NavMesh</span>')
    if L.collider is not None and floor_y is not None:
        v, f, agent = L.collider
        band = (floor_y - float(agent.get("agent_height_m", 1.8)), floor_y - float(agent.get("step_height_m", 0.2)))
        view.polygon_rings(footprint_rings(v, f, view, *band), "rgba(255,80,60,0.18)", "#ff5a3c",
                           "collider (asset stage) in the agent's height band")
        legend.append('<span><i class="sw" style="background:#ff5a3c"></i>collider (agent height band)</span>')
    if L.traj is None:
        return legend
    xz = L.traj[:, [0, 2], 3]
    start = np.asarray((L.tinfo.get("plan") or {}).get("hub", xz[0]), np.float64).reshape(2)
    if L.tinfo.get("kind", L.tdoc.get("kind")) == "sector":
        view.sector_rays(start, L.n_sectors, reach_m)
        legend.append('<span><i class="sw" style="background:#ffd400"></i>sector boundaries (numbered)</span>')
    for idx in L.clips or [list(range(len(xz)))]:  # each path from its predecessor: no line across a home's cut
        if len(idx) > 1:
            view.polyline(xz[idx], "#ffffff", 2.0)
    view.headings(L.traj, 3 * dot_r * view.cell, "#ffffff")
    clearance = np.asarray(L.tdoc.get("clearance_m", [np.nan] * len(xz)), np.float64)
    cap = float(L.tdoc.get("clearance_cap_m", L.tinfo.get("clearance_cap_m", 0.5)) or 0.5)
    titles = [f"pose {i}: clearance {c:.3f} m" for i, c in enumerate(clearance)]
    view.dots(xz, clearance_colors(np.nan_to_num(clearance), cap), dot_r, titles)
    exempt = [i for i in L.tinfo.get("exempt_poses", []) if 0 <= i < len(xz)]
    if exempt:
        view.rings(xz[exempt], "#ff66ff", 2.2 * dot_r, "exempt from the clearance check")
        legend.append('<span><i class="sw" style="border-color:#ff66ff;border-width:2px"></i>exempt poses</span>')
    invalid = [p["index"] for p in L.tdoc.get("invalid_poses", L.tinfo.get("invalid_poses", [])) if p.get("index", -1) < len(xz)]
    if invalid:
        view.crosses(xz[invalid], "#ff2222", titles=[f"invalid pose {i}" for i in invalid])
        legend.append('<span><i class="sw" style="background:#ff2222"></i>invalid poses</span>')
    view.star(xz[0], "#ffffff", title="start (pose 0, the source panorama)")
    legend.append("<span>&#9734; start (pose 0)</span>")
    if L.captures:
        for name, T in L.captures.items():
            view.star(np.asarray(T)[[0, 2], 3], "#ffb020", title=f"capture point {name}")
        legend.append(f'<span style="color:#ffb020">&#9733;</span><span>{len(L.captures)} capture points '
                      f'({", ".join(map(html.escape, L.captures))})</span>')
    legend.append(f'<span>pose colour = clearance 0 .. {cap:.2f} m</span>{enc.scale_bar(0.0, cap, "m")}')
    return legend


def section_plan(scene: SceneData, params: ReportParams) -> Section:
    title = "Top-down: mesh, NavMesh and trajectory"
    nav = scene.navmesh()
    traj = scene.trajectory()
    if nav is None and traj is None and not scene.has("mesh"):
        return missing("plan", title, "mesh, navmesh and trajectory have not run yet")
    tdoc = scene.trajectory_doc() or {}
    mesh, note = _load_mesh(scene)
    notes = [note] if note else []
    notes += [f"{name}: not run" for name, x in (("navmesh", nav), ("trajectory", traj)) if x is None]
    n_sec = int((scene.manifest("trajectory") or {}).get("params", {}).get("sectors", 8))
    captures = scene.capture_points()
    layers = _PlanLayers(mesh, nav, traj, tdoc, scene.info("trajectory"), n_sec, _load_collider(scene),
                         captures if len(captures) >= 2 else None, scene.clips())
    floor_y = nav.floor_y if nav is not None else tdoc.get("floor_y")
    ext = _plan_extent(scene, traj, nav)
    view = PlanView(ext, margin_m=0.6)
    reach = float(np.max(np.linalg.norm(ext - (traj[0, [0, 2], 3] if traj is not None else 0), axis=1)))
    legend = _draw_plan(view, layers, floor_y, reach, 4.0)
    figs = svg_figure(view.svg(), "seen from above: x right, z (panorama centre) up")
    if traj is not None:
        xz = traj[:, [0, 2], 3]
        span = float(np.max(xz.max(0) - xz.min(0)))
        if span < 0.3 * view.cell * max(view.w, view.h):  # a short path: add a close-up of it
            zoom = PlanView(xz, margin_m=max(0.25, 0.2 * span), max_px=480)
            _draw_plan(zoom, layers, floor_y, reach, 5.0)
            figs += svg_figure(zoom.svg(), f"close-up of the trajectory ({span:.2f} m across)")
    tinfo = layers.tinfo
    keys = ("kind", "source", "frames", "stride", "step_m", "length_m", "step_cv", "closure_m", "min_clearance_m",
            "sectors_covered", "sectors_reachable", "agent_radius_m")
    facts = table(["trajectory", "value"], [[k, fmt(tinfo.get(k))] for k in keys if k in tinfo])
    ninfo = scene.info("navmesh")
    if ninfo.get("no_room"):
        nr = ninfo["no_room"]
        notes.append(f"no room to move: {nr.get('reason')}; decided: {nr.get('decision')} (agent radius "
                     f"{nr.get('agent_radius_m')} m instead of {nr.get('requested_agent_radius_m')} m)")
    if tinfo.get("plan", {}).get("approach_steps"):
        notes.append(f"the camera stands {fmt(tinfo.get('start_off_navmesh_m'))} m off the NavMesh: the first "
                     f"{tinfo['plan']['approach_steps']} steps walk onto it (exempt from the clearance check)")
    comps = ninfo.get("components") or []
    if len(comps) > 1:
        groups = "; ".join(f"{', '.join(c.get('capture_points') or []) or 'no capture point'} "
                           f"({fmt(c.get('area_m2'))} m²)" for c in comps)
        cuts = (tinfo.get("plan") or {}).get("cuts") or []
        joins = floor_joins(comps, scene.registration())
        notes.append(f"the home's floor is {len(comps)} NavMesh components that do not connect: {groups}"
                     + (f"; the trajectory cuts (no walk) {', '.join(' → '.join(c) for c in cuts)}" if cuts else "")
                     + (f"; {'; '.join(joins)}" if joins else ""))
    nfacts = table(["navmesh", "value"], [[k, fmt(ninfo.get(k))] for k in
                                          ("area_m2", "num_triangles", "num_holes", "floor_y", "camera_on_navmesh") if k in ninfo]
                   + ([["components", str(len(comps))]] if comps else []))
    body = (f'<div class="legend">{"".join(legend)}</div><div class="row">{figs}</div><div class="row">{facts}{nfacts}</div>'
            + "".join(f'<p class="note">{html.escape(n)}</p>' for n in notes))
    return Section("plan", title, body, missing=traj is None and nav is None)


# ---------------------------------------------------------------- frames


def _fill_fractions(masks: list[Path]) -> list[float | None]:
    def one(path):
        m = enc.read_gray(path)
        return None if m is None else float((m == 0).mean())

    return _pmap(one, masks)


def _bar_chart(values: list[float | None], key: str, marker_index: list[int] | None, label: str,
               scale: float = 100.0, unit: str = "%") -> str:
    """SVG bars of values (fractions) per frame with a marker the slider moves."""
    n = max(len(values), 1)
    W, H, bw = 600, 90, 600 / n
    vmax = max([v for v in values if v is not None] + [1e-6])
    bars = "".join(
        f'<rect x="{i * bw:.1f}" y="{H - 70 * (v / vmax):.1f}" width="{max(bw - 1, 0.5):.1f}" height="{70 * (v / vmax):.1f}" '
        f'fill="#4a7bd0"><title>frame {i}: {scale * v:.2f} {unit}</title></rect>'
        for i, v in enumerate(values) if v is not None)
    xs = json.dumps([round(i * bw, 1) for i in marker_index or []])
    marker = (f'<rect data-marker="{key}" data-xs=\'{xs}\' x="0" y="0" width="{max(bw, 2):.1f}" height="{H}" '
              'fill="rgba(255,120,0,0.35)"/>') if marker_index else ""
    return (f'<svg viewBox="0 0 {W} {H + 14}" width="{W}" height="{H + 14}" xmlns="http://www.w3.org/2000/svg">'
            f'<rect x="0" y="0" width="{W}" height="{H}" fill="#fff"/>{bars}{marker}'
            f'<text x="2" y="{H + 12}" font-size="11">{html.escape(label)} '
            f"(max {scale * vmax:.2f} {unit})</text></svg>")


def section_frames(scene: SceneData, page: Page, params: ReportParams) -> Section:
    title = "Conditions, masks and video frames"
    cond, video = scene.conditions(), scene.video()
    if cond is None and video is None:
        return missing("frames", title, "conditions and video have not run yet")
    cframes = [] if cond is None else [cond.rgb.root / p for p in cond.rgb.paths]
    cmasks = [] if cond is None else [cond.mask.root / p for p in cond.mask.paths]
    vframes = [] if video is None else video.rgb
    n = max(len(cframes), len(vframes))
    idx = subsample(n, params.max_frames)
    w = params.image_width
    cols: dict[str, list] = {}
    jobs = []
    if cframes:
        jobs += [("condition", cframes[i], "rgb") for i in idx if i < len(cframes)]
        jobs += [("mask", cmasks[i], "mask") for i in idx if i < len(cframes)]
    if vframes:
        jobs += [("video", vframes[i], "rgb") for i in idx if i < len(vframes)]

    def load(job):
        col, path, kind = job
        if kind == "mask":
            m = enc.read_gray(path, w)
            return col, None if m is None else enc.data_uri((m > 0).astype(np.uint8) * 255, "png")
        img = enc.read_rgb(path, w)
        return col, None if img is None else enc.data_uri(img)

    for col, uri in _pmap(load, jobs):
        cols.setdefault(col, []).append(uri)
    fills = _fill_fractions(cmasks)
    text = [f"frame {i} of {n}" + (f" · fill {100 * fills[i]:.2f} % (mask = 0: to be generated)"
                                    if i < len(fills) and fills[i] is not None else "") for i in idx]
    page.data["frames"] = {"images": cols, "text": {"label": text}}
    captions = {"condition": "warped condition (conditions/rgb)", "mask": "mask (white = seen from the source)",
                "video": "generated video frame (video/frames)"}
    figs = "".join(figure(uris[0] or "", captions[col], slot=f"frames:{col}") for col, uris in cols.items() if uris)
    notes = []
    if cond is None:
        notes.append("conditions: not run")
    if video is None:
        notes.append("video: not run")
    if len(idx) < n:
        notes.append(f"{len(idx)} of {n} frames embedded (every ~{n / len(idx):.1f}th; --max-frames to change)")
    chart = _bar_chart(fills, "frames", idx, "fill fraction per frame") if fills else ""
    vinfo = scene.info("video")
    facts = table(["video", "value"], [[k, fmt(vinfo.get(k))] for k in
                                       ("backend", "upscale", "num_frames", "height", "width", "fps", "hole_fraction") if k in vinfo])
    body = (slider("frames", len(idx), "label") + f'<div class="row">{figs}</div>{chart}'
            + "".join(f'<p class="note">{html.escape(x)}</p>' for x in notes) + facts)
    return Section("frames", title, body)


# ---------------------------------------------------------------- poses


def section_poses(scene: SceneData, params: ReportParams) -> Section:
    title = "Poses: recovered vs planned"
    if not scene.has("poses"):
        return missing("poses", title, "the poses stage has not run yet")
    pa = scene.poses_artifact()
    ref = scene.video_poses()
    ref_name = "video.json (the poses the video was generated along)"
    if ref is None:
        ref, ref_name = scene.trajectory(), "trajectory.json"
    if pa is None:
        return missing("poses", title, "poses.json is unreadable")
    est, reg = pa.world_from_cam, pa.registered
    unreg = [i for i in range(len(est)) if i >= len(reg) or not reg[i]]
    pts = [est[:, [0, 2], 3]] + ([ref[:, [0, 2], 3]] if ref is not None else [])
    view = PlanView(np.concatenate(pts), margin_m=0.25, max_px=480)
    view.items.append(f'<rect x="0" y="0" width="{view.w}" height="{view.h}" fill="#fff"/>')
    if ref is not None:
        view.polyline(ref[:, [0, 2], 3], "#888888", 3.0, dash="5 3")
    view.polyline(est[:, [0, 2], 3], "#1f6fd1", 1.8)
    ok = [i for i in range(len(est)) if i not in set(unreg)]
    view.dots(est[ok][:, [0, 2], 3], "#1f6fd1", 3.0, stroke="#1f6fd1")
    if unreg:
        view.crosses(est[unreg][:, [0, 2], 3], "#d11f1f", titles=[f"frame {i}: not registered (pose from the plan)" for i in unreg])
    view.star(est[0, [0, 2], 3], "#ffd400", title="frame 0")
    legend = ('<div class="legend"><span><i class="sw" style="background:#888"></i>planned (' + html.escape(ref_name)
              + ')</span><span><i class="sw" style="background:#1f6fd1"></i>recovered</span>'
              '<span><i class="sw" style="background:#d11f1f"></i>unregistered</span></div>')
    figs = svg_figure(view.svg(), "seen from above: x right, z up", legend)
    err_chart = ""
    if ref is not None and len(ref) == len(est):
        err = np.linalg.norm(est[:, :3, 3] - ref[:, :3, 3], axis=1)
        err_chart = _bar_chart([float(e) for e in err], "poses-err", None, "position error per frame vs plan", 1000.0, "mm")
    info = scene.info("poses")
    metrics = info.get("metrics_vs_planned") or {}
    rows = [[k, fmt(info.get(k))] for k in ("backend", "num_frames", "num_registered", "sim3_scale", "depth_source") if k in info]
    rows.append(["unregistered frames", ", ".join(map(str, unreg)) or "none"])
    rows += [[f"{k} (vs plan)", fmt(v)] for k, v in metrics.items()]
    body = f'<div class="row">{figs}<div>{table(["poses", "value"], rows)}{err_chart}</div></div>'
    return Section("poses", title, body)


# ---------------------------------------------------------------- eval




def section_eval(scene: SceneData, params: ReportParams) -> Section:
    title = "Evaluation against ground truth"
    has_gt = (scene.root / "gt" / "gt.json").is_file()
    path = find_eval_json(scene, params.eval_json)
    if path is None:
        why = ("no saved evaluation: run `python runner.py report SCENE --eval` (or `runner.py eval SCENE --out "
               "SCENE/artifacts/report/eval.json`)" if has_gt else "no ground truth (gt/gt.json): nothing to evaluate against")
        return missing("eval", title, why)
    try:
        rep = read_json(path)
        stages = rep["stages"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        return missing("eval", title, f"{path}: unreadable evaluation ({e})")
    targets = rep.get("targets", {})
    rows = []
    for stage, metrics in stages.items():
        if not isinstance(metrics, dict) or metrics.get("available") is False:  # a stage eval could not score
            rows.append([stage, "-", fmt(metrics), "", ""])
            continue
        for k, (name, value) in enumerate(metrics.items()):
            t = (targets.get(stage) or {}).get(name)
            met = None if t is None else t.get("met")
            ok = "" if met is None else '<span class="ok">yes</span>' if met else '<span class="bad">no</span>'
            val = fmt(value) if not isinstance(value, list) else ", ".join(map(str, value))[:80]
            rows.append([stage if k == 0 else "", name, val[:200], t["target"] if t else "", ok])
    newest = max((m.get("finished", "") for m in (scene.manifest(s) for s in _stage_names()) if m), default="")
    stale = ""
    mtime = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(path.stat().st_mtime))
    if newest and newest[:19] > mtime:
        stale = f'<p class="note bad">artifacts changed after this evaluation ({mtime} UTC): rerun with --eval</p>'
    return Section("eval", title, f'<p class="note">from {html.escape(str(path))} (written {mtime} UTC)</p>{stale}'
                   + table(["stage", "metric", "value", "target", "met"], rows, {2}, {4}))


def _stage_names() -> list[str]:
    return ["depth", "register", "mesh", "navmesh", "trajectory", "conditions", "video", "poses", "gaussians"]


def run_eval(scene_root: Path) -> Path:
    """Run `runner.py eval` on the scene and save its JSON as artifacts/report/eval.json; return the path."""
    from panoworld.tools.eval.cli import evaluate
    report, _ = evaluate(scene_root, progress=True, roam_images=Path(scene_root) / ARTIFACTS / ROAM_IMAGES)
    out = Path(scene_root) / ARTIFACTS / "report" / "eval.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    return out
