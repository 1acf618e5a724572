"""`python runner.py train video --data COND_DIR --out RUN_DIR [--weights WAN_DIR] [--preset tiny|paper] [--set K=V]...`"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from panoworld.framework.stage_params import field_docs
from panoworld.io.safe_write import check_output_dir


def build_parser() -> argparse.ArgumentParser:
    from panoworld.tools.train.video.config import PRESETS, VideoTrainConfig

    docs = field_docs(VideoTrainConfig)
    keys = "\n".join(f"  {k}: {v}" for k, v in docs.items())
    ap = argparse.ArgumentParser(
        prog="python runner.py train video", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Train the shortcut video generator (LoRA + condition projection + step-size embedding on a "
                    "frozen Wan2.2 backbone) on precomputed clips; docs/training.md.",
        epilog=f"--set KEYS (defaults < --preset < --set):\n{keys}",
    )
    ap.add_argument("--data", type=Path, required=True, help="precompute output (COND_DIR/index.jsonl)")
    ap.add_argument("--out", type=Path, required=True, help="run directory (config, checkpoints, metrics, export/)")
    ap.add_argument("--weights", type=Path, default=None, help="local Wan2.2-TI2V-5B-Diffusers directory (base=wan)")
    ap.add_argument("--preset", choices=sorted(PRESETS), default=None, help="tiny (CPU proof) or paper")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE", help="override one key")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from its latest checkpoint")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON (no progress bar)")
    return ap


def main(argv: list[str] | None = None) -> int:
    from panoworld.models.weights import MissingWeightsError
    from panoworld.tools.train.common import TrainConfigError, resolve_config
    from panoworld.tools.train.video.config import PRESETS, VideoTrainConfig
    from panoworld.tools.train.video.data import ClipDataError
    from panoworld.tools.train.video.trainer import VideoTrainer

    a = build_parser().parse_args(argv)
    check_output_dir(a.out)
    try:
        cfg = resolve_config(VideoTrainConfig, PRESETS, a.preset, a.sets)
        summary = VideoTrainer(a.data, a.out, cfg, weights=a.weights, resume=a.resume, progress=not a.json).run()
    except (TrainConfigError, ClipDataError, MissingWeightsError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"trained {summary['steps']} steps in {summary['seconds']} s (CPU {summary['cpu_seconds']} s); "
              f"export: {summary['export']} (copy its scene.yaml into a scene directory)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
