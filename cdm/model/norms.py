"""Fused GroupNorm + SiLU with per-sample statistics, on point features ``(B, N, C)`` and on the sparse
voxel back-end's rows ``(M, C)``, in their own layouts, with a hand-written backward.

The same function as ``nn.GroupNorm`` then SiLU (biased variance, ``eps`` inside the root); the measured
reasons for fusing are in benchmarks/RESULTS.md ("Lean step").
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

__all__ = ["point_norm_silu", "rows_norm_silu"]


class _NormSiLU(torch.autograd.Function):
    """``SiLU(GroupNorm(h))`` per sample, on point features ``(B, N, C)`` or on sparse voxel rows ``(M, C)``
    in their own layout, forward and backward.

    ``nn.GroupNorm`` wants ``(B, C, N)``: transposing there and back cost two copies forward, one
    backward, and a SiLU backward on mixed layouts (gradient ``(B, N, C)``, input ``(B, C, N)``), ~9× a
    contiguous one on one CPU thread (benchmarks/RESULTS.md, "Lean local step"). The same function:
    statistics per sample and group over its points (or occupied voxels), biased variance, ``eps`` inside
    the root.

    Every reduction runs over the points, per channel, and channels are then pooled into groups on
    ``(B, 1, C)``: on CPU a sum over dim 1 of ``(B, N, C)`` took ~1 % of ``var_mean`` over ``(N, C/G)``.
    Sparse rows (sorted by sample) are summed per sample by one product with the grid's ``(B, M)``
    one-hot ``samples`` and the per-sample results spread back to the rows by ``row_batch``.
    The variance is two-pass (centred per channel, then the law of total variance over the group's channels).
    """

    @staticmethod
    def forward(ctx, h: Tensor, groups: int, weight: Tensor, bias: Tensor, eps: float,
                samples: Tensor | None, row_batch: Tensor | None) -> Tensor:
        with torch.autocast(h.device.type, enabled=False):  # the per-sample sums are products for rows
            n = h.shape[1] if samples is None else samples.sum(dim=1).clamp(min=1.0)[:, None, None]
            mean_c = _sums(h, samples) / n  # (B, 1, C)
            centred = h - _spread(mean_c, row_batch)
            spread_c = _sums(centred.square(), samples) / n  # each channel's variance about its mean
            mean_g = _group_mean(mean_c, groups)
            rstd = (_group_mean(spread_c + (mean_c - mean_g).square(), groups) + eps).rsqrt()
            # x̂ = (h − μ_group)·r, pre = x̂·weight + bias, written over the centred buffer: on CPU a step is
            # bound by memory traffic, and fresh buffers cost more than the arithmetic.
            scale = rstd * weight
            shift = torch.addcmul(bias, mean_c - mean_g, scale)
            pre = torch.addcmul(_spread(shift, row_batch), centred, _spread(scale, row_batch), out=centred)
        ctx.save_for_backward(h, pre, mean_g, rstd, weight, samples, row_batch)
        ctx.groups, ctx.n = groups, n
        return F.silu(pre)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        h, pre, mean_g, rstd, weight, samples, row_batch = ctx.saved_tensors
        n = ctx.n
        g_pre = torch.ops.aten.silu_backward(grad.contiguous(), pre)
        sum_g = _sums(g_pre, samples)  # (B, 1, C)
        dot = torch.linalg.vecdot(g_pre, h, dim=1).unsqueeze(1) if samples is None else _sums(g_pre * h, samples)
        sum_gx = (dot - mean_g * sum_g) * rstd  # Σ g_pre·x̂
        grad_weight = sum_gx.sum(dim=(0, 1)) if ctx.needs_input_grad[2] else None
        grad_bias = sum_g.sum(dim=(0, 1)) if ctx.needs_input_grad[3] else None
        if not ctx.needs_input_grad[0]:
            return None, None, grad_weight, grad_bias, None, None, None
        # d/dh of x̂ over a group, with γ = ∂L/∂x̂ = g_pre·weight: r·(γ − mean(γ) − x̂·mean(γ·x̂)), both means
        # pooled from the per-channel sums above; with x̂ = (h − μ)·r, affine in g_pre and h per channel.
        mean_gamma = _group_mean(sum_g * weight, ctx.groups) / n
        mean_gamma_x = _group_mean(sum_gx * weight, ctx.groups) / n
        h_coeff = -mean_gamma_x * rstd * rstd
        constant = (mean_g * mean_gamma_x * rstd - mean_gamma) * rstd
        grad_h = torch.addcmul(_spread(constant, row_batch), g_pre, _spread(weight * rstd, row_batch), out=g_pre)
        return grad_h.addcmul_(h, _spread(h_coeff, row_batch)), None, grad_weight, grad_bias, None, None, None


def _sums(rows: Tensor, samples: Tensor | None) -> Tensor:
    """Per-sample, per-channel sums ``(B, 1, C)`` of ``(B, N, C)`` points or of ``(M, C)`` rows."""
    return rows.sum(dim=1, keepdim=True) if samples is None else (samples @ rows)[:, None]


def _spread(per_sample: Tensor, row_batch: Tensor | None) -> Tensor:
    """``(B, 1, C)`` → broadcastable against the features: as is for points, each row's sample for rows."""
    return per_sample if row_batch is None else per_sample[:, 0].index_select(0, row_batch)


def _group_mean(per_channel: Tensor, groups: int) -> Tensor:
    """``(B, 1, C)`` → the mean over each channel's group (``C/G`` consecutive channels), per channel."""
    b, _, c = per_channel.shape
    pooled = per_channel.view(b, groups, c // groups).mean(dim=-1, keepdim=True)
    return pooled.expand(b, groups, c // groups).reshape(b, 1, c)


def rows_norm_silu(rows: Tensor, norm: nn.GroupNorm, samples: Tensor, row_batch: Tensor) -> Tensor:
    """``SiLU(norm(rows))`` for ``(M, C)`` rows sorted by sample, statistics per sample over its rows:
    ``samples`` the ``(B, M)`` one-hot of ``row_batch`` ``(M,)``, both in ``rows``' dtype and device."""
    return _NormSiLU.apply(rows, norm.num_groups, norm.weight, norm.bias, norm.eps, samples, row_batch)


def point_norm_silu(h: Tensor, norm: nn.GroupNorm) -> Tensor:
    """``SiLU(norm(h))`` for ``(B, N, C)`` point features: GroupNorm statistics per sample over its points.

    In float32 whatever ``h``'s dtype, as autocast runs ``nn.GroupNorm``."""
    return _NormSiLU.apply(h.float(), norm.num_groups, norm.weight, norm.bias, norm.eps, None, None)
