"""Voxel branch of the point-voxel denoiser, with a dense and a sparse back-end behind one interface.

A :class:`VoxelGrid` is the structure of one batch of clouds at one voxel resolution ``r``: which
voxel each point falls in and how voxels are laid out. It is built once per forward pass and
resolution (the points do not move inside the network) and offers four operations on voxel
features, used by :class:`VoxelBranch` without knowing the back-end:

- :class:`DenseGrid` (PVCNN): features live on the full ``(B, C, r, r, r)`` grid; voxelise by
  scatter-mean, ``Conv3d``, ``GroupNorm`` over all ``r³`` voxels (empty ones hold zeros).
- :class:`SparseGrid`: features live on the occupied voxels only, ``(M, C)`` rows sorted by the key
  ``b·r³ + (i·r + j)·r + k``; a submanifold 3×3×3 convolution (outputs only at occupied voxels, inputs
  only from occupied neighbours) and ``GroupNorm`` statistics per sample over its occupied voxels.
  A cloud of N points fills at most N of the ``r³`` voxels (≤ 3 % at N = 1,024, r = 32): sparse is
  the faster back-end on CPU, dense on a GPU (:func:`resolve_voxel_backend`).

Both back-ends share the parameters of :class:`VoxelBranch` (same names and shapes) but compute
different functions — a dense convolution and norm also see the empty voxels — so a model must be
sampled with the back-end it was trained with.

Frames: the grids are built from coordinates already normalised into ``[0, 1]³``
(:func:`normalize_coords`); voxel ``(i, j, k)`` spans ``[i/r, (i+1)/r) × …`` along the coordinate
axes (0, 1, 2) and is stored at dense index ``[b, :, i, j, k]``. Voxel centres sit at ``(i + ½)/r``.
No gradient flows to point positions (as in PVCNN); gradients flow to features and parameters.
"""

from __future__ import annotations

import math
import warnings
from abc import ABC, abstractmethod
from typing import Literal, NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from cdm.config import Devoxelize
from cdm.model.norms import rows_norm_silu
from cdm.model.pointops import at_least_float32
from cdm.model.sparse_conv import build_kernel_map, submanifold_conv

__all__ = [
    "DenseGrid",
    "SparseGrid",
    "VoxelBackend",
    "VoxelBranch",
    "VoxelGrid",
    "build_grid",
    "norm_groups",
    "normalize_coords",
    "resolve_voxel_backend",
]

VoxelBackend = Literal["dense", "sparse"]

def norm_groups(channels: int) -> int:
    """GroupNorm groups for ``channels``: 8 as in PVCNN when it divides, else the largest divisor of 8 that does."""
    return math.gcd(8, channels)


def resolve_voxel_backend(backend: str, device: torch.device | str | None = None) -> VoxelBackend:
    """Resolve ``model.voxel_backend``: ``auto`` is ``sparse`` on CPU and ``dense`` on CUDA, the faster
    of the two on each (``benchmarks/RESULTS.md``, "Code choices").

    ``device=None`` means CUDA when it is available.
    """
    if backend in ("dense", "sparse"):
        return backend
    if backend != "auto":
        raise ValueError(f"model.voxel_backend must be 'auto', 'dense' or 'sparse', got {backend!r}")
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    return "dense" if torch.device(device).type == "cuda" else "sparse"


@torch.no_grad()
def normalize_coords(points: Tensor, eps: float = 1e-6) -> Tensor:
    """Map each cloud into ``[0, 1]³`` for voxelisation: centre it on its mean, scale isotropically.

    ``x_t`` lies in ``[-1, 1]³`` only at low noise; at high noise it spreads to |x| ≈ 4, so a fixed
    frame would pile points onto the boundary voxels. Like PVCNN we normalise per cloud, but by the
    largest absolute centred coordinate (L∞) instead of the largest norm, so the cloud's bounding
    cube — not its bounding ball — fills the grid.

    Args:
        points: ``(B, N, 3)`` world coordinates.
    Returns:
        ``(B, N, 3)`` coordinates in ``[0, 1]``, no gradient. A single point (or a cloud collapsed onto
        one position) maps to the centre 0.5.
    """
    centred = points - points.mean(dim=1, keepdim=True)
    scale = centred.abs().amax(dim=(1, 2), keepdim=True)
    return (centred / (2.0 * scale + eps) + 0.5).clamp(0.0, 1.0)


def _trilinear_corners(coords: Tensor, resolution: int) -> tuple[Tensor, Tensor, Tensor]:
    """The 8 voxel centres around each point and their trilinear weights.

    Args:
        coords: ``(P, 3)`` in ``[0, 1]``.
    Returns:
        ``index`` ``(P, 8)`` local voxel index ``(i·r + j)·r + k`` (clamped into the grid),
        ``weight`` ``(P, 8)`` trilinear weights, ``inside`` ``(P, 8)`` bool, the corner is in the grid.
        The point's own voxel is always a corner with weight ≥ 1/8.
    """
    r = resolution
    u = coords * r - 0.5  # continuous index; voxel centres at integers
    lo = torch.floor(u)
    frac = u - lo
    bits = torch.tensor([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], device=coords.device)  # (8, 3)
    corner = lo.long()[:, None, :] + bits  # (P, 8, 3)
    frac = frac[:, None, :]
    weight = torch.where(bits.bool(), frac, 1.0 - frac).prod(dim=-1)
    inside = ((corner >= 0) & (corner < r)).all(dim=-1)
    corner = corner.clamp(0, r - 1)
    index = (corner[..., 0] * r + corner[..., 1]) * r + corner[..., 2]
    return index, weight, inside


class _Interpolation(NamedTuple):
    """Trilinear devoxelisation as a sparse ``(P, R)`` matrix (CSR) and its transpose ``(R, P)``."""

    matrix: Tensor
    transpose: Tensor


def _interpolation(corner_rows: Tensor, weight: Tensor, present: Tensor, num_rows: int) -> _Interpolation:
    """Build :class:`_Interpolation` from ``(P, 8)`` corner rows, trilinear weights and presence.

    Absent corners are dropped and each point's weights renormalised to sum to 1 (its own voxel is
    always present). The present corners of a point are distinct and, in corner order, ascending —
    so the CSR column indices are sorted within each row, as CSR requires.
    """
    w = weight * present.to(weight.dtype)
    w = w / w.sum(dim=1, keepdim=True)
    kept = present.reshape(-1).nonzero().squeeze(1)  # point-major: CSR order
    cols, values = corner_rows.reshape(-1).index_select(0, kept), w.reshape(-1).index_select(0, kept)
    crow = F.pad(present.sum(dim=1).cumsum(0), (1, 0))
    order = torch.sort(cols, stable=True).indices  # stable: point indices stay ascending per voxel
    points = kept // present.shape[1]
    crow_t = F.pad(torch.bincount(cols, minlength=num_rows).cumsum(0), (1, 0))
    with warnings.catch_warnings():
        # torch warns once per process that CSR support is "beta"; CSR @ dense is all we use.
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
        matrix = torch.sparse_csr_tensor(crow, cols, values, size=(weight.shape[0], num_rows), check_invariants=False)
        transpose = torch.sparse_csr_tensor(
            crow_t, points[order], values[order], size=(num_rows, weight.shape[0]), check_invariants=False
        )
    return _Interpolation(matrix, transpose)


class _Interpolate(torch.autograd.Function):
    """``matrix @ rows`` with the precomputed transpose in the backward pass.

    Sparse-matrix products both ways: faster on CPU than ``embedding_bag`` or gather + ``bmm``
    (``benchmarks/RESULTS.md``, "Code choices"). Computed in float32 (or float64) with autocast off:
    there are no half-precision CPU kernels.
    """

    @staticmethod
    def forward(ctx, rows: Tensor, interp: _Interpolation) -> Tensor:
        ctx.transpose, ctx.rows_dtype = interp.transpose, rows.dtype
        with torch.autocast(rows.device.type, enabled=False):
            return interp.matrix @ rows.to(interp.matrix.dtype)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:
        with torch.autocast(grad.device.type, enabled=False):
            return (ctx.transpose @ grad.to(ctx.transpose.dtype)).to(ctx.rows_dtype), None


class VoxelGrid(ABC):
    """Voxel structure of a batch of clouds at one resolution; operations on its voxel features.

    Voxel features ``V`` are back-end specific (dense: ``(B, C, r, r, r)``; sparse: ``(M, C)``);
    only the grid that made them may read them.
    """

    def __init__(self, coords: Tensor, resolution: int):
        if coords.ndim != 3 or coords.shape[-1] != 3:
            raise ValueError(f"coords must be (B, N, 3) in [0, 1], got shape {tuple(coords.shape)}")
        if resolution < 1:
            raise ValueError(f"resolution must be >= 1, got {resolution}")
        self.batch_size, self.num_points = coords.shape[:2]
        self.resolution = resolution
        r = resolution
        self._coords = coords.detach().reshape(-1, 3)
        own = (self._coords * r).floor().long().clamp(0, r - 1)
        self._batch = torch.arange(self.batch_size, device=coords.device).repeat_interleave(self.num_points)
        #: ``(B·N,)`` global key ``b·r³ + (i·r + j)·r + k`` of each point's own voxel.
        self.point_keys = self._batch * r**3 + (own[:, 0] * r + own[:, 1]) * r + own[:, 2]
        self._trilinear: _Interpolation | None = None

    @abstractmethod
    def voxelize(self, features: Tensor) -> Tensor:
        """``(B, N, C)`` point features → voxel features: the mean over each voxel's points."""

    @abstractmethod
    def conv(self, voxels: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        """3×3×3 convolution, stride 1, zero padding 1; ``weight`` ``(C_out, C_in, 3, 3, 3)`` as ``Conv3d``."""

    @abstractmethod
    def group_norm(self, voxels: Tensor, num_groups: int, weight: Tensor, bias: Tensor, eps: float) -> Tensor:
        """GroupNorm with per-sample statistics; affine ``weight``/``bias`` ``(C,)``."""

    def norm_silu(self, voxels: Tensor, norm: nn.GroupNorm) -> Tensor:
        """``SiLU(GroupNorm(voxels))`` with :meth:`group_norm`'s statistics."""
        return F.silu(self.group_norm(voxels, norm.num_groups, norm.weight, norm.bias, norm.eps))

    @abstractmethod
    def _rows(self, voxels: Tensor) -> Tensor:
        """Voxel features as ``(R, C)`` rows, the row space of :meth:`_own_rows` and :meth:`_corner_rows`."""

    @abstractmethod
    def _own_rows(self) -> Tensor:
        """``(B·N,)`` row of each point's own voxel."""

    @abstractmethod
    def _corner_rows(self, keys: Tensor, inside: Tensor) -> tuple[Tensor, Tensor]:
        """Rows of corner voxels given their ``(P, 8)`` global keys and in-grid flags → ``(rows, present)``;
        an absent corner's row may be any valid row."""

    def devoxelize(self, voxels: Tensor, mode: Devoxelize) -> Tensor:
        """Voxel features → ``(B, N, C)`` point features.

        ``nearest``: the point's own voxel. ``trilinear``: the 8 voxel centres around the point,
        weighted trilinearly; corners outside the grid (dense) or unoccupied (sparse) are dropped and
        the rest renormalised. For the dense grid this equals clamping the coordinate to the outermost
        centres (PVCNN; ``grid_sample`` with ``padding_mode="border"``).
        """
        rows = self._rows(voxels)
        if mode == "nearest":
            out = rows.index_select(0, self._own_rows())
        else:
            # Sparse-matrix products lack half-precision CPU kernels: they run in float32 even under autocast.
            dtype = torch.promote_types(rows.dtype, torch.float32)
            if self._trilinear is None or self._trilinear.matrix.dtype != dtype:
                index, weight, inside = _trilinear_corners(self._coords, self.resolution)
                corner_rows, present = self._corner_rows(self._batch[:, None] * self.resolution**3 + index, inside)
                self._trilinear = _interpolation(corner_rows, weight.to(dtype), present, rows.shape[0])
            out = _Interpolate.apply(rows, self._trilinear)
        return out.view(self.batch_size, self.num_points, rows.shape[1])


class DenseGrid(VoxelGrid):
    """PVCNN's dense voxel grid; voxel features ``(B, C, r, r, r)``."""

    def __init__(self, coords: Tensor, resolution: int):
        super().__init__(coords, resolution)
        cells = self.batch_size * resolution**3
        self._counts = torch.bincount(self.point_keys, minlength=cells).clamp(min=1)

    def voxelize(self, features: Tensor) -> Tensor:
        b, n, c = features.shape
        r = self.resolution
        features = at_least_float32(features)
        total = features.new_zeros(b * r**3, c).index_add_(0, self.point_keys, features.reshape(b * n, c))
        mean = total / self._counts[:, None].to(features.dtype)
        return mean.view(b, r, r, r, c).permute(0, 4, 1, 2, 3).contiguous()

    def conv(self, voxels: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        return F.conv3d(voxels, weight, bias, padding=1)

    def group_norm(self, voxels: Tensor, num_groups: int, weight: Tensor, bias: Tensor, eps: float) -> Tensor:
        return F.group_norm(voxels, num_groups, weight, bias, eps)

    def _rows(self, voxels: Tensor) -> Tensor:
        return voxels.permute(0, 2, 3, 4, 1).reshape(-1, voxels.shape[1])

    def _own_rows(self) -> Tensor:
        return self.point_keys

    def _corner_rows(self, keys: Tensor, inside: Tensor) -> tuple[Tensor, Tensor]:
        return keys, inside


class SparseGrid(VoxelGrid):
    """Occupied voxels only; voxel features ``(M, C)``, one row per occupied voxel, sorted by key.

    Attributes:
        keys: ``(M,)`` global key of each row. ``point_rows``: ``(B·N,)`` row of each point's voxel.
        row_batch: ``(M,)`` sample of each row. ``rows_per_sample``: ``(B,)`` occupied voxels per sample.
        kernel_map: the :class:`~cdm.model.sparse_conv.KernelMap` of the submanifold convolution, shared by
            every layer on this grid.
    """

    def __init__(self, coords: Tensor, resolution: int):
        super().__init__(coords, resolution)
        r = resolution
        device = coords.device
        self.keys, self.point_rows, counts = torch.unique(
            self.point_keys, sorted=True, return_inverse=True, return_counts=True
        )
        self._counts = counts
        m = self.keys.shape[0]
        self.row_batch = self.keys // r**3
        self.rows_per_sample = torch.bincount(self.row_batch, minlength=self.batch_size)
        self._table = torch.full((self.batch_size * r**3,), -1, dtype=torch.long, device=device)
        self._table[self.keys] = torch.arange(m, device=device)
        self.kernel_map = build_kernel_map(self.keys, self._table, r)
        self._samples: dict[torch.dtype, Tensor] = {}  # (B, M) one-hot of row_batch, per dtype

    def voxelize(self, features: Tensor) -> Tensor:
        b, n, c = features.shape
        features = at_least_float32(features)
        total = features.new_zeros(self.keys.shape[0], c).index_add_(0, self.point_rows, features.reshape(b * n, c))
        return total / self._counts[:, None].to(features.dtype)

    def conv(self, voxels: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        out = submanifold_conv(voxels, weight, self.kernel_map)
        return out if bias is None else out + bias

    def group_norm(self, voxels: Tensor, num_groups: int, weight: Tensor, bias: Tensor, eps: float) -> Tensor:
        m, c = voxels.shape
        x = voxels.view(m, num_groups, c // num_groups)
        count = (self.rows_per_sample * (c // num_groups)).to(voxels.dtype)[:, None]  # (B, 1)
        mean = voxels.new_zeros(self.batch_size, num_groups).index_add_(0, self.row_batch, x.sum(-1)) / count
        centred = x - mean[self.row_batch][..., None]
        var = (
            voxels.new_zeros(self.batch_size, num_groups).index_add_(0, self.row_batch, centred.square().sum(-1))
            / count
        )
        normed = centred * torch.rsqrt(var + eps)[self.row_batch][..., None]
        return normed.view(m, c) * weight + bias

    def norm_silu(self, voxels: Tensor, norm: nn.GroupNorm) -> Tensor:
        # Fused forward and backward (cdm.model.norms); at least float32, as autocast runs GroupNorm.
        voxels = at_least_float32(voxels)
        samples = self._samples.get(voxels.dtype)
        if samples is None:
            samples = self._samples[voxels.dtype] = F.one_hot(self.row_batch, self.batch_size).T.to(voxels.dtype)
        return rows_norm_silu(voxels, norm, samples, self.row_batch)

    def _rows(self, voxels: Tensor) -> Tensor:
        return voxels

    def _own_rows(self) -> Tensor:
        return self.point_rows

    def _corner_rows(self, keys: Tensor, inside: Tensor) -> tuple[Tensor, Tensor]:
        rows = self._table[keys]
        return rows.clamp(min=0), inside & (rows >= 0)


def build_grid(backend: VoxelBackend, coords: Tensor, resolution: int) -> VoxelGrid:
    """The :class:`VoxelGrid` of ``backend`` for ``(B, N, 3)`` coordinates in ``[0, 1]``."""
    if backend == "dense":
        return DenseGrid(coords, resolution)
    if backend == "sparse":
        return SparseGrid(coords, resolution)
    raise ValueError(f"voxel backend must be 'dense' or 'sparse' (resolve 'auto' first), got {backend!r}")


class VoxelBranch(nn.Module):
    """PVCNN's voxel branch: voxelise → (Conv3d 3³ → GroupNorm → SiLU) × 2 → devoxelise.

    The parameters are plain ``Conv3d`` / ``GroupNorm`` modules whatever the back-end, so the
    dense and sparse models have identical state dicts.

    Args:
        in_channels, out_channels: feature channels before and after.
        resolution: voxel grid side ``r``.
        devoxelize: ``trilinear`` (over the 8 surrounding voxel centres present in the grid,
            renormalised) or ``nearest`` (the point's own voxel).
    """

    def __init__(self, in_channels: int, out_channels: int, resolution: int, devoxelize: Devoxelize = "trilinear"):
        super().__init__()
        self.resolution = resolution
        self.devoxelize = devoxelize
        self.conv1 = nn.Conv3d(in_channels, out_channels, 3, padding=1)
        self.norm1 = nn.GroupNorm(norm_groups(out_channels), out_channels)
        self.conv2 = nn.Conv3d(out_channels, out_channels, 3, padding=1)
        self.norm2 = nn.GroupNorm(norm_groups(out_channels), out_channels)

    def forward(self, features: Tensor, grid: VoxelGrid) -> Tensor:
        """``(B, N, C_in)`` point features on ``grid`` (resolution ``r``) → ``(B, N, C_out)``."""
        if grid.resolution != self.resolution:
            raise ValueError(f"grid resolution {grid.resolution} != branch resolution {self.resolution}")
        v = grid.voxelize(features)
        for conv, norm in ((self.conv1, self.norm1), (self.conv2, self.norm2)):
            v = grid.conv(v, conv.weight, conv.bias)
            v = grid.norm_silu(v, norm)
        return grid.devoxelize(v, self.devoxelize)
