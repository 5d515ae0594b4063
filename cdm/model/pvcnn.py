"""Point-voxel denoiser (PVCNN-style, as PC²'s backbone) in pure PyTorch.

``x_t (B, N, 3)`` and per-point conditioning ``(B, N, C)`` → ``(B, N, 3)``. Every point is kept at
every block (no set abstraction / feature propagation, whose FPS, ball query and 3-NN ops are the
CUDA extensions PC² depends on); the voxel branch supplies the neighbourhood context instead:

    h₀ = Linear([xyz, conditioning])
    h_{i+1} = VoxelBranch_i(h_i + T_i(τ)) + SiLU(GN(Linear_i(h_i + T_i(τ))))     (PVConv)
    out = Linear(SiLU(GN(Linear(h_L))))

with ``τ`` the sinusoidal timestep embedding through a two-layer MLP and ``T_i`` a per-block linear
map of it. The voxel grids are built once per forward pass from ``x_t`` normalised per cloud into
``[0, 1]³`` (:func:`~cdm.model.voxels.normalize_coords`: centred, scaled by its largest absolute
coordinate, since ``x_t`` leaves ``[-1, 1]³`` at high noise); blocks of equal resolution share one.
With ``token_channels`` set, one :class:`~cdm.model.global_features.PointCrossAttention` follows the
middle block.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from cdm.config import Devoxelize
from cdm.model.global_features import TOKEN_GRID, PointCrossAttention
from cdm.model.norms import point_norm_silu
from cdm.model.voxels import (
    VoxelBackend,
    VoxelBranch,
    VoxelGrid,
    build_grid,
    norm_groups,
    normalize_coords,
)

__all__ = ["PVCNNDenoiser", "PointVoxelBlock", "point_norm_silu", "timestep_embedding"]


def timestep_embedding(t: Tensor, dim: int, max_period: float = 10_000.0) -> Tensor:
    """Sinusoidal embedding of integer timesteps (Transformer / DDPM): ``(B,)`` → ``(B, dim)``.

    ``[sin(t·ω_0..ω_{h−1}), cos(t·ω_0..ω_{h−1})]`` with ``ω_i = max_period^(−i/h)``, ``h = dim // 2``;
    an odd ``dim`` gets a trailing zero.
    """
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    angles = t.to(torch.float32)[:, None] * freqs[None]
    emb = torch.cat([torch.sin(angles), torch.cos(angles)], dim=1)
    return F.pad(emb, (0, dim % 2))


class PointVoxelBlock(nn.Module):
    """One PVConv block with time injection: voxel branch + point MLP, summed.

    Args:
        in_channels, out_channels: point feature channels before / after.
        resolution: voxel grid side of the branch.
        time_channels: size of the time embedding ``τ``.
        devoxelize: ``trilinear`` or ``nearest`` (:class:`~cdm.model.voxels.VoxelBranch`).
    """

    def __init__(
        self, in_channels: int, out_channels: int, resolution: int, time_channels: int, devoxelize: Devoxelize
    ):
        super().__init__()
        self.time = nn.Linear(time_channels, in_channels)
        self.voxel = VoxelBranch(in_channels, out_channels, resolution, devoxelize)
        self.point = nn.Linear(in_channels, out_channels)
        self.point_norm = nn.GroupNorm(norm_groups(out_channels), out_channels)

    def forward(self, h: Tensor, temb: Tensor, grids: dict[int, VoxelGrid]) -> Tensor:
        """``(B, N, C_in)``, ``(B, time_channels)``, grids by resolution → ``(B, N, C_out)``."""
        h = h + self.time(temb)[:, None, :]
        point = point_norm_silu(self.point(h), self.point_norm)
        return self.voxel(h, grids[self.voxel.resolution]) + point


class PVCNNDenoiser(nn.Module):
    """Point-voxel denoiser; see the module docstring for the architecture.

    Args:
        in_channels: per-point conditioning channels ``C`` (xyz is appended here, not counted).
        widths: channels of the blocks (``model.widths``).
        resolutions: voxel grid side per block (``model.voxel_resolutions``).
        time_embed_dim: sinusoidal embedding size (``model.time_embed_dim``).
        voxel_backend: ``dense`` or ``sparse`` (resolved; see ``resolve_voxel_backend``).
        devoxelize: ``trilinear`` or ``nearest``.
        token_channels: channels of image tokens for one cross-attention block; ``None`` = no block.
        num_tokens: tokens per image the block attends to (``TOKEN_GRID²`` pooled features, or ``T``
            per-object embeddings).
    """

    def __init__(
        self,
        in_channels: int,
        widths: tuple[int, ...],
        resolutions: tuple[int, ...],
        time_embed_dim: int,
        voxel_backend: VoxelBackend,
        devoxelize: Devoxelize = "trilinear",
        token_channels: int | None = None,
        num_tokens: int = TOKEN_GRID**2,
    ):
        super().__init__()
        if len(widths) != len(resolutions) or not widths:
            raise ValueError("model.widths and model.voxel_resolutions must be non-empty and of equal length")
        if voxel_backend not in ("dense", "sparse"):
            raise ValueError(f"voxel_backend must be 'dense' or 'sparse' (resolve 'auto' first), got {voxel_backend!r}")
        self.in_channels = in_channels
        self.voxel_backend = voxel_backend
        self.time_embed_dim = time_embed_dim
        self.time_mlp = nn.Sequential(
            nn.Linear(time_embed_dim, time_embed_dim), nn.SiLU(), nn.Linear(time_embed_dim, time_embed_dim)
        )
        self.stem = nn.Linear(3 + in_channels, widths[0])
        ins = (widths[0],) + tuple(widths[:-1])
        self.blocks = nn.ModuleList(
            PointVoxelBlock(i, o, r, time_embed_dim, devoxelize) for i, o, r in zip(ins, widths, resolutions)
        )
        self.attention_after = len(widths) // 2 if token_channels is not None else None
        self.attention = (
            PointCrossAttention(widths[self.attention_after], token_channels, num_tokens)
            if token_channels is not None
            else None
        )
        last = widths[-1]
        self.head = nn.Linear(last, last)
        self.head_norm = nn.GroupNorm(norm_groups(last), last)
        self.out = nn.Linear(last, 3)

    def forward(self, x_t: Tensor, conditioning: Tensor, t: Tensor, tokens: Tensor | None = None) -> Tensor:
        """Denoise.

        Args:
            x_t: ``(B, N, 3)`` noisy points, world frame.
            conditioning: ``(B, N, C)`` per-point conditioning (projection + global features).
            t: ``(B,)`` long timesteps.
            tokens: ``(B, T, F)`` image tokens when built with ``token_channels``, else ``None``.
        Returns:
            ``(B, N, 3)`` raw output (its meaning — ε, x₀ or v — is the diffusion's business).
        """
        if conditioning.shape[:2] != x_t.shape[:2] or conditioning.shape[2] != self.in_channels:
            raise ValueError(
                f"conditioning must be (B, N, {self.in_channels}) for x_t {tuple(x_t.shape)}, "
                f"got {tuple(conditioning.shape)}"
            )
        if (tokens is None) != (self.attention is None):
            raise ValueError("pass tokens exactly when the denoiser was built with token_channels")
        coords = normalize_coords(x_t)
        grids = {r: build_grid(self.voxel_backend, coords, r) for r in {b.voxel.resolution for b in self.blocks}}
        temb = self.time_mlp(timestep_embedding(t, self.time_embed_dim))
        h = self.stem(torch.cat([x_t, conditioning], dim=-1))
        for i, block in enumerate(self.blocks):
            h = block(h, temb, grids)
            if i == self.attention_after:
                h = self.attention(h, tokens)
        return self.out(point_norm_silu(self.head(h), self.head_norm))
