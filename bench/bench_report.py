"""Report generation time (target <= 10 s for a default-preset scene) and page size: python bench/bench_report.py [SCENE_DIR].

SCENE_DIR defaults to demo_out/scene (`python runner.py demo` builds the default-preset demo). Prints wall and CPU
time (user+sys of this process, imports included) and the seconds per section; the report goes to a temporary file.
"""

from __future__ import annotations

import resource
import sys
import tempfile
import time
from pathlib import Path

T0 = time.perf_counter()
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> int:
    scene = Path(sys.argv[1] if len(sys.argv) > 1 else "demo_out/scene")
    if not (scene / "artifacts").is_dir():
        print(f"error: {scene}: no artifacts/ (run `python runner.py demo` first)", file=sys.stderr)
        return 2
    from panoworld.core.errors import ArtifactError
    from panoworld.io.manifest import read_manifest
    from panoworld.tools.report.cli import build_scene_report

    timings: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        out = build_scene_report(scene, Path(tmp) / "index.html", timings=timings)
        size = out.stat().st_size
    wall = time.perf_counter() - T0
    info = {}
    for stage in ("conditions", "video", "gaussians"):
        try:
            info[stage] = read_manifest(scene / "artifacts" / stage)["info"]
        except ArtifactError:
            info[stage] = {}
    print(f"scene: {scene}  ({info['video'].get('num_frames', '?')} frames of {info['video'].get('height', '?')}x"
          f"{info['video'].get('width', '?')}, {info['gaussians'].get('num_gaussians', '?')} Gaussians)")
    print(f"report: {size / 1e6:.2f} MB, wall {wall:.2f} s (imports included), CPU {cpu():.2f} s (user+sys, all threads)")
    print("seconds per section (the gaussians section runs beside the others):")
    for k, v in timings.items():
        print(f"  {k:<10} {v:6.2f}")
    print(f"target <= 10 s: {'met' if wall <= 10 else 'NOT met'} (wall on this machine; compare CPU time on a loaded one)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
