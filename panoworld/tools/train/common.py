"""Shared training infrastructure: preset + --set config, run directory, checkpoints with exact resume, metrics, export.

The API (used by `panoworld.tools.train.video` and `panoworld.tools.train.recon`):

- `resolve_config(cls, presets, preset, sets)` -> config dataclass (defaults < preset < `--set KEY=VALUE`);
  `RunDir(path).start(cfg, resume)` writes/validates `config.yaml` (the resolved config).
- `seed_everything(seed)`, `rng_state()` / `set_rng_state(state)`: python, numpy and torch (CPU + CUDA) RNGs.
- `EpochSampler(n, seed, rank, world)`: a resumable, deterministic shuffled index stream sharded over ranks;
  its `state_dict()` is the data position.
- `Checkpointer(run_dir, keep)`: `save(step, objects, extra)` stores the `state_dict()` of every object (model,
  optimiser, scheduler, sampler, ...) + all RNG states atomically; `restore(objects)` loads the latest.
- `MetricsLog(run_dir, resume_step)`: `metrics.jsonl` (+ TensorBoard when installed); on resume, rows after the
  checkpoint are dropped so the file continues exactly where the checkpoint was taken.
- `progress(total, initial, desc)`: tqdm with it/s and ETA; set the loss with `bar.set_postfix(loss=...)`.
- `Runtime.create(device, mixed_precision, use_accelerate)`: device, autocast and (lazily) `accelerate`.
- `write_export_scene_yaml(run_dir, {STAGE: {PARAM: VALUE}})` -> RUN_DIR/export/scene.yaml.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from panoworld.core.errors import InputError
from panoworld.framework.stage_params import params_from_dict, params_to_dict
from panoworld.io.safe_write import write_text_atomic

CONFIG = "config.yaml"
METRICS = "metrics.jsonl"
CHECKPOINTS = "checkpoints"
EXPORT = "export"


class TrainConfigError(InputError):
    """A bad preset, --set or run directory (the message names the flag or file and the fix)."""


# ---------------------------------------------------------------- config


def parse_sets(sets: list[str]) -> dict[str, Any]:
    """['lr=1e-4', 'steps=10'] -> {'lr': 1e-4, 'steps': 10} (values read as YAML scalars)."""
    out: dict[str, Any] = {}
    for s in sets:
        key, eq, value = s.partition("=")
        if not eq or not key.strip():
            raise TrainConfigError(f"--set {s}: expected KEY=VALUE")
        try:
            out[key.strip()] = yaml.safe_load(value) if value.strip() else ""
        except yaml.YAMLError:
            out[key.strip()] = value
    return out


def resolve_config(cls: type, presets: dict[str, dict[str, Any]], preset: str | None, sets: list[str] = ()) -> Any:
    """The config dataclass `cls`: field defaults < presets[preset] < `--set KEY=VALUE` (type-checked per field)."""
    if preset is not None and preset not in presets:
        raise TrainConfigError(f"--preset {preset}: unknown; known: {', '.join(presets)}")
    values = {**(presets.get(preset) or {}), **parse_sets(list(sets))}
    try:
        return params_from_dict(cls, values, where="config")
    except ValueError as e:
        raise TrainConfigError(f"{e} (--set KEY=VALUE)") from None


def config_to_dict(cfg: Any) -> dict[str, Any]:
    return params_to_dict(cfg)


class RunDir:
    """A training run directory: config.yaml, metrics.jsonl, checkpoints/, export/."""

    def __init__(self, path: Path | str):
        self.path = Path(path)

    @property
    def checkpoints(self) -> Path:
        return self.path / CHECKPOINTS

    @property
    def export(self) -> Path:
        return self.path / EXPORT

    def start(self, cfg: Any, resume: bool) -> None:
        """Create the run (config.yaml = the resolved config). With `resume`, the saved config must match `cfg`;
        without it, a directory that already holds checkpoints is refused (pass --resume or another --out)."""
        conf = self.path / CONFIG
        want = config_to_dict(cfg)
        if resume:
            if not conf.is_file():
                raise TrainConfigError(f"{conf}: no run to resume (drop --resume to start one)")
            have = yaml.safe_load(conf.read_text()) or {}
            diff = sorted(k for k in set(have) | set(want) if have.get(k) != want.get(k))
            if diff:
                raise TrainConfigError(
                    f"{conf}: --resume with a different config ({', '.join(f'{k}: {have.get(k)!r} -> {want.get(k)!r}' for k in diff[:4])}); "
                    "resume with the same --preset/--set or use another --out"
                )
            return
        if self.checkpoints.is_dir() and any(self.checkpoints.iterdir()):
            raise TrainConfigError(f"{self.path}: already holds checkpoints; pass --resume or choose another --out")
        self.path.mkdir(parents=True, exist_ok=True)
        write_text_atomic(conf, yaml.safe_dump(want, sort_keys=True))


# ---------------------------------------------------------------- randomness and data position


def seed_everything(seed: int) -> None:
    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def rng_state() -> dict[str, Any]:
    """Python, numpy and torch RNG states as tensors and plain numbers (loadable with torch.load(weights_only=True))."""
    import torch

    version, mt, gauss = random.getstate()
    name, keys, pos, has_gauss, cached = np.random.get_state()
    state = {
        "python": {"version": version, "state": torch.tensor(mt, dtype=torch.int64), "gauss_next": gauss},
        "numpy": {"name": name, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    import torch

    py, npy = state["python"], state["numpy"]
    random.setstate((py["version"], tuple(int(x) for x in py["state"].tolist()), py["gauss_next"]))
    np.random.set_state((npy["name"], npy["keys"].numpy().astype(np.uint32), npy["pos"], npy["has_gauss"],
                         npy["cached_gaussian"]))
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def load_checkpoint(path: Path) -> dict[str, Any]:
    """torch.load with weights_only=True (tensors and plain state only: a planted checkpoint cannot run code)."""
    import pickle

    import torch

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError) as e:
        raise TrainConfigError(f"{path}: not a checkpoint of tensors and plain state ({' '.join(str(e).split())[:200]}); "
                               "delete it (or resume from an older step_*.pt)") from None


class EpochSampler:
    """Endless stream of dataset indices: epoch e is a permutation seeded by (seed, e); rank r of `world` takes every
    world-th index (the tail is padded by wrapping so all ranks take the same number of steps). Resumable."""

    def __init__(self, n: int, seed: int = 0, rank: int = 0, world: int = 1, shuffle: bool = True):
        if n < 1:
            raise ValueError(f"{n=}: the dataset is empty")
        self.n, self.seed, self.rank, self.world, self.shuffle = n, seed, rank, world, shuffle
        self.epoch, self.pos = 0, 0

    def _order(self, epoch: int) -> np.ndarray:
        idx = np.random.default_rng([self.seed, epoch]).permutation(self.n) if self.shuffle else np.arange(self.n)
        per = -(-self.n // self.world)
        idx = np.resize(idx, per * self.world)
        return idx[self.rank :: self.world]

    def __len__(self) -> int:
        return -(-self.n // self.world)

    def next(self) -> int:
        order = self._order(self.epoch)
        i = int(order[self.pos])
        self.pos += 1
        if self.pos == len(order):
            self.epoch, self.pos = self.epoch + 1, 0
        return i

    def take(self, k: int) -> list[int]:
        return [self.next() for _ in range(k)]

    def state_dict(self) -> dict[str, int]:
        return {"epoch": self.epoch, "pos": self.pos, "n": self.n, "seed": self.seed, "world": self.world}

    def load_state_dict(self, state: dict[str, int]) -> None:
        if (state["n"], state["seed"], state["world"]) != (self.n, self.seed, self.world):
            raise TrainConfigError(f"checkpoint data position is for {state} but the data has n={self.n}, "
                                   f"seed={self.seed}, world={self.world}; resume on the same data")
        self.epoch, self.pos = state["epoch"], state["pos"]


# ---------------------------------------------------------------- checkpoints


class Checkpointer:
    """RUN_DIR/checkpoints/step_00000100.pt: the state_dict() of each named object + RNG states + extra.

    Writes go to a temporary file renamed into place, so a killed save never leaves a half checkpoint; the newest
    `keep` are kept.
    """

    def __init__(self, run_dir: RunDir | Path | str, keep: int = 2):
        self.dir = (run_dir if isinstance(run_dir, RunDir) else RunDir(run_dir)).checkpoints
        self.keep = keep

    def list(self) -> list[Path]:
        return sorted(self.dir.glob("step_*.pt")) if self.dir.is_dir() else []

    def latest(self) -> Path | None:
        ckpts = self.list()
        return ckpts[-1] if ckpts else None

    def save(self, step: int, objects: dict[str, Any], extra: dict[str, Any] | None = None) -> Path:
        import torch

        self.dir.mkdir(parents=True, exist_ok=True)
        state = {"step": step, "rng": rng_state(), "extra": extra or {},
                 "objects": {k: v.state_dict() for k, v in objects.items()}}
        path = self.dir / f"step_{step:08d}.pt"
        tmp = path.with_suffix(".pt.part")
        torch.save(state, tmp)
        os.replace(tmp, path)
        for old in self.list()[: -self.keep] if self.keep > 0 else []:
            old.unlink()
        return path

    def restore(self, objects: dict[str, Any], path: Path | None = None) -> tuple[int, dict[str, Any]]:
        """Load the latest checkpoint (or `path`) into `objects` and restore the RNGs; returns (step, extra)."""

        path = path or self.latest()
        if path is None:
            raise TrainConfigError(f"{self.dir}: no checkpoint to resume from")
        state = load_checkpoint(path)
        missing = sorted(set(objects) - set(state["objects"]))
        if missing:
            raise TrainConfigError(f"{path}: checkpoint lacks {missing}")
        for k, obj in objects.items():
            obj.load_state_dict(state["objects"][k])
        set_rng_state(state["rng"])
        return int(state["step"]), state["extra"]


# ---------------------------------------------------------------- metrics and progress


class MetricsLog:
    """Append-only RUN_DIR/metrics.jsonl ({"step", "split", ...values}) and TensorBoard scalars when installed."""

    def __init__(self, run_dir: RunDir | Path | str, resume_step: int | None = None, tensorboard: bool = True):
        root = (run_dir if isinstance(run_dir, RunDir) else RunDir(run_dir)).path
        self.path = root / METRICS
        if resume_step is None:
            self.path.unlink(missing_ok=True)
        elif self.path.is_file():  # drop rows logged after the checkpoint we resume from
            keep = [ln for ln in self.path.read_text().splitlines() if ln and json.loads(ln)["step"] <= resume_step]
            write_text_atomic(self.path, "".join(ln + "\n" for ln in keep))
        self.tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self.tb = SummaryWriter(str(root / "tensorboard"), purge_step=resume_step)
            except ImportError:
                pass

    def log(self, step: int, split: str, **values: float) -> None:
        row = {"step": int(step), "split": split, **{k: float(v) for k, v in values.items()}}
        with self.path.open("a") as f:
            f.write(json.dumps(row) + "\n")
        if self.tb is not None:
            for k, v in values.items():
                self.tb.add_scalar(f"{split}/{k}", float(v), step)

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()


def read_metrics(run_dir: Path | str, split: str | None = None) -> list[dict]:
    path = Path(run_dir) / METRICS
    rows = [json.loads(ln) for ln in path.read_text().splitlines() if ln] if path.is_file() else []
    return [r for r in rows if split is None or r["split"] == split]


def progress(total: int, initial: int = 0, desc: str = "train", enabled: bool = True):
    """A tqdm bar over steps (shows it/s and ETA); call bar.set_postfix(loss=...) each step."""
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, desc=desc, unit="it", disable=not enabled, dynamic_ncols=True)


# ---------------------------------------------------------------- devices, precision, accelerate


@dataclasses.dataclass
class Runtime:
    """Where and how a run computes. `accelerator` is an `accelerate.Accelerator` when requested (multi-GPU,
    DeepSpeed through its config file), else None and everything runs in this process on `device`."""

    device: Any
    mixed_precision: str = "no"
    accelerator: Any = None
    rank: int = 0
    world: int = 1

    @classmethod
    def create(cls, device: str = "auto", mixed_precision: str = "auto", use_accelerate: bool = False) -> Runtime:
        """device auto = cuda when available; mixed_precision auto = bf16 on CUDA, no on CPU."""
        import torch

        if use_accelerate:
            try:
                from accelerate import Accelerator
            except ImportError:
                raise TrainConfigError("use_accelerate=true needs accelerate: pip install '.[train]'") from None
            mp = mixed_precision if mixed_precision != "auto" else ("bf16" if torch.cuda.is_available() else "no")
            acc = Accelerator(mixed_precision=mp)
            return cls(acc.device, mp, acc, acc.process_index, acc.num_processes)
        dev = torch.device("cuda" if device == "auto" and torch.cuda.is_available() else
                           ("cpu" if device == "auto" else device))
        mp = mixed_precision if mixed_precision != "auto" else ("bf16" if dev.type == "cuda" else "no")
        return cls(dev, mp)

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def autocast(self):
        import torch

        if self.accelerator is not None:
            return self.accelerator.autocast()
        if self.mixed_precision == "bf16":
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def prepare(self, *objs):
        return self.accelerator.prepare(*objs) if self.accelerator is not None else objs

    def backward(self, loss) -> None:
        if self.accelerator is not None:
            self.accelerator.backward(loss)
        else:
            loss.backward()

    def unwrap(self, model):
        return self.accelerator.unwrap_model(model) if self.accelerator is not None else model


# ---------------------------------------------------------------- export


def write_export_scene_yaml(run_dir: RunDir | Path | str, params: dict[str, dict[str, Any]], note: str = "") -> Path:
    """RUN_DIR/export/scene.yaml = {params: {STAGE: {PARAM: VALUE}}} (paths absolute, so the file can be copied
    into any scene directory and `runner.py run` picks the trained weights up with no other flag)."""
    export = (run_dir if isinstance(run_dir, RunDir) else RunDir(run_dir)).export
    export.mkdir(parents=True, exist_ok=True)
    plain = {stage: {k: str(v) if isinstance(v, Path) else v for k, v in p.items()} for stage, p in params.items()}
    head = f"# {note}\n" if note else ""
    path = export / "scene.yaml"
    write_text_atomic(path, head + yaml.safe_dump({"params": plain}, sort_keys=False))
    return path


def replace_dir(tmp: Path, final: Path) -> None:
    """Move a fully written directory into place (the previous one is removed first)."""
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)
