"""Wan2.2 parts of the shortcut generator: widened patch embedding, step-size embedding, condition latents, IO."""

from __future__ import annotations

import contextlib
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from panoworld.models.weights import MissingWeightsError, require_weights_file

MODELS_EXTRA = "pip install '.[models]'"
ADAPTER_NAME = "panoworld"
EXTRA_PREFIXES = ("patch_embedding.", "step_embedder.")
EXTRA_FORMAT = "panoworld-wan-shortcut-extra/1"
# diffusers names of Wan's attention and feed-forward linears (original Wan: q, k, v, o, ffn.0, ffn.2)
DEFAULT_LORA_TARGETS = ("to_q", "to_k", "to_v", "to_out.0", "ffn.net.0.proj", "ffn.net.2")


def import_diffusers():
    """The diffusers module, or an ImportError saying how to install it."""
    try:
        import diffusers
    except ImportError as e:
        raise ImportError(f"the wan-shortcut generator needs diffusers ({e}); {MODELS_EXTRA}") from None
    return diffusers


def widen_patch_embedding(transformer: nn.Module, in_channels: int) -> None:
    """Give `transformer.patch_embedding` `in_channels` inputs; the new input channels get zero weights, so the
    widened model ignores them (its output equals the base model's) until trained."""
    old = transformer.patch_embedding
    if in_channels < old.in_channels:
        raise ValueError(f"cannot narrow patch_embedding from {old.in_channels} to {in_channels} channels")
    new = nn.Conv3d(
        in_channels, old.out_channels, old.kernel_size, old.stride, device=old.weight.device, dtype=old.weight.dtype
    )
    with torch.no_grad():
        new.weight.zero_()
        new.weight[:, : old.in_channels] = old.weight
        new.bias.copy_(old.bias)
    transformer.patch_embedding = new
    transformer.register_to_config(in_channels=in_channels)


class StepSizeEmbedding(nn.Module):
    """MLP on a sinusoidal embedding of the step size dt (in sigma units, scaled like timesteps by 1000),
    added to the timestep embedding. The last layer starts at zero, so at init the model is unchanged."""

    def __init__(self, freq_dim: int, dim: int):
        super().__init__()
        from diffusers.models.embeddings import TimestepEmbedding, Timesteps

        self.proj = Timesteps(num_channels=freq_dim, flip_sin_to_cos=True, downscale_freq_shift=0)
        self.embedder = TimestepEmbedding(in_channels=freq_dim, time_embed_dim=dim)
        nn.init.zeros_(self.embedder.linear_2.weight)
        nn.init.zeros_(self.embedder.linear_2.bias)
        self.dt: torch.Tensor | None = None

    def forward(self, dt: torch.Tensor) -> torch.Tensor:
        """(B,) step sizes -> (B, dim)."""
        weight = self.embedder.linear_1.weight
        return self.embedder(self.proj(dt.to(weight.device, torch.float32) * 1000.0).to(weight.dtype))

    @contextlib.contextmanager
    def step_size(self, dt: torch.Tensor):
        """Within the block, transformer forwards add the embedding of `dt` (B,) to the timestep embedding."""
        self.dt = dt
        try:
            yield
        finally:
            self.dt = None

    def add_to_temb(self, module: nn.Module, args: tuple, temb: torch.Tensor) -> torch.Tensor:
        """Forward hook on condition_embedder.time_embedder: temb (B, dim) or (B, seq, dim) += emb(dt)."""
        if self.dt is None:
            raise RuntimeError("the step size is unset: call the transformer through wan_layers.velocity()")
        emb = self(self.dt).to(temb.dtype)
        return temb + (emb[:, None] if temb.ndim == 3 else emb)


def add_step_size_embedding(transformer: nn.Module) -> StepSizeEmbedding:
    """Attach `transformer.step_embedder` (zero-initialised) and hook it into the timestep embedding."""
    time_embedder = transformer.condition_embedder.time_embedder
    weight = time_embedder.linear_1.weight
    step = StepSizeEmbedding(transformer.config.freq_dim, weight.shape[0]).to(weight.device, weight.dtype)
    transformer.step_embedder = step
    time_embedder.register_forward_hook(step.add_to_temb)
    return step


ANCHOR_MIN_VALID = 0.99
"""Frame 0's condition is the input panorama when at least this fraction of it is valid (a few pixels of invalid
source depth, e.g. at a pole, must not switch the first-frame anchoring off)."""


def anchors_first_frame(valid0) -> bool:
    """Whether the first frame's valid mask (H, W) (numpy or torch, bool or {0, 1}) counts as the given panorama."""
    return float(valid0.float().mean() if hasattr(valid0, "float") else valid0.mean()) >= ANCHOR_MIN_VALID


def condition_channels(vae: nn.Module) -> int:
    """Channels of the condition concatenated to the noisy latent: VAE latents + one mask channel per frame folded
    into a latent frame."""
    return vae.config.z_dim + vae.config.scale_factor_temporal


def prepare_transformer(transformer: nn.Module, cond_channels: int) -> None:
    """Widen the patch embedding for `cond_channels` extra inputs and add the step-size embedding, if not done yet."""
    latent = transformer.config.out_channels
    want = latent + cond_channels
    have = transformer.config.in_channels
    if have == latent:
        widen_patch_embedding(transformer, want)
    elif have != want:
        raise ValueError(f"transformer takes {have} input channels; expected {latent} (base) or {want} (widened)")
    if not hasattr(transformer, "step_embedder"):
        add_step_size_embedding(transformer)


def latent_stats(vae: nn.Module, device, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """The VAE's per-channel latent mean and std, shaped (1, z, 1, 1, 1)."""
    z = vae.config.z_dim
    mean = torch.tensor(vae.config.latents_mean, device=device, dtype=dtype).view(1, z, 1, 1, 1)
    std = torch.tensor(vae.config.latents_std, device=device, dtype=dtype).view(1, z, 1, 1, 1)
    return mean, std


def mask_to_latent(mask: torch.Tensor, temporal: int, spatial: int) -> torch.Tensor:
    """(B, 1, T, H, W) float mask -> (B, temporal, T_lat, H/spatial, W/spatial), T_lat = (T-1)/temporal + 1.

    Spatially the valid fraction per latent pixel (area resize); temporally Wan's rule: the first frame alone
    forms latent frame 0 (repeated `temporal` times), each later latent frame folds `temporal` frames into channels.
    """
    b, _, t, h, w = mask.shape
    if (t - 1) % temporal or h % spatial or w % spatial:
        raise ValueError(f"{mask.shape=}: T-1 must be divisible by {temporal} and H, W by {spatial}")
    small = F.interpolate(mask.flatten(0, 2)[:, None].float(), size=(h // spatial, w // spatial), mode="area")
    small = small.view(b, t, h // spatial, w // spatial)
    small = torch.cat([small[:, :1].expand(b, temporal, -1, -1), small[:, 1:]], dim=1)
    return small.view(b, -1, temporal, h // spatial, w // spatial).transpose(1, 2)


def encode_video(vae: nn.Module, video: torch.Tensor) -> torch.Tensor:
    """(B, 3, T, H, W) in [-1, 1] -> normalised latents (B, z, T_lat, H/s, W/s) float32 (posterior mode)."""
    dist = vae.encode(video.to(vae.dtype)).latent_dist
    mean, std = latent_stats(vae, video.device)
    return (dist.mode().float() - mean) / std


def decode_latents(vae: nn.Module, latents: torch.Tensor) -> torch.Tensor:
    """Normalised latents (B, z, T_lat, h, w) -> video (B, 3, T, H, W) in [-1, 1] float32."""
    mean, std = latent_stats(vae, latents.device)
    return vae.decode((latents * std + mean).to(vae.dtype), return_dict=False)[0].float()


def encode_condition(vae: nn.Module, cond: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Warped video (B, 3, T, H, W) in [-1, 1] and valid mask (B, 1, T, H, W) in {0, 1} -> condition
    (B, z + temporal, T_lat, h, w): latents of cond * mask (holes become 0, mid grey) and the latent-size mask."""
    latents = encode_video(vae, cond * mask)
    small = mask_to_latent(mask, vae.config.scale_factor_temporal, vae.config.scale_factor_spatial)
    return torch.cat([latents, small.to(latents)], dim=1)


def velocity(
    transformer: nn.Module,
    x_t: torch.Tensor,
    sigma: torch.Tensor,
    dt: torch.Tensor | None,
    condition: torch.Tensor | None,
    prompt_embeds: torch.Tensor,
    anchor: torch.Tensor | None = None,
) -> torch.Tensor:
    """One transformer forward: s_theta(x_t, sigma, dt | condition, prompt) -> velocity (eps - x0), float32.

    x_t (B, z, T_lat, h, w); sigma, dt (B,) in [0, 1]; condition (B, Cc, T_lat, h, w); prompt_embeds (B, L, D).
    dt = None and condition = None: the plain base model (no step-size embedding, no widened input).
    anchor (B, z, 1, h, w): a clean first latent frame (Wan2.2 TI2V image conditioning) that replaces
    x_t's first frame, whose tokens get timestep 0; the returned velocity of that frame is meaningless.
    """
    if dt is not None and not hasattr(transformer, "step_embedder"):
        raise ValueError("the transformer has no step-size embedding: call prepare_transformer() first")
    dtype = transformer.patch_embedding.weight.dtype
    timestep = sigma.float() * 1000.0
    if anchor is not None:
        x_t = torch.cat([anchor.to(x_t), x_t[:, :, 1:]], dim=2)
        p_t, p_h, p_w = transformer.config.patch_size
        b, _, t, h, w = x_t.shape
        per_frame = (h // p_h) * (w // p_w)
        timestep = timestep[:, None].repeat(1, (t // p_t) * per_frame)
        timestep[:, :per_frame] = 0.0
    hidden = (x_t if condition is None else torch.cat([x_t, condition.to(x_t)], dim=1)).to(dtype)
    step = transformer.step_embedder.step_size(dt) if dt is not None else contextlib.nullcontext()
    with step:
        out = transformer(
            hidden_states=hidden, timestep=timestep, encoder_hidden_states=prompt_embeds.to(dtype), return_dict=False
        )[0]
    return out.float()


def extra_state_dict(transformer: nn.Module) -> dict[str, torch.Tensor]:
    """The non-LoRA trained weights: the widened patch embedding and the step-size embedding."""
    return {
        k: v.detach().contiguous()
        for k, v in transformer.state_dict().items()
        if k.startswith(EXTRA_PREFIXES) and "lora_" not in k
    }


def save_trained_weights(transformer: nn.Module, lora_path: Path, extra_path: Path) -> None:
    """Write the LoRA (diffusers Wan LoRA format, LoraConfig in the metadata) and the extra weights (safetensors)."""
    import_diffusers()
    from diffusers.loaders import WanLoraLoaderMixin
    from peft.utils import get_peft_model_state_dict
    from safetensors.torch import save_file

    lora_path, extra_path = Path(lora_path), Path(extra_path)
    layers = get_peft_model_state_dict(transformer, adapter_name=ADAPTER_NAME)
    metadata = transformer.peft_config[ADAPTER_NAME].to_dict()
    metadata = {k: sorted(v) if isinstance(v, set) else v for k, v in metadata.items()}
    WanLoraLoaderMixin.save_lora_weights(
        lora_path.parent, transformer_lora_layers=layers, weight_name=lora_path.name,
        transformer_lora_adapter_metadata=metadata,
    )
    extra = extra_state_dict(transformer)
    save_file(extra, str(extra_path), metadata={"format": "pt", "panoworld": EXTRA_FORMAT})


def load_extra_weights(transformer: nn.Module, path: Path) -> None:
    """Widen/extend `transformer` as the file says and load its patch and step-size embedding weights."""
    from safetensors import safe_open

    path = require_weights_file(
        path, model="wan-shortcut", flag="--extra-weights",
        expected="the safetensors of trained patch_embedding.* and step_embedder.* weights",
    )
    with safe_open(str(path), framework="pt") as f:
        state = {k: f.get_tensor(k) for k in f.keys()}
    if "patch_embedding.weight" not in state or not any(k.startswith("step_embedder.") for k in state):
        raise MissingWeightsError(
            f"wan-shortcut: --extra-weights {path} lacks patch_embedding.weight or step_embedder.* "
            f"(has {sorted(state)[:6]}); pass the extra-weights file saved with the LoRA"
        )
    prepare_transformer(transformer, int(state["patch_embedding.weight"].shape[1]) - transformer.config.out_channels)
    own = extra_state_dict(transformer)
    bad = sorted(set(own) ^ set(state)) + sorted(k for k in own.keys() & state.keys() if own[k].shape != state[k].shape)
    if bad:
        raise ValueError(f"{path}: extra weights do not fit this transformer (mismatched keys {bad[:6]})")
    transformer.load_state_dict(state, strict=False)


def load_lora(transformer: nn.Module, path: Path) -> None:
    """Load a Wan LoRA file (diffusers, original-Wan or musubi key layout) as adapter 'panoworld' and check
    that every tensor in the file found its layer."""
    import_diffusers()
    from diffusers.loaders import WanLoraLoaderMixin
    from peft.utils import get_peft_model_state_dict

    path = require_weights_file(
        path, model="wan-shortcut", flag="--lora", expected="the LoRA safetensors (rank 48) trained for wan-shortcut"
    )
    state, metadata = WanLoraLoaderMixin.lora_state_dict(
        str(path.parent), weight_name=path.name, local_files_only=True, return_lora_metadata=True
    )
    n_file = sum(1 for k in state if k.startswith("transformer."))
    if n_file == 0:
        raise ValueError(f"{path}: no 'transformer.*' LoRA tensors (keys like {sorted(state)[:3]})")
    transformer.load_lora_adapter(
        state, prefix="transformer", adapter_name=ADAPTER_NAME, metadata=metadata, low_cpu_mem_usage=False
    )
    n_model = len(get_peft_model_state_dict(transformer, adapter_name=ADAPTER_NAME))
    if n_model != n_file:
        raise ValueError(f"{path}: only {n_model} of {n_file} LoRA tensors matched layers of the transformer")


def load_trained_weights(transformer: nn.Module, lora_path: Path | None, extra_path: Path | None) -> None:
    """Load the extra weights (widening the patch embedding) and then the LoRA on top of the base transformer."""
    load_extra_weights(transformer, extra_path)
    load_lora(transformer, lora_path)
