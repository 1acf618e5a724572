"""`python runner.py train recon --stage 1|2 --data DATASET_DIR --out RUN_DIR [--init DIR] [--preset tiny|paper]
[--set KEY=VALUE]... [--resume]`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from panoworld.io.safe_write import check_output_dir


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python runner.py train recon",
        description="Train PanoVGGT: stage 1 = camera + depth heads (and backbone); stage 2 = the Gaussian head, "
        "everything else frozen. Exports RUN_DIR/export/weights and RUN_DIR/export/scene.yaml.",
    )
    p.add_argument("--stage", type=int, choices=(1, 2), required=True)
    p.add_argument("--data", type=Path, required=True, help="dataset directory of scenes with gt/gt.json "
                   "(runner.py synth DIR --scenes K); the last val_scenes scenes validate")
    p.add_argument("--out", type=Path, required=True, help="run directory")
    p.add_argument("--init", type=Path, help="weights directory to start from (stage 2: a stage-1 export, required)")
    p.add_argument("--preset", default="tiny", help="tiny (CPU, minutes) or paper (392x784, VGGT-1B sizes)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config field (python -c 'from panoworld.tools.train.recon.config import ReconConfig; "
                   "help(ReconConfig)' lists them)")
    p.add_argument("--resume", action="store_true", help="continue from the latest checkpoint in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    check_output_dir(args.out)
    from panoworld.models.weights import MissingWeightsError
    from panoworld.tools.dataset import DatasetError
    from panoworld.tools.train import common
    from panoworld.tools.train.recon.config import PRESETS, ReconConfig
    from panoworld.tools.train.recon.loop import Trainer

    try:
        cfg = common.resolve_config(ReconConfig, PRESETS, args.preset, [*args.sets, f"stage={args.stage}"])
        trainer = Trainer(cfg, args.data, args.out, init=args.init, resume=args.resume,
                          progress=not args.no_progress)
        result = trainer.run()
    except (common.TrainConfigError, DatasetError, MissingWeightsError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
