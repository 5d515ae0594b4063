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
from torch.autograd.function import once_differentiable

from cdm.config import Devoxelize
from cdm.model.global_features import TOKEN_GRID, PointCrossAttention
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


class _PointNormSiLU(torch.autograd.Function):
    """``SiLU(GroupNorm(h))`` on ``(B, N, C)`` point features in their own layout, forward and backward.

    ``nn.GroupNorm`` wants ``(B, C, N)``: transposing there and back cost two copies forward, one
    backward, and a SiLU backward on mixed layouts (gradient ``(B, N, C)``, input ``(B, C, N)``), ~9× a
    contiguous one on one CPU thread (benchmarks/RESULTS.md, "Lean local step"). The same function:
    statistics per sample and group over its points, biased variance, ``eps`` inside the root.

    Every reduction runs over the points (dim 1), per channel, and channels are then pooled into groups
    on ``(B, C)``: on CPU a sum over dim 1 of ``(B, N, C)`` took ~1 % of ``var_mean`` over ``(N, C/G)``.
    The variance is two-pass (centred per channel, then the law of total variance over the group's channels).
    """

    @staticmethod
    def forward(ctx, h: Tensor, groups: int, weight: Tensor, bias: Tensor, eps: float) -> Tensor:
        n = h.shape[1]
        mean_c = h.sum(dim=1, keepdim=True) / n  # (B, 1, C)
        centred = h - mean_c
        spread_c = centred.square().sum(dim=1, keepdim=True) / n  # each channel's variance about its mean
        mean_g = _group_mean(mean_c, groups)
        rstd = (_group_mean(spread_c + (mean_c - mean_g).square(), groups) + eps).rsqrt()
        # x̂ = (h − μ_group)·r, pre = x̂·weight + bias, written over the centred buffer: on CPU a step is
        # bound by memory traffic, and fresh buffers cost more than the arithmetic.
        scale = rstd * weight
        pre = torch.addcmul(torch.addcmul(bias, mean_c - mean_g, scale), centred, scale, out=centred)
        ctx.save_for_backward(h, pre, mean_g, rstd, weight)
        ctx.groups = groups
        return F.silu(pre)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        h, pre, mean_g, rstd, weight = ctx.saved_tensors
        n = h.shape[1]
        g_pre = torch.ops.aten.silu_backward(grad.contiguous(), pre)
        sum_g = g_pre.sum(dim=1, keepdim=True)  # (B, 1, C)
        sum_gx = (torch.linalg.vecdot(g_pre, h, dim=1).unsqueeze(1) - mean_g * sum_g) * rstd  # Σ g_pre·x̂
        grad_weight = sum_gx.sum(dim=(0, 1)) if ctx.needs_input_grad[2] else None
        grad_bias = sum_g.sum(dim=(0, 1)) if ctx.needs_input_grad[3] else None
        if not ctx.needs_input_grad[0]:
            return None, None, grad_weight, grad_bias, None
        # d/dh of x̂ over a group, with γ = ∂L/∂x̂ = g_pre·weight: r·(γ − mean(γ) − x̂·mean(γ·x̂)), both means
        # pooled from the per-channel sums above; with x̂ = (h − μ)·r, affine in g_pre and h per channel.
        mean_gamma = _group_mean(sum_g * weight, ctx.groups) / n
        mean_gamma_x = _group_mean(sum_gx * weight, ctx.groups) / n
        h_coeff = -mean_gamma_x * rstd * rstd
        constant = (mean_g * mean_gamma_x * rstd - mean_gamma) * rstd
        grad_h = torch.addcmul(constant, g_pre, weight * rstd, out=g_pre)
        return grad_h.addcmul_(h, h_coeff), None, grad_weight, grad_bias, None


def _group_mean(per_channel: Tensor, groups: int) -> Tensor:
    """``(B, 1, C)`` → the mean over each channel's group (``C/G`` consecutive channels), per channel."""
    b, _, c = per_channel.shape
    pooled = per_channel.view(b, groups, c // groups).mean(dim=-1, keepdim=True)
    return pooled.expand(b, groups, c // groups).reshape(b, 1, c)


def point_norm_silu(h: Tensor, norm: nn.GroupNorm) -> Tensor:
    """``SiLU(norm(h))`` for ``(B, N, C)`` point features: GroupNorm statistics per sample over its points.

    In float32 whatever ``h``'s dtype, as autocast runs ``nn.GroupNorm``."""
    return _PointNormSiLU.apply(h.float(), norm.num_groups, norm.weight, norm.bias, norm.eps)


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
