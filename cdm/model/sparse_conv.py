"""Submanifold 3×3×3 convolution of the sparse voxel back-end, and the kernel map its layers share.

Features live on the occupied voxels of a grid only, ``(M, C)`` rows sorted by the key
``b·r³ + (i·r + j)·r + k`` (:class:`cdm.model.voxels.SparseGrid`). The convolution is submanifold: outputs
only at occupied voxels, inputs only from occupied neighbours, which equals a dense ``Conv3d`` with zero
padding read at the occupied voxels when the empty ones hold zeros. The kernel map (which occupied
voxel neighbours which, per offset) is built once per grid and reused by every layer at that resolution.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["KernelMap", "build_kernel_map", "submanifold_conv"]

_CENTRE = 13  # index of the (0, 0, 0) offset among the 27 of a 3×3×3 kernel ([kd, kh, kw] flattened)

_PAIRED = [k for j in range(_CENTRE) for k in (j, 26 - j)]
"""The 26 off-centre offsets, each beside its mirror image: ``[0, 26, 1, 25, …, 12, 14]``."""


class KernelMap(NamedTuple):
    """Neighbour pairs of a submanifold 3×3×3 convolution, built once per grid and shared by its layers.

    An offset ``δ`` pairs ``(o, i)`` exactly when ``−δ`` pairs ``(i, o)``, so offset ``k`` and its mirror
    ``26 − k`` have the same number of pairs. The centre offset pairs every row with itself and is left
    out; the other offsets' pairs are concatenated in the order of ``_PAIRED``, mirror beside mirror, so an
    offset and its mirror share one gather, one batched GEMM and one scatter.

    Attributes:
        out_rows, in_rows: ``(P,)`` the occupied voxel ``in`` is the neighbour of ``out`` at the pair's offset.
        bounds: 14 ints; mirror pair ``j`` (offsets ``j`` and ``26 − j``) holds ``[bounds[j], bounds[j + 1])``,
            offset ``j``'s pairs in its first half.
    """

    out_rows: Tensor
    in_rows: Tensor
    bounds: tuple[int, ...]


def build_kernel_map(keys: Tensor, table: Tensor, resolution: int) -> KernelMap:
    """The :class:`KernelMap` of the occupied voxels ``keys`` (``(M,)`` sorted global keys) of a grid of side
    ``resolution``; ``table`` maps every global key to its row, ``-1`` where the voxel is empty."""
    r = resolution
    device = keys.device
    local = keys % r**3
    ijk = torch.stack([local // (r * r), (local // r) % r, local % r], dim=1)
    steps = torch.arange(-1, 2, device=device)
    offsets = torch.cartesian_prod(steps, steps, steps)  # (27, 3), [kd, kh, kw] order
    nb = ijk[:, None, :] + offsets[None]  # (M, 27, 3)
    inside = ((nb >= 0) & (nb < r)).all(dim=-1)
    # inside the grid, a neighbour's key is the row's key plus its offset's (same sample, no wrap-around)
    nb_keys = torch.where(inside, keys[:, None] + (offsets[:, 0] * r + offsets[:, 1]) * r + offsets[:, 2], 0)
    nb_rows = torch.where(inside, table[nb_keys], -1)  # (M, 27)
    present = (nb_rows >= 0).T[_PAIRED]  # the centre pairs each row with itself: the convolution needs no map
    slot, out_rows = present.nonzero(as_tuple=True)  # by offset (mirror beside mirror), then output row
    in_rows = nb_rows[out_rows, torch.tensor(_PAIRED, device=device)[slot]]
    bounds = F.pad(present.sum(dim=1).view(_CENTRE, 2).sum(1).cumsum(0), (1, 0)).tolist()
    return KernelMap(out_rows, in_rows, tuple(bounds))


def _compute_dtype(x: Tensor) -> torch.dtype:
    """The precision autocast would give the products (``x``'s own outside autocast)."""
    device = x.device.type
    return torch.get_autocast_dtype(device) if torch.is_autocast_enabled(device) else x.dtype


def _offset_major(weight: Tensor) -> Tensor:
    """``(C_out, C_in, 3, 3, 3)`` → ``(27, C_out, C_in)``, offsets in ``[kd, kh, kw]`` order: one transposing
    copy, cheaper than gathering the offsets in another order from the strided view."""
    return weight.flatten(2).flatten(0, 1).T.contiguous().view(27, *weight.shape[:2])


def _mirrors(kernels: Tensor, j: int) -> Tensor:
    """Offsets ``j`` and ``26 − j`` of offset-major ``kernels``, a ``(2, C_out, C_in)`` view (no copy)."""
    return kernels[j : 27 - j : 26 - 2 * j]


class _SubmanifoldConv(torch.autograd.Function):
    """Submanifold 3×3×3 convolution on occupied voxels: ``out[o] = Σ_k W_k · x[i]`` over the pairs
    ``(o, i)`` of each offset ``k`` of a :class:`KernelMap`.

    Gather → GEMM → scatter per offset, as sparse-convolution libraries do on CPU (spconv,
    MinkowskiEngine), with an offset and its mirror in one ``index_select`` → ``bmm`` → ``index_add_``:
    13 rounds of three ops instead of 26. Each round's buffers stay small enough for the cache; gathering
    all offsets at once was slower, and a padded gather-once GEMM over all 27 offsets spends
    ``1 / density`` times the FLOPs on grids 40–60 % dense (``benchmarks/RESULTS.md``, "Lean step
    (issue 54)"). The backward gathers the output gradient once per round and recomputes the gathered
    inputs rather than keep a ``(P, C)`` copy per layer. The products run in autocast's precision when it
    is on; the weight gradient comes back in the weight's dtype.
    """

    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, kmap: KernelMap) -> Tensor:
        dtype = _compute_dtype(x)
        with torch.autocast(x.device.type, enabled=False):
            x = x.to(dtype)
            kernels = _offset_major(weight.to(dtype))
            out = x @ kernels[_CENTRE].T
            for j in range(_CENTRE):
                start, stop = kmap.bounds[j], kmap.bounds[j + 1]
                if stop > start:
                    gathered = x.index_select(0, kmap.in_rows[start:stop]).view(2, (stop - start) // 2, -1)
                    products = torch.bmm(gathered, _mirrors(kernels, j).transpose(1, 2))
                    out.index_add_(0, kmap.out_rows[start:stop], products.view(stop - start, -1))
        ctx.save_for_backward(x, kernels)
        ctx.kmap, ctx.weight_dtype, ctx.weight_shape = kmap, weight.dtype, weight.shape
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None, None]:
        x, kernels = ctx.saved_tensors
        kmap = ctx.kmap
        x, kernels = x.to(grad.dtype), kernels.to(grad.dtype)  # autocast gives a half-precision grad
        need_x, need_w = ctx.needs_input_grad[:2]
        grad_x = grad @ kernels[_CENTRE] if need_x else None
        grad_k = torch.empty_like(kernels) if need_w else None  # (27, C_out, C_in), offset-major as the kernels
        if need_w:
            torch.mm(grad.T, x, out=grad_k[_CENTRE])
        for j in range(_CENTRE):
            start, stop = kmap.bounds[j], kmap.bounds[j + 1]
            if stop == start:
                if need_w:
                    _mirrors(grad_k, j).zero_()
                continue
            half = (stop - start) // 2
            grad_rows = grad.index_select(0, kmap.out_rows[start:stop]).view(2, half, -1)
            if need_x:
                products = torch.bmm(grad_rows, _mirrors(kernels, j))
                grad_x.index_add_(0, kmap.in_rows[start:stop], products.view(stop - start, -1))
            if need_w:
                gathered = x.index_select(0, kmap.in_rows[start:stop]).view(2, half, -1)
                torch.bmm(grad_rows.transpose(1, 2), gathered, out=_mirrors(grad_k, j))
        grad_w = None
        if need_w:
            grad_w = grad_k.flatten(1).T.reshape(ctx.weight_shape).to(ctx.weight_dtype)
        return grad_x, grad_w, None


def submanifold_conv(x: Tensor, weight: Tensor, kmap: KernelMap) -> Tensor:
    """``(M, C_in)`` occupied-voxel features → ``(M, C_out)``; ``weight`` ``(C_out, C_in, 3, 3, 3)`` as ``Conv3d``
    (stride 1, zero padding 1, no bias)."""
    return _SubmanifoldConv.apply(x, weight, kmap)
