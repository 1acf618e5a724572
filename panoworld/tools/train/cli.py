"""`python runner.py train video|recon ...`: dispatch to the trainer's own CLI (imported lazily)."""

from __future__ import annotations

import importlib
import sys

TRAINERS = {
    "video": ("panoworld.tools.train.video.cli:main", "the shortcut video generator (LoRA on Wan2.2)"),
    "recon": ("panoworld.tools.train.recon.cli:main", "the panoramic reconstruction model (PanoVGGT + Gaussian head)"),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in TRAINERS:
        lines = "\n".join(f"  {k:<6} {help}" for k, (_, help) in TRAINERS.items())
        stream = sys.stdout if argv[:1] in (["-h"], ["--help"]) else sys.stderr
        print(f"usage: python runner.py train {{{','.join(TRAINERS)}}} [--help] ...\n{lines}", file=stream)
        return 0 if stream is sys.stdout else 2
    module, func = TRAINERS[argv[0]][0].split(":")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name and module.startswith(e.name):
            print(f"error: train {argv[0]}: {module} is not available in this checkout", file=sys.stderr)
            return 2
        raise
    return getattr(mod, func)(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
