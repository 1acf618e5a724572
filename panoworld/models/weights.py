"""Checks that local model weights exist, with one-line errors naming the expected files and the flag to pass."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from panoworld.stage import StageInputError


class MissingWeightsError(StageInputError):
    """Weights absent or incomplete; a stage that lets it propagate exits with code 2 and this message."""


def _present(root: Path, pattern: str) -> bool:
    return any(root.glob(pattern)) if any(c in pattern for c in "*?[") else (root / pattern).is_file()


def require_weights_dir(root: Path | str | None, expected: Sequence[str], *, model: str, flag: str) -> Path:
    """Return `root` if it holds every entry of `expected` (relative paths, glob patterns allowed), else raise.

    Weights are never downloaded: the message lists what is missing and the CLI flag that names the directory.
    """
    listing = ", ".join(expected)
    if root is None:
        raise MissingWeightsError(
            f"{model}: no weights directory given; pass {flag} DIR holding {listing} (weights are never downloaded)"
        )
    root = Path(root)
    if not root.is_dir():
        raise MissingWeightsError(f"{model}: {flag} {root} is not a directory; it must hold {listing}")
    missing = [p for p in expected if not _present(root, p)]
    if missing:
        raise MissingWeightsError(
            f"{model}: {flag} {root} lacks {', '.join(missing)}; it must hold {listing} (weights are never downloaded)"
        )
    return root


def require_weights_file(path: Path | str | None, *, model: str, flag: str, expected: str) -> Path:
    """Return `path` if it is an existing file, else raise naming the expected file (e.g. 'RealESRGAN_x2plus.pth')."""
    if path is None:
        raise MissingWeightsError(f"{model}: no weights file given; pass {flag} FILE ({expected})")
    path = Path(path)
    if not path.is_file():
        raise MissingWeightsError(f"{model}: {flag} {path} does not exist; it must be {expected}")
    return path
