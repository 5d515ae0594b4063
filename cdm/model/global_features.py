"""Global image features for the denoiser (supplementary Table 7), ``model.global_feature``:

- ``none``: projection conditioning only — the paper's CDM (global features lowered F1 there).
- ``concat`` (⊕): one pooled embedding per image, broadcast and concatenated to every point's input.
- ``cross_attention`` (⊗): point features attend to a grid of image tokens in one block.

The paper took its embeddings from OpenCLIP (image, text or depth-image embeddings) and injected
them with ControlNet-like multi-scale cross-attention. Offline, we pool the image encoder's own
feature map instead: the mean for ``concat``, an 8×8 average-pooled token grid for
``cross_attention``. Both are computed once per image (:class:`~cdm.model.network.ImageContext`).
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from cdm.model.voxels import norm_groups

__all__ = ["TOKEN_GRID", "PointCrossAttention", "global_embedding", "image_tokens"]


TOKEN_GRID = 8
"""Side of the token grid for ``cross_attention``: ``TOKEN_GRID²`` tokens per image."""


def global_embedding(features: Tensor) -> Tensor:
    """``(B, F, S, S)`` feature map → ``(B, F)`` embedding, the spatial mean."""
    return features.mean(dim=(2, 3))


def image_tokens(features: Tensor, grid: int = TOKEN_GRID) -> Tensor:
    """``(B, F, S, S)`` feature map → ``(B, grid², F)`` tokens by adaptive average pooling, row-major."""
    return F.adaptive_avg_pool2d(features, grid).flatten(2).transpose(1, 2)


class PointCrossAttention(nn.Module):
    """Residual cross-attention from points to image tokens: ``h + Attn(GN(h), tokens + pos)``.

    The output projection starts at zero (as ControlNet's zero convolutions), so inserting the
    block leaves the network's initial function unchanged.

    Args:
        point_channels: ``C`` of the point features (queries).
        token_channels: ``F`` of the tokens (keys and values).
        num_tokens: tokens per image (``TOKEN_GRID²``), each with a learned position embedding.
    """

    def __init__(self, point_channels: int, token_channels: int, num_tokens: int = TOKEN_GRID**2):
        super().__init__()
        self.position = nn.Parameter(0.02 * torch.randn(num_tokens, token_channels))
        self.norm = nn.GroupNorm(norm_groups(point_channels), point_channels)
        self.attn = nn.MultiheadAttention(
            point_channels,
            math.gcd(4, point_channels),
            kdim=token_channels,
            vdim=token_channels,
            batch_first=True,
        )
        nn.init.zeros_(self.attn.out_proj.weight)
        nn.init.zeros_(self.attn.out_proj.bias)

    def forward(self, points: Tensor, tokens: Tensor) -> Tensor:
        """``(B, N, C)`` point features, ``(B, T, F)`` tokens → ``(B, N, C)``."""
        if tokens.shape[1] != self.position.shape[0]:
            raise ValueError(f"expected {self.position.shape[0]} tokens per image, got {tokens.shape[1]}")
        query = self.norm(points.transpose(1, 2)).transpose(1, 2)
        keys = tokens + self.position
        attended, _ = self.attn(query, keys, keys, need_weights=False)
        return points + attended
