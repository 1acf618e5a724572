"""`runner.py report`: write a scene's (or a precompute dataset's) self-contained HTML report."""

from __future__ import annotations

import argparse
import dataclasses
import html
import sys
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from panoworld.io.safe_write import check_output_file, write_text_atomic
from panoworld.tools.report.page import Page, Section

DEFAULT_OUT = Path("artifacts") / "report" / "index.html"


def _guarded(fn, id: str, title: str, *args) -> Section:
    """fn(*args), or a section naming the error: one broken artifact never costs the rest of the report."""
    try:
        return fn(*args)
    except Exception as e:  # shown on the page, the report still gets written
        tb = traceback.format_exc(limit=3)
        return Section(id, title, f'<p class="note bad">could not draw this section: {html.escape(repr(e))}</p>'
                       f"<pre>{html.escape(tb)}</pre>", missing=True)


def build_scene_report(scene_dir: Path, out: Path | None = None, params=None, *, run_results: list[dict] | None = None,
                       timings: dict | None = None) -> Path:
    """Write the report of a scene directory to out (default SCENE/artifacts/report/index.html); return its path.

    run_results: the runner's per-stage results (dicts with stage, action, reason) of the run that just finished;
    without them the stage table shows each stage's current state (up to date / stale) instead.
    """
    from panoworld.tools.report import scene as sc
    from panoworld.tools.report.home import is_home, section_home
    from panoworld.tools.report.roam import section_roam
    from panoworld.tools.report.scene_data import ReportParams, SceneData
    from panoworld.tools.report.splats import section_gaussians

    params = params or ReportParams()
    scene_dir = Path(scene_dir)
    out = Path(out) if out else scene_dir / DEFAULT_OUT
    out.parent.mkdir(parents=True, exist_ok=True)
    data = SceneData(scene_dir)
    page = Page(f"PanoWorld scene report: {scene_dir.resolve().name}",
                f"{scene_dir.resolve()} · written {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}")
    builders = [
        ("stages", "Stages", sc.section_stages, (data, out.parent, params, run_results)),
        ("depth", "Panorama and depth", sc.section_depth, (data, params)),
        *([("home", "Home: capture points and registration", section_home, (data, page, params))]
          if is_home(data) else []),
        ("plan", "Top-down: mesh, NavMesh and trajectory", sc.section_plan, (data, params)),
        ("frames", "Conditions, masks and video frames", sc.section_frames, (data, page, params)),
        ("poses", "Poses: recovered vs planned", sc.section_poses, (data, params)),
        ("gaussians", "Gaussians: renders beside video frames", section_gaussians, (data, params)),
        ("eval", "Evaluation against ground truth", sc.section_eval, (data, params)),
        ("roam", "Roam: the scene away from the capture point", section_roam, (data, params)),
    ]
    def timed(id, title, fn, args):
        t0 = time.perf_counter()
        section = _guarded(fn, id, title, *args)
        if timings is not None:
            timings[id] = time.perf_counter() - t0
        return section

    # The Gaussian renders (torch) overlap with the image work of the other sections (OpenCV, no GIL).
    k = next(i for i, b in enumerate(builders) if b[0] == "gaussians")
    with ThreadPoolExecutor(1) as pool:
        splats = pool.submit(timed, *builders[k])
        sections = [timed(*b) for b in builders[:k]] + [splats.result()] + [timed(*b) for b in builders[k + 1:]]
    for section in sections:
        page.add(section)
    write_text_atomic(out, page.render())
    return out


def is_dataset_dir(path: Path) -> bool:
    from panoworld.tools.precompute.run import INDEX

    return (Path(path) / INDEX).is_file()


def build_parser() -> argparse.ArgumentParser:
    from panoworld.framework.stage_params import field_docs
    from panoworld.tools.report.scene_data import ReportParams

    ap = argparse.ArgumentParser(prog="python runner.py report", description=__doc__)
    ap.add_argument("path", type=Path, help="scene directory, or a precompute output directory (has index.jsonl)")
    ap.add_argument("--out", type=Path, help=f"HTML file to write (default: SCENE/{DEFAULT_OUT.as_posix()}, "
                    "COND_DIR/report.html for a dataset)")
    ap.add_argument("--eval", action="store_true", help="run `runner.py eval` first (slow) and save its JSON as "
                    "artifacts/report/eval.json (needs gt/)")
    docs = field_docs(ReportParams)
    for f in dataclasses.fields(ReportParams):
        kind = {int: int, float: float}.get(type(f.default), str) if f.default is not None else str
        if f.name == "eval_json":
            kind = Path
        ap.add_argument(f"--{f.name.replace('_', '-')}", dest=f.name, type=kind, default=f.default,
                        help=f"{docs.get(f.name, '')} (default: {f.default})")
    ap.add_argument("--clips", type=int, default=12, help="dataset view: sample clips shown (default: 12)")
    return ap


def main(argv: list[str] | None = None) -> int:
    from panoworld.tools.report.scene import run_eval
    from panoworld.tools.report.scene_data import ReportParams

    args = build_parser().parse_args(argv)
    path: Path = args.path
    if args.out is not None:
        check_output_file(args.out)
    if not path.is_dir():
        print(f"error: {path}: not a directory (pass a scene directory or a precompute output directory)", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    if is_dataset_dir(path):
        from panoworld.tools.report.dataset import build_dataset_report

        out = build_dataset_report(path, args.out, clips=args.clips)
    else:
        if not any((path / n).is_file() for n in ("panorama.png", "panorama.jpg", "panorama.jpeg")) \
                and not (path / "artifacts").is_dir():
            print(f"error: {path}: neither a scene (panorama.png|jpg, artifacts/) nor a precompute output "
                  "(index.jsonl)", file=sys.stderr)
            return 2
        if args.eval:
            if not (path / "gt" / "gt.json").is_file():
                print(f"error: {path}: --eval needs ground truth in gt/ (scenes from `runner.py synth`)", file=sys.stderr)
                return 2
            print(f"evaluation saved to {run_eval(path)}", file=sys.stderr)
        params = ReportParams(**{f.name: getattr(args, f.name) for f in dataclasses.fields(ReportParams)})
        out = build_scene_report(path, args.out, params)
    size = out.stat().st_size / 1e6
    print(f"report: {out} ({size:.1f} MB, {time.perf_counter() - t0:.1f} s)")
    return 0
