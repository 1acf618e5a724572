"""Real-ESRGAN RRDBNet (x2 via pixel-unshuffle) loading the official RealESRGAN_x2plus.pth; ERP-seam-aware tiling."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from panoworld.core.progress import bar
from panoworld.core.shapes import check_shape
from panoworld.models.weights import read_state_file, require_weights_file

EXPECTED_FILE = "RealESRGAN_x2plus.pth (official Real-ESRGAN release; state dict under 'params_ema' or 'params')"


class ResidualDenseBlock(nn.Module):
    """Five 3x3 convs with dense connections, residual scaled by 0.2."""

    def __init__(self, num_feat: int = 64, num_grow_ch: int = 32):
        super().__init__()
        self.conv1 = nn.Conv2d(num_feat, num_grow_ch, 3, 1, 1)
        self.conv2 = nn.Conv2d(num_feat + num_grow_ch, num_grow_ch, 3, 1, 1)
        self.conv3 = nn.Conv2d(num_feat + 2 * num_grow_ch, num_grow_ch, 3, 1, 1)
        self.conv4 = nn.Conv2d(num_feat + 3 * num_grow_ch, num_grow_ch, 3, 1, 1)
        self.conv5 = nn.Conv2d(num_feat + 4 * num_grow_ch, num_feat, 3, 1, 1)
        self.lrelu = nn.LeakyReLU(negative_slope=0.2, inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x1 = self.lrelu(self.conv1(x))
        x2 = self.lrelu(self.conv2(torch.cat((x, x1), 1)))
        x3 = self.lrelu(self.conv3(torch.cat((x, x1, x2), 1)))
        x4 = self.lrelu(self.conv4(torch.cat((x, x1, x2, x3), 1)))
        x5 = self.conv5(torch.cat((x, x1, x2, x3, x4), 1))
        return x5 * 0.2 + x


class RRDB(nn.Module):
    """Residual in residual dense block."""

    def __init__(self, num_feat: int, num_grow_ch: int = 32):
        super().__init__()
        self.rdb1 = ResidualDenseBlock(num_feat, num_grow_ch)
        self.rdb2 = ResidualDenseBlock(num_feat, num_grow_ch)
        self.rdb3 = ResidualDenseBlock(num_feat, num_grow_ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.rdb3(self.rdb2(self.rdb1(x))) * 0.2 + x


class RRDBNet(nn.Module):
    """ESRGAN generator with the official parameter names; scale 2 and 1 fold the input with pixel-unshuffle."""

    def __init__(
        self,
        num_in_ch: int = 3,
        num_out_ch: int = 3,
        scale: int = 2,
        num_feat: int = 64,
        num_block: int = 23,
        num_grow_ch: int = 32,
    ):
        super().__init__()
        if scale not in (1, 2, 4):
            raise ValueError(f"{scale=} but RRDBNet supports 1, 2 or 4")
        self.scale = scale
        unshuffle = {1: 4, 2: 2, 4: 1}[scale]
        self.unshuffle = unshuffle
        self.conv_first = nn.Conv2d(num_in_ch * unshuffle**2, num_feat, 3, 1, 1)
        self.body = nn.Sequential(*[RRDB(num_feat, num_grow_ch) for _ in range(num_block)])
        self.conv_body = nn.Conv2d(num_feat, num_feat, 3, 1, 1)
        self.conv_up1 = nn.Conv2d(num_feat, num_feat, 3, 1, 1)
        self.conv_up2 = nn.Conv2d(num_feat, num_feat, 3, 1, 1)
        self.conv_hr = nn.Conv2d(num_feat, num_feat, 3, 1, 1)
        self.conv_last = nn.Conv2d(num_feat, num_out_ch, 3, 1, 1)
        self.lrelu = nn.LeakyReLU(negative_slope=0.2, inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [0, 1] -> (B, 3, scale*H, scale*W); H, W divisible by 4 // scale."""
        feat = F.pixel_unshuffle(x, self.unshuffle) if self.unshuffle > 1 else x
        feat = self.conv_first(feat)
        feat = feat + self.conv_body(self.body(feat))
        feat = self.lrelu(self.conv_up1(F.interpolate(feat, scale_factor=2, mode="nearest")))
        feat = self.lrelu(self.conv_up2(F.interpolate(feat, scale_factor=2, mode="nearest")))
        return self.conv_last(self.lrelu(self.conv_hr(feat)))


def rrdbnet_from_state_dict(state: dict[str, torch.Tensor]) -> RRDBNet:
    """Build an RRDBNet whose architecture (scale, num_feat, num_block, num_grow_ch) is read off the state dict."""
    try:
        first = state["conv_first.weight"]
        num_feat, in_folded = int(first.shape[0]), int(first.shape[1])
        num_out_ch = int(state["conv_last.weight"].shape[0])
        num_grow_ch = int(state["body.0.rdb1.conv1.weight"].shape[0])
    except KeyError as e:
        raise ValueError(f"not an RRDBNet state dict: key {e} missing (expected the Real-ESRGAN layout)") from None
    num_block = 1 + max(int(m.group(1)) for k in state if (m := re.match(r"body\.(\d+)\.", k)))
    num_in_ch = num_out_ch
    scale = {1: 4, 4: 2, 16: 1}.get(in_folded // num_in_ch)
    if scale is None or in_folded % num_in_ch:
        raise ValueError(f"conv_first takes {in_folded} channels: not 3, 12 or 48 (scale 4, 2, 1)")
    model = RRDBNet(num_in_ch, num_out_ch, scale=scale, num_feat=num_feat, num_block=num_block, num_grow_ch=num_grow_ch)
    model.load_state_dict(state, strict=True)
    return model


def load_rrdbnet(weights: Path | str | None) -> RRDBNet:
    """Load an official Real-ESRGAN .pth (keys under 'params_ema' or 'params', or a bare state dict) or .safetensors."""
    path = require_weights_file(weights, model="RealESRGAN x2", flag="--upscale-weights", expected=EXPECTED_FILE)
    state = read_state_file(path, model="RealESRGAN x2", expected=EXPECTED_FILE)
    for key in ("params_ema", "params"):
        if isinstance(state, dict) and key in state:
            state = state[key]
            break
    return rrdbnet_from_state_dict(state).eval()


def pad_erp(image: torch.Tensor, pad: int) -> torch.Tensor:
    """Pad (B, C, H, W) ERP images by `pad` pixels continuing the sphere: wrapped columns left/right,
    rows mirrored across the pole and rotated by 180 degrees of longitude at top/bottom."""
    h, w = image.shape[-2:]
    if pad > h or w % 2:
        raise ValueError(f"{image.shape=}: ERP padding needs an even width and pad <= H (got {pad=})")
    top = torch.roll(image[..., :pad, :].flip(-2), w // 2, dims=-1)
    bottom = torch.roll(image[..., h - pad :, :].flip(-2), w // 2, dims=-1)
    image = torch.cat([top, image, bottom], dim=-2)
    return torch.cat([image[..., w - pad :], image, image[..., :pad]], dim=-1)


@torch.no_grad()
def upscale_tensor(model: RRDBNet, image: torch.Tensor, *, tile: int = 0, pad: int = 16) -> torch.Tensor:
    """Upscale (B, 3, H, W) ERP images in [0, 1] by model.scale with `pad` px of sphere-continued context.

    tile = 0 runs whole frames; otherwise tiles of tile x tile output-source pixels, each with `pad` px of
    context, are stitched. Tiled and whole-frame results agree exactly when `pad` covers the receptive field.
    """
    b, c, h, w = image.shape
    m = model.unshuffle
    if h % m or w % m or pad % m or (tile and tile % m):
        raise ValueError(f"{image.shape=}, {pad=}, {tile=}: H, W, pad and tile must be divisible by {m}")
    s = model.scale
    padded = pad_erp(image, pad) if pad else image
    if not tile:
        out = model(padded)
        return out[..., s * pad : s * (pad + h), s * pad : s * (pad + w)].clamp_(0, 1)
    out = image.new_empty(b, c, s * h, s * w)
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            piece = model(padded[..., y0 : y1 + 2 * pad, x0 : x1 + 2 * pad])
            out[..., s * y0 : s * y1, s * x0 : s * x1] = piece[
                ..., s * pad : s * (pad + y1 - y0), s * pad : s * (pad + x1 - x0)
            ]
    return out.clamp_(0, 1)


def upscale_frames(
    model: RRDBNet, frames: np.ndarray, *, tile: int = 0, pad: int = 16, device: str = "cpu", dtype: str = "float32"
) -> np.ndarray:
    """(T, H, W, 3) uint8 RGB ERP frames -> (T, s*H, s*W, 3) uint8 with s = model.scale, one frame at a time."""
    check_shape("frames", frames, "T H W 3", dtype=np.uint8)
    model = model.to(device=device, dtype=getattr(torch, dtype))
    t, h, w, _ = frames.shape
    out = np.empty((t, model.scale * h, model.scale * w, 3), np.uint8)
    for i in bar(range(t), desc="realesrgan", leave=False):
        x = torch.from_numpy(frames[i]).to(device).permute(2, 0, 1)[None].to(model.conv_first.weight.dtype) / 255
        y = upscale_tensor(model, x, tile=tile, pad=pad)[0].float()
        out[i] = (y * 255).round_().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    return out


def upscale_realesrgan(
    frames: np.ndarray,
    weights: Path | str | None,
    *,
    tile: int = 0,
    pad: int = 16,
    device: str = "cpu",
    dtype: str = "float32",
) -> np.ndarray:
    """Upscale (T, H, W, 3) uint8 ERP frames x2 with Real-ESRGAN loaded from `weights` -> (T, 2H, 2W, 3) uint8.

    Context across the ERP seam and poles comes from the sphere (see pad_erp), so the left/right borders match.
    tile > 0 bounds memory for big frames; dtype 'float16' halves it on GPU.
    """
    return upscale_frames(load_rrdbnet(weights), frames, tile=tile, pad=pad, device=device, dtype=dtype)
