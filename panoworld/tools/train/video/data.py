"""Training clips of a precompute output (index.jsonl): a torch Dataset, the scene split, and the VAE latent cache."""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from panoworld.core.errors import DataError
from panoworld.tools.precompute.run import INDEX


class ClipDataError(DataError):
    """A precompute output that cannot be trained on (the message names the file)."""


@dataclass(frozen=True)
class ClipRow:
    scene: str
    clip: str
    path: Path
    length: int
    stride: float
    digest: str


def read_index(cond_dir: Path) -> list[ClipRow]:
    """The rows of COND_DIR/index.jsonl (written by `runner.py precompute`)."""
    path = Path(cond_dir) / INDEX
    if not path.is_file():
        raise ClipDataError(f"{path}: missing; run `python runner.py precompute DATASET --out {cond_dir}` first")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        try:
            r = json.loads(line)
            rows.append(ClipRow(r["scene"], r["clip"], Path(cond_dir) / r["path"], int(r["length"]), float(r["stride"]),
                                r.get("digest", "")))
        except (ValueError, KeyError) as e:
            raise ClipDataError(f"{path}:{n}: unreadable row ({e})") from None
    if not rows:
        raise ClipDataError(f"{path}: lists no clips")
    return rows


def split_scenes(scenes: list[str], val_fraction: float, seed: int = 0) -> tuple[list[str], list[str]]:
    """(train, val) scene names: the val scenes are the first ceil(fraction n) by sha256(seed, name), so a scene never
    changes side when scenes are added; at least one scene each side when there are two or more."""
    uniq = sorted(set(scenes))
    if not 0 <= val_fraction < 1:
        raise ClipDataError(f"val_fraction={val_fraction}: expected 0 <= fraction < 1")
    order = sorted(uniq, key=lambda s: hashlib.sha256(f"{seed}:{s}".encode()).hexdigest())
    k = math.ceil(val_fraction * len(uniq)) if val_fraction > 0 else 0
    if len(uniq) >= 2:
        k = min(max(k, 1 if val_fraction > 0 else 0), len(uniq) - 1)
    val = set(order[:k])
    return [s for s in uniq if s not in val], [s for s in uniq if s in val]


def _resize(frames: np.ndarray, h: int, w: int, interp: int) -> np.ndarray:
    if frames.shape[1:3] == (h, w):
        return frames
    return np.stack([cv2.resize(f, (w, h), interpolation=interp) for f in frames])


class ClipDataset(Dataset):
    """Item i: {"target", "cond": (3, T, H, W) float in [-1, 1], "mask": (1, T, H, W) {0, 1} (1 = warped pixel valid),
    "poses": (T, 4, 4) canonical_from_cam, "index": i, "scene", "clip", "stride"} at the training size.

    Clips shorter than `frames` are skipped (listed in `skipped`), longer ones are cut to their first `frames`.
    """

    def __init__(self, rows: list[ClipRow], frames: int, height: int):
        self.frames, self.height, self.width = frames, height, 2 * height
        self.rows = [r for r in rows if r.length >= frames]
        self.skipped = [r for r in rows if r.length < frames]

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int) -> dict:
        from panoworld.io.conditions import load_conditions

        row = self.rows[i]
        try:
            clip = json.loads((row.path / "clip.json").read_text())
            cond = load_conditions(row.path / "cond")
        except (OSError, ValueError) as e:
            raise ClipDataError(f"{row.path}: unreadable clip ({e}); rerun precompute") from None
        t, h, w = self.frames, self.height, self.width
        if not clip.get("targets"):
            raise ClipDataError(f"{row.path}/clip.json: no target frames (precompute ran with --no-targets)")
        targets = []
        for name in clip["targets"][:t]:
            bgr = cv2.imread(str(row.path / name), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ClipDataError(f"{row.path / name}: missing or unreadable target frame; rerun precompute")
            targets.append(bgr[..., ::-1])
        target = _resize(np.stack(targets), h, w, cv2.INTER_AREA)
        rgb = _resize(np.stack([cond.rgb[k] for k in range(t)]), h, w, cv2.INTER_AREA)
        mask = _resize(np.stack([cond.mask[k] for k in range(t)]).astype(np.uint8), h, w, cv2.INTER_NEAREST)

        def video(x: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(x)).permute(3, 0, 1, 2).float() / 127.5 - 1.0

        return {
            "target": video(target), "cond": video(rgb), "mask": torch.from_numpy(mask > 0)[None].float(),
            "poses": torch.tensor(clip["poses"][:t], dtype=torch.float64), "index": i, "scene": row.scene,
            "clip": row.clip, "stride": row.stride,
        }


def vae_fingerprint(vae: torch.nn.Module) -> str:
    """A short digest of the VAE's config and weights (the latent cache is only valid for one VAE)."""
    h = hashlib.sha256(json.dumps(dict(vae.config), sort_keys=True, default=str).encode())
    for name, t in sorted(vae.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().float().flatten()[:: max(1, t.numel() // 4096)].cpu().numpy().tobytes())
    return h.hexdigest()[:16]


class LatentCache:
    """DIR/<scene>/<clip>.pt = {"x0": (z, T_lat, h, w), "cond": (z + temporal, T_lat, h, w), "anchor": bool} from the
    frozen VAE, keyed by the clip digest, the training size and the VAE fingerprint (a stale file is recomputed)."""

    def __init__(self, root: Path, key: str, in_memory: bool = True):
        self.root, self.key, self.in_memory = Path(root), key, in_memory
        self._mem: dict[int, dict] = {}

    def path(self, row: ClipRow) -> Path:
        return self.root / row.scene / f"{row.clip}.pt"

    def valid(self, row: ClipRow) -> bool:
        p = self.path(row)
        if not p.is_file():
            return False
        try:
            return torch.load(p, map_location="cpu", weights_only=True).get("key") == self._key(row)
        except Exception:
            return False

    def _key(self, row: ClipRow) -> str:
        return f"{self.key}:{row.digest}"

    def put(self, row: ClipRow, x0: torch.Tensor, cond: torch.Tensor, anchor: bool) -> None:
        p = self.path(row)
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_suffix(".pt.part")
        torch.save({"key": self._key(row), "x0": x0.cpu(), "cond": cond.cpu(), "anchor": bool(anchor)}, tmp)
        tmp.replace(p)

    def get(self, i: int, row: ClipRow) -> dict:
        if i in self._mem:
            return self._mem[i]
        item = torch.load(self.path(row), map_location="cpu", weights_only=True)
        if self.in_memory:
            self._mem[i] = item
        return item


@torch.no_grad()
def encode_item(vae, item: dict, device, anchor_first_frame: bool) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """A ClipDataset item -> (x0 latents (z, T_lat, h, w), condition (z + temporal, T_lat, h, w), anchored)."""
    from panoworld.models import wan_layers as wl

    target = item["target"][None].to(device)
    cond, mask = item["cond"][None].to(device), item["mask"][None].to(device)
    x0 = wl.encode_video(vae, target)[0]
    c = wl.encode_condition(vae, cond, mask)[0]
    return x0.float(), c.float(), bool(anchor_first_frame and wl.anchors_first_frame(mask[0, 0, 0]))


def build_latent_cache(dataset: ClipDataset, cache: LatentCache, vae, device, *, anchor_first_frame: bool,
                       workers: int = 0, rank: int = 0, world: int = 1, progress: bool = True) -> dict:
    """Encode every clip of `dataset` whose cache file is missing or stale (this rank's share: i % world == rank)."""
    from torch.utils.data import DataLoader, Subset
    from tqdm import tqdm

    todo = [i for i in range(len(dataset)) if i % world == rank and not cache.valid(dataset.rows[i])]
    if not todo:
        return {"encoded": 0, "cached": len(dataset)}
    loader = DataLoader(Subset(dataset, todo), batch_size=None, num_workers=workers, shuffle=False)
    for item in tqdm(loader, total=len(todo), desc="latents", unit="clip", disable=not progress):
        x0, c, anchor = encode_item(vae, item, device, anchor_first_frame)
        cache.put(dataset.rows[item["index"]], x0, c, anchor)
    return {"encoded": len(todo), "cached": len(dataset) - len(todo)}
