"""A small U-Net that segments the capture rig on the downward cube face (the learned rig detector, docs/rig.md)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from panoworld.models.weights import load_config_and_weights, save_config_and_weights

MODEL = "rig U-Net"
FLAG = "--set depth.rig_weights"


@dataclass(kw_only=True)
class RigUNetConfig:
    """Shape of the network; stored as config.json beside model.safetensors."""

    channels: int = 8
    """Channels of the first level (doubled per level down)."""
    levels: int = 3
    """Down-sampling steps (the input side must be divisible by 2**levels)."""
    size: int = 96
    """Side of the downward face the network sees (faces are resized to it)."""


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class RigUNet(nn.Module):
    """RGB face + the face's angle from the nadir (4 channels) -> rig logit per pixel."""

    def __init__(self, cfg: RigUNetConfig):
        super().__init__()
        self.cfg = cfg
        ch = [cfg.channels * 2**k for k in range(cfg.levels + 1)]
        self.down = nn.ModuleList([_block(4, ch[0])] + [_block(ch[k], ch[k + 1]) for k in range(cfg.levels)])
        self.up = nn.ModuleList([nn.ConvTranspose2d(ch[k + 1], ch[k], 2, stride=2) for k in range(cfg.levels)])
        self.merge = nn.ModuleList([_block(2 * ch[k], ch[k]) for k in range(cfg.levels)])
        self.head = nn.Conv2d(ch[0], 1, 1)
        c = (torch.arange(cfg.size) + 0.5 - 0.5 * cfg.size) / (0.5 * cfg.size)
        self.register_buffer("radius", torch.hypot(*torch.meshgrid(c, c, indexing="ij"))[None, None], persistent=False)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        """rgb (B, 3, size, size) in [0, 1] -> logits (B, 1, size, size)."""
        x = torch.cat([rgb * 2 - 1, self.radius.expand(rgb.shape[0], -1, -1, -1)], 1)
        skips = []
        for k, block in enumerate(self.down):
            x = block(x if k == 0 else nn.functional.max_pool2d(x, 2))
            skips.append(x)
        for k in reversed(range(self.cfg.levels)):
            x = self.merge[k](torch.cat([self.up[k](x), skips[k]], 1))
        return self.head(x)

    @torch.no_grad()
    def predict(self, face: np.ndarray) -> np.ndarray:
        """Rig probability (S, S) float32 for a uint8 face (S, S, 3) of any side."""
        import cv2

        S = face.shape[0]
        x = cv2.resize(face, (self.cfg.size, self.cfg.size), interpolation=cv2.INTER_AREA)
        dev = next(self.parameters()).device
        t = torch.from_numpy(x).to(dev).permute(2, 0, 1)[None].float() / 255.0
        p = torch.sigmoid(self(t))[0, 0].cpu().numpy()
        return cv2.resize(p, (S, S), interpolation=cv2.INTER_LINEAR)

    def save(self, root: Path | str) -> Path:
        return save_config_and_weights(self, asdict(self.cfg), root)

    @classmethod
    def load(cls, root: Path | str | None, device: str = "cpu") -> RigUNet:
        """The network from a directory holding config.json + model.safetensors (WeightsError naming the fix)."""
        return load_config_and_weights(lambda d: cls(RigUNetConfig(**d)), root, model=MODEL, flag=FLAG, device=device)
