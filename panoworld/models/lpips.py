"""LPIPS v0.1 (Zhang et al. 2018): AlexNet or VGG16 features with learned linear heads, weights from local files."""

from __future__ import annotations

import enum
from pathlib import Path

import numpy as np
import torch
from torch import nn

from panoworld.models.weights import MissingWeightsError, read_state_file, require_weights_file

# Input normalisation of the lpips package (ScalingLayer), applied to images in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
EPS = 1e-10


class Net(enum.StrEnum):
    ALEX = "alex"
    VGG = "vgg"


# Per net: channels of the five tapped ReLU outputs and the index in `features` just after each tap.
CHANNELS = {Net.ALEX: (64, 192, 384, 256, 256), Net.VGG: (64, 128, 256, 512, 512)}
TAP_ENDS = {Net.ALEX: (2, 5, 8, 10, 12), Net.VGG: (4, 9, 16, 23, 30)}
BACKBONE_FILES = {Net.ALEX: "torchvision AlexNet state dict, e.g. alexnet-owt-7be5be79.pth",
                  Net.VGG: "torchvision VGG16 state dict, e.g. vgg16-397923af.pth"}
LIN_FILES = {Net.ALEX: "lpips weights/v0.1/alex.pth", Net.VGG: "lpips weights/v0.1/vgg.pth"}


def alexnet_features() -> nn.Sequential:
    """torchvision's alexnet().features (same layer indices, so its state-dict keys load unchanged)."""
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
    )


def vgg16_features() -> nn.Sequential:
    """torchvision's vgg16().features (configuration D, no batch norm)."""
    layers: list[nn.Module] = []
    c_in = 3
    for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"):
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c_in, v, 3, padding=1), nn.ReLU(inplace=True)]
            c_in = v
    return nn.Sequential(*layers)


def _load_state(path: Path, what: str) -> dict[str, torch.Tensor]:
    return read_state_file(path, model="LPIPS", expected=f"the {what}")


class LPIPS(nn.Module):
    """Learned perceptual distance: unit-normalised features at five depths, squared differences weighted by
    non-negative 1x1 heads, averaged over space and summed over depths. Identical images give exactly 0."""

    def __init__(self, net: Net | str = Net.ALEX):
        super().__init__()
        self.net = Net(net)
        self.features = alexnet_features() if self.net == Net.ALEX else vgg16_features()
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in CHANNELS[self.net])
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))

    def taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five tapped feature maps of images x (B, 3, H, W) in [-1, 1]."""
        x = (x - self.shift) / self.scale
        out, start = [], 0
        for end in TAP_ENDS[self.net]:
            x = self.features[start:end](x)
            out.append(x)
            start = end
        return out

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """Distance (B,) between images x0, x1 (B, 3, H, W) in [-1, 1]."""
        if x0.shape != x1.shape or x0.ndim != 4 or x0.shape[1] != 3:
            raise ValueError(f"{tuple(x0.shape)=} and {tuple(x1.shape)=} but expected equal (B, 3, H, W)")
        total = torch.zeros(x0.shape[0], dtype=x0.dtype, device=x0.device)
        for f0, f1, lin in zip(self.taps(x0), self.taps(x1), self.lins):
            n0 = f0 / (f0.pow(2).sum(1, keepdim=True).sqrt() + EPS)
            n1 = f1 / (f1.pow(2).sum(1, keepdim=True).sqrt() + EPS)
            total = total + lin((n0 - n1) ** 2).mean(dim=(1, 2, 3))
        return total

    @torch.no_grad()
    def distance_uint8(self, a: np.ndarray, b: np.ndarray) -> float:
        """LPIPS of two RGB images (H, W, 3) uint8."""
        if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"{a.shape=} and {b.shape=} but expected equal (H, W, 3)")
        p = next(self.parameters())

        def t(img):
            return torch.from_numpy(np.ascontiguousarray(img)).to(p).permute(2, 0, 1)[None] / 127.5 - 1.0

        return float(self(t(a), t(b))[0])

    def load_backbone(self, state: dict[str, torch.Tensor], where: str = "backbone") -> None:
        """Load a torchvision classifier state dict (keys 'features.N.weight'; the classifier is ignored) or a bare
        features state dict (keys 'N.weight')."""
        feats = {k.removeprefix("features."): v for k, v in state.items() if k.startswith("features.")} or dict(state)
        self._load_into(self.features, feats, where, BACKBONE_FILES[self.net])

    def load_lins(self, state: dict[str, torch.Tensor], where: str = "linear heads") -> None:
        """Load the official lpips v0.1 heads: keys 'lin{k}.model.1.weight' (with dropout) or 'lin{k}.model.0.weight'."""
        lins = {}
        for k in range(len(self.lins)):
            key = next((f"lin{k}.model.{i}.weight" for i in (1, 0) if f"lin{k}.model.{i}.weight" in state), None)
            if key is None:
                raise MissingWeightsError(f"LPIPS: {where} lacks lin{k}.model.1.weight; it must be the {LIN_FILES[self.net]}")
            lins[f"{k}.weight"] = state[key]
        self._load_into(self.lins, lins, where, LIN_FILES[self.net])

    @staticmethod
    def _load_into(module: nn.Module, state: dict, where: str, what: str) -> None:
        own = module.state_dict()
        missing = sorted(set(own) - set(state))
        if missing:
            raise MissingWeightsError(f"LPIPS: {where} lacks {missing[:4]}; it must be the {what}")
        for k, v in own.items():
            if tuple(state[k].shape) != tuple(v.shape):
                raise MissingWeightsError(
                    f"LPIPS: {where} has {k} of shape {tuple(state[k].shape)} but expected {tuple(v.shape)}; it must be the {what}"
                )
        module.load_state_dict({k: state[k] for k in own})

    @classmethod
    def from_files(cls, backbone: Path | str | None, lins: Path | str | None, *, net: Net | str = Net.ALEX) -> LPIPS:
        """LPIPS with a torchvision backbone state dict and the official v0.1 linear-head file (.pth or .safetensors)."""
        net = Net(net)
        b = require_weights_file(backbone, model="LPIPS", flag="--lpips-weights", expected=BACKBONE_FILES[net])
        lp = require_weights_file(lins, model="LPIPS", flag="--lpips-lin-weights", expected=LIN_FILES[net])
        model = cls(net)
        model.load_backbone(_load_state(b, BACKBONE_FILES[net]), str(b))
        model.load_lins(_load_state(lp, LIN_FILES[net]), str(lp))
        return model.eval()
