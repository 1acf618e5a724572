"""Architecture options of PanoVGGT (config.json of its weights)."""

from __future__ import annotations

from dataclasses import dataclass

from panoworld.models.gs_decoder import GaussianHeadConfig
from panoworld.models.weights import JsonConfig


@dataclass(kw_only=True)
class PanoVGGTConfig(JsonConfig):
    """Architecture of PanoVGGT; the defaults follow VGGT-1B (ViT-L width, 24 frame/global block pairs)."""

    patch_size: int = 14
    """Side of the square patches in pixels; input H and W must be multiples of it."""
    embed_dim: int = 1024
    """Token width."""
    depth: int = 24
    """Number of (frame attention, global attention) block pairs in the aggregator."""
    num_heads: int = 16
    """Attention heads per block."""
    mlp_ratio: float = 4.0
    """Hidden width of the block MLPs relative to embed_dim."""
    num_register_tokens: int = 4
    """Register tokens per frame (separate learned sets for frame 0 and the other frames, as in VGGT)."""
    coord_frequencies: int = 8
    """ERP coordinate encoding: sin/cos of k*lon and k*lat for k = 1..coord_frequencies (integer k: 2pi-periodic in lon)."""
    layer_scale_init: float = 0.01
    """Initial LayerScale of every residual branch."""
    camera_trunk_depth: int = 4
    """Transformer blocks of the camera head (attending across frames)."""
    camera_iterations: int = 4
    """Iterative refinement steps of the camera head."""
    pose_correlation: int = 0
    """Channels of the camera head's panoramic correlation cues (0 = off, VGGT's head): each frame's patch features
    correlated with the first frame's at every whole-patch turn about the vertical axis (ErpCorrelation). Not in the
    paper; a from-scratch tiny model does not learn to find the turn between two frames without it."""
    dpt_layers: tuple[int, ...] = (4, 11, 17, 23)
    """Aggregator block pairs whose tokens feed the depth head (four, shallow to deep)."""
    dpt_features: int = 256
    """Channels of the depth head's fusion path."""
    dpt_out_channels: tuple[int, ...] = (256, 512, 1024, 1024)
    """Channels of the four reassembled feature maps of the depth head."""
    image_height: int = 392
    """Input ERP height the weights were trained at (width = 2 * height); frames are resized to it."""
    pose_refine_iters: int = 0
    """Depth-consistency pose refinement in predict(): Gauss-Newton steps of every frame against frame 0, then two
    sweeps over neighbouring frames (pose_refine.refine_sequence), so that the predicted depth maps agree; 0 = off,
    the camera head's poses as VGGT. Not in the paper; no learned parameters; training losses always see the head's
    own poses."""
    gaussian_head: GaussianHeadConfig | None = None
    """The voxel-aligned Gaussian head sharing the aggregator's tokens (None = camera and depth heads only)."""

    def __post_init__(self):
        if isinstance(self.gaussian_head, dict):
            self.gaussian_head = GaussianHeadConfig.from_json(self.gaussian_head)
        if self.gaussian_head is not None and not -self.depth <= self.gaussian_head.backbone_layer < self.depth:
            raise ValueError(f"gaussian_head.backbone_layer={self.gaussian_head.backbone_layer} must index the "
                             f"{self.depth} aggregator block pairs")
        self.dpt_layers = tuple(int(i) for i in self.dpt_layers)
        self.dpt_out_channels = tuple(int(c) for c in self.dpt_out_channels)
        if len(self.dpt_layers) != 4 or len(self.dpt_out_channels) != 4:
            raise ValueError(f"{self.dpt_layers=} and {self.dpt_out_channels=} must both have 4 entries")
        if max(self.dpt_layers) >= self.depth or min(self.dpt_layers) < 0:
            raise ValueError(f"{self.dpt_layers=} must index the {self.depth} aggregator block pairs")
        if self.embed_dim % self.num_heads:
            raise ValueError(f"{self.embed_dim=} is not divisible by {self.num_heads=}")
        if self.image_height % self.patch_size:
            raise ValueError(f"{self.image_height=} is not a multiple of {self.patch_size=}")
        if self.pose_refine_iters < 0:
            raise ValueError(f"{self.pose_refine_iters=} but expected >= 0 (0 = off)")
