"""The paper's table layouts from per-scene reports: means with scene counts and which scenes lacked each metric."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from panoworld.tools.eval.common import is_unavailable

# (column title, report stage, metric key)
VIDEO_COLUMNS = [("PSNR", "video", "psnr"), ("SSIM", "video", "ssim"), ("LPIPS", "video", "lpips"),
                 ("WS-PSNR", "video", "ws_psnr"), ("FVD", "dist", "fvd"), ("FID", "dist", "fid"),
                 ("ATE", "poses", "ate"), ("RRE (deg)", "poses", "rre"), ("RTE", "poses", "rte")]
ZERO_SHOT_COLUMNS = [("FID", "dist", "fid"), ("Loop (deg, lower better)", "loop", "loop_flow_deg"),
                     ("LPIPS-Loop", "loop", "lpips_loop"), ("ATE", "poses", "ate"), ("RRE (deg)", "poses", "rre"),
                     ("RTE", "poses", "rte")]
POSE_COLUMNS = [("ATE", "poses", "ate"), ("ATE-RMSE", "poses", "ate_rmse"), ("RPE_t", "poses", "rpe_t"),
                ("RPE_r (deg)", "poses", "rpe_r")]
GS_COLUMNS = [("PSNR ctx", "gaussians", "context_psnr"), ("PSNR nov", "gaussians", "novel_psnr"),
              ("SSIM ctx", "gaussians", "context_ssim"), ("SSIM nov", "gaussians", "novel_ssim"),
              ("LPIPS ctx", "gaussians", "context_lpips"), ("LPIPS nov", "gaussians", "novel_lpips")]
ROAM_COLUMNS = [("PSNR 0 m", "roam", "d0_erp_psnr"), ("PSNR ~0.5 m", "roam", "d0.5_erp_psnr"),
                ("PSNR ~1 m", "roam", "d1_erp_psnr"), ("PSNR ~2 m", "roam", "d2_erp_psnr"),
                ("PSNR far", "roam", "far_erp_psnr"), ("SSIM ~1 m", "roam", "d1_erp_ssim"),
                ("SSIM ~2 m", "roam", "d2_erp_ssim"), ("cov ~1 m", "roam", "d1_erp_coverage"),
                ("cov ~2 m", "roam", "d2_erp_coverage"), ("cov far", "roam", "far_erp_coverage"),
                ("pinhole PSNR ~1 m", "roam", "d1_pinhole_psnr"), ("pinhole PSNR ~2 m", "roam", "d2_pinhole_psnr")]
ROAM_COVERAGE_COLUMNS = [("PSNR 0 m vs input", "roam", "d0_erp_psnr_vs_input"), ("cov 0 m", "roam", "d0_erp_coverage"),
                         ("cov ~0.5 m", "roam", "d0.5_erp_coverage"), ("cov ~1 m", "roam", "d1_erp_coverage"),
                         ("cov ~2 m", "roam", "d2_erp_coverage"), ("cov far", "roam", "far_erp_coverage")]

GT_TRACK_REASON = ("GT track (ref.) needs COLMAP on the ground-truth frames of each scene: run the poses stage on a "
                   "video of ground-truth frames (not automated yet)")


@dataclass
class Cell:
    mean: float | None
    n: int
    lacking: list[str]
    reason: str | None = None

    def text(self, digits: int = 4) -> str:
        if self.mean is None:
            return "n/a"
        return f"{self.mean:.{digits}f}"


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[tuple[str, list[Cell]]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"title": self.title, "columns": self.columns, "notes": self.notes,
                "rows": [{"label": label, "cells": {c: {"mean": cell.mean, "n": cell.n, "lacking": cell.lacking,
                                                         "reason": cell.reason}
                                                    for c, cell in zip(self.columns, cells)}}
                         for label, cells in self.rows]}

    def _grid(self) -> list[list[str]]:
        grid = [["", *self.columns]]
        for label, cells in self.rows:
            grid.append([label, *[c.text(2 if "PSNR" in col or col in ("FID", "FVD") else 4)
                                  for c, col in zip(cells, self.columns)]])
        return grid

    def text(self) -> str:
        grid = self._grid()
        widths = [max(len(r[i]) for r in grid) for i in range(len(grid[0]))]
        lines = [self.title, *("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in grid)]
        return "\n".join(lines + [f"  {n}" for n in self.notes])

    def markdown(self) -> str:
        grid = self._grid()
        lines = [f"**{self.title}**", "", "| " + " | ".join(grid[0]) + " |", "|" + "---|" * len(grid[0])]
        lines += ["| " + " | ".join(r) + " |" for r in grid[1:]]
        return "\n".join(lines + [""] + [f"- {n}" for n in self.notes])


def _value(report: dict, dist: dict, stage: str, key: str) -> tuple[float | None, str | None]:
    if stage == "dist":
        v = dist.get(key)
    else:
        section = report.get("stages", {}).get(stage)
        if section is None:
            return None, f"{stage} not evaluated"
        if is_unavailable(section):
            return None, section["reason"]
        v = section.get(key)
    if is_unavailable(v):
        return None, v["reason"]
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return float(v), None
    return None, f"{key} = {v!r}"


def _cell(reports: list[dict], dist: dict, stage: str, key: str) -> Cell:
    if stage == "dist":  # one value for the whole group
        v, why = _value({}, dist, stage, key)
        return Cell(v, len(reports) if v is not None else 0, [] if v is not None else [r["unit"] for r in reports], why)
    vals, lacking, reason = [], [], None
    for r in reports:
        v, why = _value(r, dist, stage, key)
        if v is None:
            lacking.append(r["unit"])
            reason = reason or why
        else:
            vals.append(v)
    return Cell(sum(vals) / len(vals) if vals else None, len(vals), lacking, reason)


def _rows(groups: dict[str, list[dict]], dists: dict[str, dict], columns, label) -> list[tuple[str, list[Cell]]]:
    return [(label(name, reps), [_cell(reps, dists.get(name, {}), st, k) for _, st, k in columns])
            for name, reps in groups.items()]


def _notes(table: Table) -> list[str]:
    notes = []
    for label, cells in table.rows:
        for col, cell in zip(table.columns, cells):
            if cell.lacking:
                who = ", ".join(cell.lacking[:6]) + (" ..." if len(cell.lacking) > 6 else "")
                notes.append(f"{label} / {col}: lacking in {len(cell.lacking)} scene(s) ({who}): {cell.reason}")
    return notes


def group_key(report: dict) -> str:
    """Rows of the paper's tables: trajectory stride r (and kind when not the default sector)."""
    s = report.get("setting") or {}
    kind = s.get("kind")
    stride = s.get("stride")
    key = f"r={stride}" if stride is not None else "r=?"
    return key if kind in (None, "sector") else f"{key} {kind}"


def build_tables(reports: list[dict], dists: dict[str, dict[str, dict]] | None = None) -> list[Table]:
    """The paper's tables from unit reports (each with "unit", "reference", "setting", "stages"):

    - video generation (InteriorGS protocol: scenes with ground-truth frames or a synthetic mesh), rows per stride,
      with the GT-track reference row;
    - zero-shot (RealSee3D protocol: plan-only scenes), rows per stride/kind;
    - pose estimation (ATE, ATE-RMSE, RPE_t, RPE_r) and 3DGS rendering (N@N context / novel) per stride.
    dists: {"gt" | "plan": {group: distribution_metrics(...)}} for FID/FVD.
    """
    dists = dists or {}
    gt_reports = [r for r in reports if r.get("reference") in ("synthetic", "frames")]
    plan_reports = [r for r in reports if r.get("reference") == "plan-only"]

    def groups(reps):
        out: dict[str, list[dict]] = {}
        for r in sorted(reps, key=lambda r: (group_key(r), r["unit"])):
            out.setdefault(group_key(r), []).append(r)
        return out

    def label(name, reps):
        backend = sorted({str((r.get("setting") or {}).get("video_backend")) for r in reps})
        return f"ours ({'/'.join(backend)}) {name} [{len(reps)} scenes]"

    tables = []
    if gt_reports:
        g = groups(gt_reports)
        t = Table("Panoramic video generation (ground-truth scenes; the paper's Table: video_main)",
                  [c for c, _, _ in VIDEO_COLUMNS])
        for name, reps in g.items():
            t.rows.append((f"GT track (ref.) {name}", [Cell(None, 0, [], GT_TRACK_REASON) for _ in VIDEO_COLUMNS]))
            t.rows += _rows({name: reps}, dists.get("gt", {}), VIDEO_COLUMNS, label)
        t.notes = [GT_TRACK_REASON] + [n for n in _notes(t) if not n.startswith("GT track")]
        tables.append(t)
        t = Table("Pose estimation on the generated frames (the paper's Table: recon_gt layout)",
                  [c for c, _, _ in POSE_COLUMNS])
        t.rows = _rows(g, {}, POSE_COLUMNS, label)
        t.notes = _notes(t)
        tables.append(t)
        t = Table("3DGS rendering, N@N context / novel views (the paper's Table: recon_render)",
                  [c for c, _, _ in GS_COLUMNS])
        t.rows = _rows(g, {}, GS_COLUMNS, label)
        settings = sorted({str(r["stages"]["gaussians"].get("setting")) for r in gt_reports
                           if isinstance(r["stages"].get("gaussians"), dict) and "setting" in r["stages"]["gaussians"]})
        t.notes = ([f"setting: {', '.join(settings)}"] if settings else []) + _notes(t)
        tables.append(t)
    synthetic = [r for r in reports if r.get("reference") == "synthetic"]
    if synthetic:
        t = Table("Roam: Gaussians at random NavMesh poses by distance from the capture point, ERP vs the anti-aliased "
                  "ground truth (docs/evaluation.md)", [c for c, _, _ in ROAM_COLUMNS])
        t.rows = _rows(groups(synthetic), {}, ROAM_COLUMNS, label)
        t.notes = _notes(t)
        tables.append(t)
    no_mesh = [r for r in reports if r.get("reference") != "synthetic"]
    if no_mesh and any(isinstance(r.get("stages", {}).get("roam"), dict) and "d0_erp_coverage" in r["stages"]["roam"]
                       for r in no_mesh):
        t = Table("Roam coverage, scenes without a ground-truth mesh (alpha > 0.5; distance 0 also vs the input)",
                  [c for c, _, _ in ROAM_COVERAGE_COLUMNS])
        t.rows = _rows(groups(no_mesh), {}, ROAM_COVERAGE_COLUMNS, label)
        t.notes = _notes(t)
        tables.append(t)
    if plan_reports:
        t = Table("Zero-shot, plan-only scenes (the paper's Table: video_realsee)", [c for c, _, _ in ZERO_SHOT_COLUMNS])
        t.rows = _rows(groups(plan_reports), dists.get("plan", {}), ZERO_SHOT_COLUMNS, label)
        t.notes = ["Loop: our loop-closure error (flow between first and last frame, degrees, lower is better); the "
                   "paper's Loop column follows OmniRoam and is higher-is-better, so the numbers are not comparable "
                   "(docs/evaluation.md)"] + _notes(t)
        tables.append(t)
    return tables
