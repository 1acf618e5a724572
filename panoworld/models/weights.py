"""Local model weights: existence checks with one-line errors, config + safetensors save/load, state-dict files."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

from panoworld.core.errors import WeightsError


class MissingWeightsError(WeightsError):
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


class JsonConfig:
    """Mixin for model config dataclasses: to_json / from_json, rejecting unknown keys with a clear error."""

    def to_json(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_json(cls, d: dict):
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"{cls.__name__} has unknown keys {unknown}; known: {sorted(known)}")
        return cls(**d)


CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"


def save_config_and_weights(model, config: dict, root: Path | str) -> Path:
    """Write `config` as config.json and the model's state dict as model.safetensors into the directory root."""
    import json

    from safetensors.torch import save_file

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    (root / CONFIG_FILE).write_text(json.dumps(config, indent=2))
    save_file({k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}, str(root / WEIGHTS_FILE))
    return root


def load_config_and_weights(build, root: Path | str | None, *, model: str, flag: str, device: str = "cpu"):
    """Build a model from root/config.json with `build(config_dict)` and load root/model.safetensors into it.

    Never downloads. Missing files, an invalid config, or a state dict that does not match the config (missing or
    unexpected keys, other tensor shapes) raise MissingWeightsError naming the file and `flag`.
    """
    import json

    try:
        from safetensors.torch import load_file
    except ImportError as e:  # pragma: no cover - safetensors ships with the models extra
        raise ImportError(f"{model} needs safetensors: pip install '.[models]'") from e
    root = require_weights_dir(root, [CONFIG_FILE, WEIGHTS_FILE], model=model, flag=flag)
    try:
        net = build(json.loads((root / CONFIG_FILE).read_text()))
    except (json.JSONDecodeError, TypeError, ValueError) as e:
        raise MissingWeightsError(f"{model}: {root / CONFIG_FILE} is not a valid config: {e}") from None
    state = load_file(str(root / WEIGHTS_FILE), device=device)
    try:
        missing, unexpected = net.load_state_dict(state, strict=False)
    except RuntimeError as e:  # tensor shapes that differ from the config's
        shapes = " ".join(str(e).split())[:300]
        raise MissingWeightsError(f"{model}: {root / WEIGHTS_FILE} does not match {CONFIG_FILE}: {shapes}") from None
    if missing or unexpected:
        raise MissingWeightsError(
            f"{model}: {root / WEIGHTS_FILE} does not match {CONFIG_FILE}: missing {missing[:3]}"
            f"{'...' if len(missing) > 3 else ''}, unexpected {unexpected[:3]}{'...' if len(unexpected) > 3 else ''}"
        )
    return net.to(device).eval()


def read_state_file(path: Path, *, model: str, expected: str) -> dict:
    """Read a .safetensors or torch .pth/.pt file into a dict; an unreadable file or a non-dict raises
    MissingWeightsError naming `expected` (what the file must be)."""
    import torch

    try:
        if Path(path).suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # every unreadable file gets the same actionable message
        raise MissingWeightsError(f"{model}: cannot read {path}: {e}; it must be {expected}") from None
    if not isinstance(state, dict):
        raise MissingWeightsError(f"{model}: {path} holds a {type(state).__name__}, not a state dict; it must be {expected}")
    return state
