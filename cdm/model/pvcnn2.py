"""PC²'s denoiser, PVCNN2, layer for layer in pure PyTorch (``model.denoiser: pvcnn2``).

The network the paper trained (PC²: lukemelas/projection-conditioned-point-cloud-diffusion,
``experiments/model/pvcnn/pvcnn.py`` with ``pvcnn_utils.py`` and ``modules/``, built through
``experiments/model/point_cloud_model.py``: ``embed_dim=64``, ``dropout=0.1``, multipliers 1):

    SA1  2 × PVConv(32, r 32)              → FPS 1,024, ball r 0.1, K 32, MLP (32, 64)
    SA2  PVConv(64, r 16, voxel attention) → FPS 256,   ball r 0.2, K 32, MLP (64, 128)
    SA3  PVConv(128, r 8)                  → FPS 64,    ball r 0.4, K 32, MLP (128, 256)
    SA4                                      FPS 16,    ball r 0.8, K 32, MLP (256, 256, 512)
    global self-attention over the 16 centres (512 channels)
    FP1  3-NN → MLP (256, 256), 3 × PVConv(256, r 8)      FP2  same
    FP3  3-NN → MLP (256, 128), 2 × PVConv(128, r 16)     FP4  3-NN → MLP (128, 128, 64), 2 × PVConv(64, r 32)
    head Conv1d 64→128, GroupNorm, Swish, Dropout 0.1, Conv1d 128→3 (weight and bias ~ N(0, 1e-6))

PVConv = voxelise → Conv3d 3³ → GroupNorm(8) → Swish → Dropout → Conv3d 3³ → GroupNorm(8) →
Swish (or voxel self-attention) → squeeze-excitation (reduction 8, bias-free, ReLU, sigmoid) →
trilinear devoxelise, plus a point branch Conv1d → GroupNorm(8) → Swish. The time embedding
(64-wide sinusoid through Linear–LeakyReLU(0.1)–Linear) is concatenated to the input of SA2–SA4's
first layer and of every FP level's MLP. Set-abstraction MLPs see ``[neighbour xyz − centre xyz,
neighbour features]``; FP MLPs see ``[interpolated features, time embedding, skip features]``.

PC²'s build quirks are kept because they define the trained network: SA2 and SA3 are configured with
three PVConvs but build only the first (``if c == 0`` / ``elif k == 0`` in ``pvcnn_utils.py``); the
FP attention is never built (its test reads a list that was just emptied); voxel attention has no
1/√C scaling (commented out in ``modules/pvconv.py``). Module names and parameter shapes equal PC²'s
``PVCNN2``, so its state dicts load as they are (:mod:`cdm.model.reference_weights`).

Ours differs in computation only where the numbers do not: the geometric operations are
:mod:`cdm.model.pointops` (no CUDA extension); the time embedding, constant over points, is broadcast
to each level instead of being grouped and 3-NN-interpolated (max-pooling a constant returns it,
interpolating it returns it up to float rounding); voxel attention uses
``scaled_dot_product_attention`` with ``scale=1`` instead of materialising the (r³ × r³) matrix.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from cdm.model import pointops
from cdm.model.global_features import TOKEN_GRID, PointCrossAttention

__all__ = ["PVCNN2Denoiser", "pc2_timestep_embedding"]

GROUPS = 8  # GroupNorm groups everywhere in PC²'s PVCNN2

# PC²'s ``PVCNN2.sa_blocks``: (PVConv width, PVConvs configured, voxel resolution) or None, then
# (centres, ball radius, neighbours, MLP widths). Configured, not built: see the module docstring.
SA_BLOCKS: tuple[tuple[tuple[int, int, int] | None, tuple[int, float, int, tuple[int, ...]]], ...] = (
    ((32, 2, 32), (1024, 0.1, 32, (32, 64))),
    ((64, 3, 16), (256, 0.2, 32, (64, 128))),
    ((128, 3, 8), (64, 0.4, 32, (128, 256))),
    (None, (16, 0.8, 32, (256, 256, 512))),
)
# PC²'s ``PVCNN2.fp_blocks``: (MLP widths), (PVConv width, PVConvs, voxel resolution).
FP_BLOCKS: tuple[tuple[tuple[int, ...], tuple[int, int, int]], ...] = (
    ((256, 256), (256, 3, 8)),
    ((256, 256), (256, 3, 8)),
    ((256, 128), (128, 2, 16)),
    ((128, 128, 64), (64, 2, 32)),
)
HEAD_WIDTH = 128


def pc2_timestep_embedding(t: Tensor, dim: int) -> Tensor:
    """PC²'s sinusoidal embedding (``pvcnn_utils.get_timestep_embedding``): ``(B,)`` → ``(B, dim)``.

    ``[sin(t·ω_i), cos(t·ω_i)]``, ``ω_i = exp(−i · ln(10⁴)/(h − 1))``, ``h = dim // 2`` — note ``h − 1``
    where :func:`cdm.model.pvcnn.timestep_embedding` divides by ``h``; frequencies in float64, then float32.
    """
    half = dim // 2
    freqs = torch.from_numpy(np.exp(np.arange(half) * -(math.log(10000) / (half - 1)))).float().to(t.device)
    angles = t[:, None] * freqs[None]
    return F.pad(torch.cat([torch.sin(angles), torch.cos(angles)], dim=1), (0, dim % 2))


def _pointwise(conv: nn.Module, x: Tensor) -> Tensor:
    """A 1×…×1 ``Conv1d/2d/3d`` on ``(B, C, *S)`` as one batched matmul (faster than the conv on CPU)."""
    w = conv.weight.flatten(1)  # (C_out, C_in)
    out = torch.matmul(w, x.flatten(2)) + conv.bias[:, None]
    return out.view(x.shape[0], w.shape[0], *x.shape[2:])


class SharedMLP(nn.Module):
    """PC²'s ``SharedMLP``: per width, a 1×1 conv → GroupNorm(8) → Swish, on ``(B, C, *S)``.

    Args:
        in_channels: ``C``.
        widths: output channels of each layer.
        dim: 1 (``Conv1d``, points ``(B, C, N)``) or 2 (``Conv2d``, neighbourhoods ``(B, C, M, K)``);
            only the parameter shapes depend on it.
    """

    def __init__(self, in_channels: int, widths: tuple[int, ...], dim: Literal[1, 2] = 1):
        super().__init__()
        conv = nn.Conv1d if dim == 1 else nn.Conv2d
        layers: list[nn.Module] = []
        for width in widths:
            layers += [conv(in_channels, width, 1), nn.GroupNorm(GROUPS, width), nn.SiLU()]
            in_channels = width
        self.layers = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:
        for i in range(0, len(self.layers), 3):
            x = F.silu(self.layers[i + 1](_pointwise(self.layers[i], x)))
        return x


class SelfAttention(nn.Module):
    """PC²'s ``Attention``: ``x + out(softmax(qᵀk) v)`` (no 1/√C), then GroupNorm(8) and Swish.

    Args:
        channels: ``C``.
        dims: 1 (``Conv1d`` projections, ``(B, C, L)``) or 3 (``Conv3d``, ``(B, C, r, r, r)``).
    """

    def __init__(self, channels: int, dims: Literal[1, 3]):
        super().__init__()
        conv = nn.Conv1d if dims == 1 else nn.Conv3d
        self.q, self.k, self.v, self.out = (conv(channels, channels, 1) for _ in range(4))
        self.norm = nn.GroupNorm(GROUPS, channels)

    def forward(self, x: Tensor) -> Tensor:
        tokens = x.flatten(2).transpose(1, 2)  # (B, L, C)
        # Contiguous (B, 1, L, C) projections: strided ones sent CPU attention to its 8× slower math path.
        q, k, v = (F.linear(tokens, p.weight.flatten(1), p.bias)[:, None] for p in (self.q, self.k, self.v))
        h = F.scaled_dot_product_attention(q, k, v, scale=1.0)[:, 0]  # (B, L, C)
        h = F.linear(h, self.out.weight.flatten(1), self.out.bias).transpose(1, 2).reshape(x.shape)
        return F.silu(self.norm(h + x))


class SqueezeExcitation(nn.Module):
    """PC²'s ``SE3d`` with ``use_relu=True``: channel gates ``σ(W₂ ReLU(W₁ mean(x)))``, bias-free, reduction 8."""

    def __init__(self, channels: int, reduction: int = 8):
        super().__init__()
        self.fc = nn.Sequential(
            nn.Linear(channels, channels // reduction, bias=False),
            nn.ReLU(),
            nn.Linear(channels // reduction, channels, bias=False),
            nn.Sigmoid(),
        )

    def forward(self, x: Tensor) -> Tensor:
        """``(B, C, r, r, r)`` → same shape."""
        return x * self.fc(x.mean(dim=(2, 3, 4)))[:, :, None, None, None]


class PVConv(nn.Module):
    """PC²'s ``PVConv`` (``modules/pvconv.py``); ``voxel_layers`` indices as PC²'s (3: dropout, 7: SE).

    Args:
        in_channels, out_channels: point feature channels.
        resolution: voxel grid side ``r``.
        attention: voxel self-attention in place of the second Swish.
        dropout: after the first voxel Swish (PC²: 0.1).
    """

    def __init__(self, in_channels: int, out_channels: int, resolution: int, attention: bool, dropout: float):
        super().__init__()
        self.resolution = resolution
        self.voxel_layers = nn.Sequential(
            nn.Conv3d(in_channels, out_channels, 3, padding=1),
            nn.GroupNorm(GROUPS, out_channels),
            nn.SiLU(),
            nn.Dropout(dropout),
            nn.Conv3d(out_channels, out_channels, 3, padding=1),
            nn.GroupNorm(GROUPS, out_channels),
            SelfAttention(out_channels, 3) if attention else nn.SiLU(),
            SqueezeExcitation(out_channels),
        )
        self.point_features = SharedMLP(in_channels, (out_channels,))

    def forward(self, features: Tensor, cloud: pointops.VoxelizedCloud) -> Tensor:
        """``(B, C_in, N)`` features of the points voxelised in ``cloud`` (resolution ``r``) → ``(B, C_out, N)``."""
        voxels = self.voxel_layers(pointops.voxelize(features, cloud))
        return pointops.trilinear_devoxelize(voxels, cloud) + self.point_features(features)


class SetAbstraction(nn.Module):
    """PC²'s ``PointNetSAModule`` with one ball: FPS centres, group neighbours, MLP, max over neighbours.

    Args:
        in_channels: feature channels (the 3 relative coordinates come on top).
        widths: MLP widths.
        num_centers, radius, num_neighbors: FPS centres ``M``, ball radius (world units of ``x_t``, which
            PC² does not rescale), neighbours ``K``.
    """

    def __init__(self, in_channels: int, widths: tuple[int, ...], num_centers: int, radius: float, num_neighbors: int):
        super().__init__()
        self.num_centers, self.radius, self.num_neighbors = num_centers, radius, num_neighbors
        self.mlps = nn.ModuleList([SharedMLP(in_channels + 3, widths, dim=2)])

    def forward(self, features: Tensor, coords: Tensor) -> tuple[Tensor, Tensor]:
        """``(B, C, N)`` features at ``(B, 3, N)`` coords → ``(B, C_out, M)`` features, ``(B, 3, M)`` centres."""
        centers = pointops.gather_points(coords, pointops.farthest_point_sample(coords, self.num_centers))
        index = pointops.ball_query(centers, coords, self.radius, self.num_neighbors)
        offsets = pointops.group(coords, index) - centers[..., None]
        grouped = torch.cat([offsets, pointops.group(features, index)], dim=1)  # (B, 3 + C, M, K)
        return self.mlps[0](grouped).amax(dim=-1), centers


class FeaturePropagation(nn.Module):
    """PC²'s ``PointNetFPModule``: 3-NN-interpolate centre features to points, concatenate, MLP."""

    def __init__(self, in_channels: int, widths: tuple[int, ...]):
        super().__init__()
        self.mlp = SharedMLP(in_channels, widths)

    def forward(self, points: Tensor, centers: Tensor, center_features: Tensor, temb: Tensor, skip: Tensor) -> Tensor:
        """Args: ``points`` ``(B, 3, N)``, ``centers`` ``(B, 3, M)``, ``center_features`` ``(B, C, M)``,
        ``temb`` ``(B, E)``, ``skip`` ``(B, S, N)`` → ``(B, C_out, N)``."""
        up = pointops.three_nn_interpolate(points, centers, center_features)
        t = temb[:, :, None].expand(-1, -1, points.shape[2])
        return self.mlp(torch.cat([up, t, skip], dim=1))


def _pvconvs(layer: nn.Module) -> list[PVConv]:
    """The PVConvs of one SA/FP level (an SA level without any is a bare :class:`SetAbstraction`)."""
    return [m for m in layer.children() if isinstance(m, PVConv)] if isinstance(layer, nn.Sequential) else []


def _voxelized(cache: dict[int, pointops.VoxelizedCloud], coords: Tensor, resolution: int) -> pointops.VoxelizedCloud:
    """The voxelisation of ``coords`` at ``resolution``, computed once per level (PC² redoes it per PVConv)."""
    if resolution not in cache:
        cache[resolution] = pointops.voxelize_coords(coords, resolution)
    return cache[resolution]


def _scaled(width: int, multiplier: float, field: str) -> int:
    """PC²'s ``int(multiplier · width)``, which GroupNorm(8) requires to be a positive multiple of 8."""
    out = int(multiplier * width)
    if out < GROUPS or out % GROUPS:
        raise ValueError(
            f"model.{field}={multiplier} makes a {width}-channel layer {out} wide; GroupNorm(8) needs a positive "
            "multiple of 8 (e.g. 0.25, 0.5, 1, 2)"
        )
    return out


def _resolution(r: int, vm: float) -> int:
    """Voxel grid side ``r`` scaled by ``model.voxel_resolution_multiplier`` ``vm``; an empty grid is refused."""
    out = int(vm * r)
    if out < 1:
        raise ValueError(f"model.voxel_resolution_multiplier={vm} makes a resolution-{r} grid empty")
    return out


def _sa_layers(
    in_channels: int, wm: float, vm: float, dropout: float, embed_dim: int
) -> tuple[nn.ModuleList, int, list[int]]:
    """PC²'s set-abstraction levels (:data:`SA_BLOCKS`) with widths × ``wm`` and grids × ``vm``: the layers, the
    bottleneck's channels and each level's input channels (the skips the propagation levels take)."""
    sa_layers, skip_channels = [], []
    channels = 3 + in_channels
    for level, (conv, (centers, radius, neighbors, widths)) in enumerate(SA_BLOCKS):
        skip_channels.append(channels)
        blocks: list[nn.Module] = []
        extra = 0 if level == 0 else embed_dim  # the time embedding joins the level's first layer
        if conv is not None:
            width, configured, resolution = conv
            width = _scaled(width, wm, "width_multiplier")
            # PC² builds all of SA1's PVConvs but only the first of any later level's; the voxel
            # attention sits in the odd levels (SA2).
            for p in range(configured if level == 0 else 1):
                blocks.append(
                    PVConv(channels + extra, width, _resolution(resolution, vm), level % 2 == 1 and p == 0, dropout)
                )
                channels, extra = width, 0
        scaled = tuple(_scaled(w, wm, "width_multiplier") for w in widths)
        blocks.append(SetAbstraction(channels + extra, scaled, centers, radius, neighbors))
        channels = scaled[-1]
        sa_layers.append(blocks[0] if len(blocks) == 1 else nn.Sequential(*blocks))
    return nn.ModuleList(sa_layers), channels, skip_channels


def _fp_layers(
    channels: int, skip_channels: list[int], wm: float, vm: float, dropout: float, embed_dim: int
) -> tuple[nn.ModuleList, int]:
    """PC²'s feature-propagation levels (:data:`FP_BLOCKS`) from a ``channels``-wide bottleneck, the skips taken
    deepest first: the layers and their output channels."""
    fp_layers = []
    for level, (widths, (width, count, resolution)) in enumerate(FP_BLOCKS):
        scaled = tuple(_scaled(w, wm, "width_multiplier") for w in widths)
        blocks = [FeaturePropagation(channels + skip_channels[-1 - level] + embed_dim, scaled)]
        channels = scaled[-1]
        width = _scaled(width, wm, "width_multiplier")
        for _ in range(count):
            blocks.append(PVConv(channels, width, _resolution(resolution, vm), False, dropout))
            channels = width
        fp_layers.append(nn.Sequential(*blocks))
    return nn.ModuleList(fp_layers), channels


class PVCNN2Denoiser(nn.Module):
    """PC²'s PVCNN2 as a CDM denoiser: ``(x_t, per-point conditioning, t) → (B, N, 3)``.

    Args:
        in_channels: per-point conditioning channels ``S`` (xyz is prepended here; PC²'s ``in_channels``
            is ``3 + S``: 392 with its RGB, ViT-S/16 features, mask and distance transform).
        width_multiplier: PC²'s, scales every width but the time embedding (paper: 1).
        voxel_resolution_multiplier: PC²'s, scales every voxel resolution (paper: 1).
        dropout: PC²'s, in every PVConv and the head (paper: 0.1).
        embed_dim: time embedding width ``E`` (PC²'s ``point_cloud_model_embed_dim``: 64; ``model.time_embed_dim``).
        token_channels: channels of image tokens for one cross-attention block at the bottleneck (not in
            PC²; supplementary Table 7's ⊗); ``None`` = no block, PC²'s network exactly.
        num_tokens: tokens per image the block attends to.
    """

    def __init__(
        self,
        in_channels: int,
        width_multiplier: float = 1.0,
        voxel_resolution_multiplier: float = 1.0,
        dropout: float = 0.1,
        embed_dim: int = 64,
        token_channels: int | None = None,
        num_tokens: int = TOKEN_GRID**2,
    ):
        super().__init__()
        self.in_channels, self.embed_dim = in_channels, embed_dim
        wm, vm = width_multiplier, voxel_resolution_multiplier
        self.sa_layers, channels, skip_channels = _sa_layers(in_channels, wm, vm, dropout, embed_dim)
        self.global_att = SelfAttention(channels, 1)
        # Supplementary Table 7's ⊗ rows: PC²'s network has no cross-attention and the paper does not say
        # where it adds one; ours lets the bottleneck centres attend to the tokens, after the global
        # attention. Its output projection starts at zero, so PC²'s function is unchanged at the start.
        self.cross_att = (
            PointCrossAttention(channels, token_channels, num_tokens) if token_channels is not None else None
        )
        skip_channels[0] = in_channels  # FP4 takes the inputs without xyz
        self.fp_layers, channels = _fp_layers(channels, skip_channels, wm, vm, dropout, embed_dim)

        head = _scaled(HEAD_WIDTH, wm, "width_multiplier")
        self.classifier = nn.Sequential(SharedMLP(channels, (head,)), nn.Dropout(dropout), nn.Conv1d(head, 3, 1))
        # PC²'s PointCloudModel: the last layer starts near zero, so the first predictions are ≈ 0.
        nn.init.normal_(self.classifier[-1].weight, 0.0, 1e-6)
        nn.init.normal_(self.classifier[-1].bias, 0.0, 1e-6)
        self.embedf = nn.Sequential(nn.Linear(embed_dim, embed_dim), nn.LeakyReLU(0.1), nn.Linear(embed_dim, embed_dim))

    def forward(self, x_t: Tensor, conditioning: Tensor, t: Tensor, tokens: Tensor | None = None) -> Tensor:
        """Denoise.

        Args:
            x_t: ``(B, N, 3)`` noisy points, world frame (PC²'s ball radii are in its units).
            conditioning: ``(B, N, S)`` per-point channels in PC²'s order (``CDMNetwork`` arranges them).
            t: ``(B,)`` timesteps.
            tokens: ``(B, T, F)`` image tokens when built with ``token_channels``, else ``None``.
        Returns:
            ``(B, N, 3)`` raw output.
        """
        if conditioning.shape[:2] != x_t.shape[:2] or conditioning.shape[2] != self.in_channels:
            raise ValueError(
                f"conditioning must be (B, N, {self.in_channels}) for x_t {tuple(x_t.shape)}, "
                f"got {tuple(conditioning.shape)}"
            )
        if (tokens is None) != (self.cross_att is None):
            raise ValueError("pass tokens exactly when the denoiser was built with token_channels")
        temb = self.embedf(pc2_timestep_embedding(t, self.embed_dim).to(x_t.dtype))  # (B, E)
        inputs = torch.cat([x_t, conditioning], dim=-1).transpose(1, 2)  # (B, 3 + S, N)
        coords, features = inputs[:, :3].contiguous(), inputs
        coords_list, skips = [], []
        for level, layer in enumerate(self.sa_layers):
            skips.append(features)
            coords_list.append(coords)
            if level > 0:
                features = torch.cat([features, temb[:, :, None].expand(-1, -1, features.shape[2])], dim=1)
            clouds: dict[int, pointops.VoxelizedCloud] = {}
            for conv in _pvconvs(layer):
                features = conv(features, _voxelized(clouds, coords, conv.resolution))
            sa = layer[-1] if isinstance(layer, nn.Sequential) else layer
            features, coords = sa(features, coords)
        skips[0] = inputs[:, 3:]
        features = self.global_att(features)
        if self.cross_att is not None:
            features = self.cross_att(features.transpose(1, 2), tokens).transpose(1, 2)
        for level, layer in enumerate(self.fp_layers):
            points = coords_list[-1 - level]
            features = layer[0](points, coords, features, temb, skips[-1 - level])
            clouds = {}
            for conv in _pvconvs(layer):
                features = conv(features, _voxelized(clouds, points, conv.resolution))
            coords = points
        return self._head(features).transpose(1, 2)

    def _head(self, features: Tensor) -> Tensor:
        """``(B, 64·wm, N)`` → ``(B, 3, N)``: PC²'s classifier."""
        mlp, dropout, out = self.classifier
        return _pointwise(out, dropout(mlp(features)))
