"""The submanifold convolution as it was before issue 54, kept as the naive reference of the lean one.

One gather → matmul → ``index_add_`` per offset, and the same loop reversed in the backward (cdm at
9fbe9d8, ``cdm/model/voxels.py``). Tests compare :class:`cdm.model.voxels.SparseGrid`'s convolution, its
output and both gradients, with this one.
"""

from __future__ import annotations

import torch
from torch import Tensor

from cdm.model.sparse_conv import KernelMap
from cdm.model.voxels import SparseGrid

__all__ = ["NaiveSubmanifoldConv", "naive_conv", "offset_pairs"]

_CENTRE = 13


def offset_pairs(kmap: KernelMap, rows: int) -> list[tuple[Tensor, Tensor]]:
    """The 27 per-offset ``(out_rows, in_rows)`` pairs of a kernel map over ``rows`` occupied voxels,
    the centre offset's included."""
    every = torch.arange(rows, device=kmap.out_rows.device)
    pairs = {_CENTRE: (every, every)}
    for j in range(_CENTRE):
        start, stop = kmap.bounds[j], kmap.bounds[j + 1]
        middle = (start + stop) // 2
        pairs[j] = (kmap.out_rows[start:middle], kmap.in_rows[start:middle])
        pairs[26 - j] = (kmap.out_rows[middle:stop], kmap.in_rows[middle:stop])
    return [pairs[k] for k in range(27)]


class NaiveSubmanifoldConv(torch.autograd.Function):
    """``out[o] = Σ_k W_k · x[i]`` over the per-offset pairs, one offset at a time."""

    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, pairs: list[tuple[Tensor, Tensor]]) -> Tensor:
        kernels = weight.flatten(2).permute(2, 1, 0).contiguous()  # (27, C_in, C_out)
        out = x @ kernels[_CENTRE]
        for k, (out_rows, in_rows) in enumerate(pairs):
            if k != _CENTRE and out_rows.numel():
                out.index_add_(0, out_rows, x.index_select(0, in_rows) @ kernels[k])
        ctx.save_for_backward(x, kernels)
        ctx.pairs = pairs
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None, None]:
        x, kernels = ctx.saved_tensors
        weight_dtype = kernels.dtype
        x, kernels = x.to(grad.dtype), kernels.to(grad.dtype)
        need_x, need_w = ctx.needs_input_grad[:2]
        grad_x = grad @ kernels[_CENTRE].T if need_x else None
        grad_k = torch.zeros_like(kernels, dtype=weight_dtype) if need_w else None
        if need_w:
            grad_k[_CENTRE] = x.T @ grad
        for k, (out_rows, in_rows) in enumerate(ctx.pairs):
            if k == _CENTRE or not out_rows.numel():
                continue
            g = grad.index_select(0, out_rows)
            if need_x:
                grad_x.index_add_(0, in_rows, g @ kernels[k].T)
            if need_w:
                grad_k[k] = x.index_select(0, in_rows).T @ g
        grad_w = grad_k.permute(2, 1, 0).reshape(kernels.shape[2], kernels.shape[1], 3, 3, 3) if need_w else None
        return grad_x, grad_w, None


def naive_conv(grid: SparseGrid, voxels: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """:meth:`SparseGrid.conv` computed by :class:`NaiveSubmanifoldConv`."""
    out = NaiveSubmanifoldConv.apply(voxels, weight, offset_pairs(grid.kernel_map, voxels.shape[0]))
    return out if bias is None else out + bias
