"""A set of 3D Gaussians (numpy arrays or torch tensors) and its SH colour convention, importable without torch."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SH_C0 = 0.28209479177387814
"""Degree-0 real spherical harmonic: rgb = 0.5 + SH_C0 * f_dc (the INRIA 3DGS convention)."""


@dataclass
class Gaussians:
    """A set of N 3D Gaussians in the world (canonical scene) frame.

    Fields are numpy float32 arrays, or torch tensors when they come straight from the Gaussian head (kept differentiable).
    """

    means: np.ndarray
    """(N, 3) centres in metres."""
    scales: np.ndarray
    """(N, 3) standard deviations along the rotated axes, metres (linear, not log)."""
    quats: np.ndarray
    """(N, 4) rotations (w, x, y, z), normalised when used; columns of the rotation matrix are the Gaussian's axes."""
    opacities: np.ndarray
    """(N,) opacity in (0, 1) (not logit)."""
    sh_dc: np.ndarray
    """(N, 3) degree-0 SH colour coefficients: rgb = 0.5 + SH_C0 * sh_dc."""
    sh_rest: np.ndarray | None = None
    """(N, K, 3) higher-order SH coefficients, K in {0, 3, 8, 15} (coefficient-major like INRIA's in-memory layout)."""

    def __post_init__(self):
        n = self.means.shape[0]
        if self.sh_rest is None:
            self.sh_rest = np.zeros((n, 0, 3), np.float32)
        expect = {
            "means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,), "sh_dc": (n, 3),
        }
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"Gaussians.{name}.shape={got} but expected {shape} (N={n})")
        k = tuple(self.sh_rest.shape)
        if len(k) != 3 or k[0] != n or k[2] != 3 or k[1] not in (0, 3, 8, 15):
            raise ValueError(f"Gaussians.sh_rest.shape={k} but expected ({n}, K, 3) with K in (0, 3, 8, 15)")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return {0: 0, 3: 1, 8: 2, 15: 3}[int(self.sh_rest.shape[1])]

    def base_colors(self) -> np.ndarray:
        """(N, 3) view-independent colour 0.5 + SH_C0 * sh_dc clipped to [0, 1]."""
        return np.clip(0.5 + SH_C0 * np.asarray(self.sh_dc, np.float32), 0.0, 1.0)

    def subset(self, index) -> Gaussians:
        """Gaussians selected by a boolean mask or an index array."""
        return Gaussians(
            means=self.means[index], scales=self.scales[index], quats=self.quats[index],
            opacities=self.opacities[index], sh_dc=self.sh_dc[index], sh_rest=self.sh_rest[index],
        )

    def numpy(self) -> Gaussians:
        """A detached float32 numpy copy (from torch tensors or numpy arrays)."""

        def conv(a):
            if hasattr(a, "detach"):  # a torch tensor (torch is not imported here: the asset stage runs without it)
                a = a.detach().cpu().numpy()
            return np.ascontiguousarray(a, dtype=np.float32)

        return Gaussians(
            means=conv(self.means), scales=conv(self.scales), quats=conv(self.quats),
            opacities=conv(self.opacities), sh_dc=conv(self.sh_dc), sh_rest=conv(self.sh_rest),
        )


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Colour in [0, 1] (..., 3) -> degree-0 SH coefficient."""
    return (rgb - 0.5) / SH_C0


@dataclass
class FusionResult:
    """Gaussians from voxel fusion plus statistics for reports."""

    gaussians: Gaussians
    num_observations: int
    """Pixels fused."""
    num_voxels: int
    """Occupied voxels (before pruning)."""
    num_pruned: int
    """Voxels (or voxel parts) dropped as empty or degenerate."""
    extent_m: list[float]
    """Size of the Gaussians' bounding box (x, y, z) in metres."""
    voxel_size: float
    backend: str = "voxel-fusion"
    num_source: int = 0
    """Per-pixel Gaussians of the source view among them (source_anchored_fusion)."""
    color_fit: dict | None = None
    """The colour fit at the capture point, when one ran (pixel_gaussians.fit_colors' statistics)."""
    back_sides: dict | None = None
    """The back-side layer's statistics, when one was added (panoworld.room.back_sides)."""
    own_fill: dict | None = None
    """A home's panoramas' own fill of their pixels without depth, when on: {NAME: {"filled", "stood_for"}}
    (gaussians.home.add_own_fill)."""
    fit_render: tuple[np.ndarray, np.ndarray] | None = None
    """The colour fit's render of the final Gaussians at frame 0's pose, when one ran: (rgb (H, W, 3), alpha (H, W))
    float32 at the fit's height (write_artifact's self-check of frame 0 downsamples it instead of rendering again)."""


@dataclass
class ContextFrames:
    """The frames a gaussians run fuses: colour, depth and pose of each, in the canonical world frame."""

    rgb: np.ndarray
    """(V, H, W, 3) uint8 ERP frames."""
    depth: np.ndarray
    """(V, H, W) float32 ray-distance depth in metres, NaN where unknown."""
    world_from_cam: np.ndarray
    """(V, 4, 4) float64 poses."""
    indices: list[int]
    """Frame numbers in the video."""
    depth_source: str
    """'poses' or 'video': which artifact's depth/NNNNNN.png was used."""

    def rgb_at(self, k: int) -> np.ndarray:
        return self.rgb[k]
