"""PC²'s geometric point operations in pure PyTorch (CPU and GPU from the same code).

PC²'s PVCNN2 (lukemelas/projection-conditioned-point-cloud-diffusion,
``experiments/model/pvcnn/modules/functional/``) runs six CUDA extensions. This module computes the
same functions with tensor operations, following the kernels in ``functional/src/``:

- :func:`farthest_point_sample` (``sampling/sampling.cu``): starts at point 0; each step takes the
  point farthest (squared distance) from the chosen set. The kernel scans point ``k`` on thread
  ``k mod 512`` and its reduction keeps the lower thread on a tie, so among tied points the one with
  the smallest ``(k mod 512, k // 512)`` wins; we scan the points in that order to reproduce it.
  With more centres than points the extra centres repeat point 0 (every distance is then 0).
- :func:`ball_query` (``ball_query/ball_query.cu``): per centre, the first ``K`` points in index
  order with squared distance ``< r²`` (``r²`` rounded to float32), the remaining slots filled with
  the first neighbour found; a centre without neighbours gets index 0 everywhere.
- :func:`group` (``grouping/grouping.cu``): gathers point features at neighbour indices.
- :func:`three_nn_interpolate` (``interpolate/neighbor_interpolate.cu``): features at the 3 nearest
  centres (ties: lower index), weighted by inverse *squared* distance, squared distances clamped to
  ``[1e-10, 1e10]``; with fewer than 3 centres the missing ones are index 0 at distance 1e10.
- :func:`voxelize` (``modules/voxelization.py``, ``voxelization/vox.cu``): each cloud centred on its
  mean, divided by twice its largest point norm (eps 0), shifted by ½, scaled by ``r`` and clamped to
  ``[0, r − 1]``; a point belongs to the voxel of its rounded (half to even) coordinates, and each
  voxel holds the mean of its points' features (empty voxels 0).
- :func:`trilinear_devoxelize` (``interpolate/trilinear_devox.cu``): voxel centres at integer
  coordinates; a point at ``x`` reads voxels ``floor(x)`` and, when the fractional part is > 0,
  ``floor(x) + 1``, weighted trilinearly.

Tensors are channel-first as in PC²: coordinates ``(B, 3, N)``, features ``(B, C, N)``. Indices
are int64. No gradient flows to coordinates (the CUDA ops give none); gradients flow to features.
Float results equal the kernels' up to float32 rounding (the kernels' own sums are unordered
atomics and FMA-contracted), index results exactly. ``cdm/model/voxels.py`` is not reused: its grid
normalises by the largest absolute coordinate, floors to voxels and renormalises trilinear weights
over present corners, which are different functions.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "Neighbours",
    "VoxelizedCloud",
    "at_least_float32",
    "ball_query",
    "farthest_point_sample",
    "gather_points",
    "group",
    "three_nn",
    "three_nn_interpolate",
    "trilinear_devoxelize",
    "voxelize",
    "voxelize_coords",
]

_FPS_THREADS = 512  # the FPS kernel's block size (``sampling.cu``), which sets its tie-break
# (centre, point) pairs per chunk of a brute-force search: bounds its temporary memory (two float32 buffers
# of this many) and sets how many chunks, each ~27 dispatched ops, a search takes. A GPU holds larger chunks
# and pays per launch: at Co3D's SA1 (B=8, 1,024 centres, 16,384 points) ball query took 32 chunks (878
# ops) at the CPU's 2²² (benchmarks/RESULTS.md, "Ops per pvcnn2 step"), 4 at 2²⁵ (128 MB a buffer).
_CHUNK_ELEMENTS = {"cpu": 1 << 22, "cuda": 1 << 25}


def at_least_float32(features: Tensor) -> Tensor:
    """Features to average per voxel, summed in float32 at least: under fp16 autocast a voxel of many
    points would lose the mean's low bits (and overflow past 65,504)."""
    return features.to(torch.promote_types(features.dtype, torch.float32))


def _chunk(device: torch.device, pairs_per_row: int) -> int:
    """Rows (centres or points) per chunk of a search whose rows each pair with ``pairs_per_row`` others."""
    return max(1, _CHUNK_ELEMENTS.get(device.type, _CHUNK_ELEMENTS["cpu"]) // max(1, pairs_per_row))


def _squared_distances(a: Tensor, b: Tensor) -> Tensor:
    """``(B, 3, P)`` and ``(B, 3, Q)`` → ``(B, P, Q)`` of ``Σ_axis (a − b)²``, summed x, y, z in order as the
    kernels do.

    In place on two buffers: the search is bound by memory traffic (2.5× faster than out-of-place).
    """
    d = torch.sub(a[:, 0, :, None], b[:, 0, None, :])
    d.mul_(d)
    buf = torch.empty_like(d)
    for axis in (1, 2):
        torch.sub(a[:, axis, :, None], b[:, axis, None, :], out=buf)
        buf.mul_(buf)
        d.add_(buf)
    return d


@torch.no_grad()
def farthest_point_sample(coords: Tensor, num_centers: int) -> Tensor:
    """Iterative farthest point sampling with PC²'s start point and tie-break.

    Args:
        coords: ``(B, 3, N)`` point coordinates (any frame, any unit).
        num_centers: ``M``, may exceed ``N`` (extra centres repeat point 0).
    Returns:
        ``(B, M)`` int64 indices into the ``N`` points; ``[:, 0]`` is 0.
    """
    b, _, n = coords.shape
    coords = coords.float()
    k = torch.arange(n, device=coords.device)
    scan = torch.argsort(k % _FPS_THREADS * n + k // _FPS_THREADS)  # kernel's tie order; scan[0] == 0
    pts = coords[:, :, scan]  # (B, 3, N) in scan order
    dist = torch.full((b, n), 1e38, device=coords.device)
    last = torch.zeros(b, 1, dtype=torch.long, device=coords.device)
    chosen = [last]
    # After N picks every distance is 0 and the kernel's argmax returns scan position 0 (point 0):
    # centres beyond N are point 0 without searching.
    for _ in range(1, min(num_centers, n)):
        diff = pts - pts.gather(2, last[:, None, :].expand(b, 3, 1))  # (B, 3, N)
        diff.mul_(diff)
        dx, dy, dz = diff.unbind(1)  # one view op, not three (12 → 10 dispatched ops per centre)
        d = dx + dy  # x, then y, then z: the bits of _squared_distances in fewer kernels
        torch.minimum(dist, d.add_(dz), out=dist)
        last = dist.argmax(dim=1, keepdim=True)  # first maximum in scan order
        chosen.append(last)
    picked = torch.cat(chosen, dim=1)
    return F.pad(scan[picked], (0, num_centers - picked.shape[1]))


def gather_points(features: Tensor, index: Tensor) -> Tensor:
    """``(B, C, N)`` features at ``(B, M)`` indices → ``(B, C, M)``; differentiable in ``features``."""
    b, c, _ = features.shape
    return features.gather(2, index[:, None, :].expand(b, c, index.shape[1]))


@torch.no_grad()
def ball_query(centers: Tensor, points: Tensor, radius: float, num_neighbors: int) -> Tensor:
    """The first ``K`` points (by index) strictly within ``radius`` of each centre, padded as PC².

    Args:
        centers: ``(B, 3, M)`` centre coordinates.
        points: ``(B, 3, N)`` point coordinates, same frame and unit as ``centers`` and ``radius``.
        radius: ball radius; membership is ``d² < float32(radius)²``.
        num_neighbors: ``K`` (may exceed ``N``).
    Returns:
        ``(B, M, K)`` int64 indices: the ``n ≤ K`` neighbours in ascending index order, then the first
        neighbour repeated; all 0 for a centre with no neighbour.
    """
    b, _, m = centers.shape
    n = points.shape[2]
    r = torch.tensor(radius, dtype=torch.float32)
    r2 = r * r
    take = min(num_neighbors, n)
    order = torch.arange(n, device=points.device, dtype=torch.float32)
    out = []
    step = _chunk(points.device, b * n)
    for start in range(0, m, step):
        d2 = _squared_distances(centers[:, :, start : start + step].float(), points.float())  # (B, m', N)
        key = torch.where(d2 < r2, order, float(n))  # member points keep their index, others sort last
        first_k = key.topk(take, dim=2, largest=False, sorted=True).values  # (B, m', take)
        out.append(first_k)
    found = torch.cat(out, dim=1)
    if take < num_neighbors:
        found = torch.cat([found, found.new_full((b, m, num_neighbors - take), float(n))], dim=2)
    first = torch.where(found[:, :, :1] < n, found[:, :, :1], 0.0)
    return torch.where(found < n, found, first).long()


def group(features: Tensor, index: Tensor) -> Tensor:
    """Gather features of neighbours: ``(B, C, N)`` at ``(B, M, K)`` indices → ``(B, C, M, K)``.

    Differentiable in ``features`` (the backward sums over repeated neighbours, as the kernel's atomics).
    """
    b, c, _ = features.shape
    _, m, k = index.shape
    return features.gather(2, index.reshape(b, 1, m * k).expand(b, c, m * k)).view(b, c, m, k)


class Neighbours(NamedTuple):
    """The 3 nearest centres of each point: ``index`` ``(B, 3, N)`` int64, ``weight`` ``(B, 3, N)`` float32."""

    index: Tensor
    weight: Tensor


@torch.no_grad()
def three_nn(points: Tensor, centers: Tensor) -> Neighbours:
    """PC²'s 3-NN search and inverse-squared-distance weights (``neighbor_interpolate.cu``).

    Args:
        points: ``(B, 3, N)`` where features are wanted.
        centers: ``(B, 3, M)`` where features are known, same frame.
    Returns:
        nearest first; weights ``w_i = (1/d_i) / Σ_j 1/d_j`` with ``d`` the clamped squared distances,
        computed as the kernel does (products in float64, the rest in float32).
    """
    b, _, n = points.shape
    m = centers.shape[2]
    take = min(3, m)
    index, dist = [], []
    step = _chunk(points.device, b * m)
    for start in range(0, n, step):
        d = _squared_distances(points[:, :, start : start + step].float(), centers.float())  # (B, n', M)
        nearest, nearest_d = [], []
        for _ in range(take):  # argmin gives the first minimum: ties go to the lower index, as the kernel's strict <
            i = d.argmin(dim=2, keepdim=True)
            nearest.append(i)
            nearest_d.append(d.gather(2, i))
            d.scatter_(2, i, float("inf"))
        index.append(torch.cat(nearest, dim=2))
        dist.append(torch.cat(nearest_d, dim=2))
    index, dist = torch.cat(index, dim=1), torch.cat(dist, dim=1)  # (B, N, take)
    if take < 3:
        index = torch.cat([index, index.new_zeros(b, n, 3 - take)], dim=2)
        dist = torch.cat([dist, dist.new_full((b, n, 3 - take), 1e10)], dim=2)
    dist = dist.clamp(1e-10, 1e10).double()
    d0, d1, d2 = dist.unbind(dim=2)
    d0d1, d0d2, d1d2 = (d0 * d1).float(), (d0 * d2).float(), (d1 * d2).float()
    inv = 1.0 / (d0d1 + d0d2 + d1d2)
    weight = torch.stack([d1d2 * inv, d0d2 * inv, d0d1 * inv], dim=1)
    return Neighbours(index.transpose(1, 2), weight)


def three_nn_interpolate(points: Tensor, centers: Tensor, center_features: Tensor) -> Tensor:
    """Features of the 3 nearest centres, inverse-squared-distance weighted (PC²'s feature propagation).

    Args:
        points: ``(B, 3, N)`` target coordinates.
        centers: ``(B, 3, M)`` source coordinates, same frame.
        center_features: ``(B, C, M)``.
    Returns:
        ``(B, C, N)``; differentiable in ``center_features`` only.
    """
    nn3 = three_nn(points, centers)
    b, c, _ = center_features.shape
    n = points.shape[2]
    picked = center_features.gather(2, nn3.index.reshape(b, 1, 3 * n).expand(b, c, 3 * n)).view(b, c, 3, n)
    w = nn3.weight.to(center_features.dtype)[:, None]
    return picked[:, :, 0] * w[:, :, 0] + picked[:, :, 1] * w[:, :, 1] + picked[:, :, 2] * w[:, :, 2]


class VoxelizedCloud(NamedTuple):
    """Where the points of a batch of clouds fall in an ``r³`` grid, PC²'s ``Voxelization``.

    Attributes:
        coords: ``(B, 3, N)`` float32 grid coordinates in ``[0, r − 1]`` (voxel centres at integers).
        voxel: ``(B, N)`` int64 flat voxel index ``(i·r + j)·r + k`` of the rounded coordinates.
        count: ``(B, 1, r³)`` points per voxel, at least 1 (the divisor of the mean).
        resolution: ``r``.
    """

    coords: Tensor
    voxel: Tensor
    count: Tensor
    resolution: int


@torch.no_grad()
def voxelize_coords(points: Tensor, resolution: int) -> VoxelizedCloud:
    """Normalise each cloud into PC²'s grid frame and find each point's voxel.

    Args:
        points: ``(B, 3, N)`` coordinates (world frame; no gradient is taken).
        resolution: ``r``.
    Returns:
        :class:`VoxelizedCloud`. A cloud whose points all coincide divides 0 by 0, as PC²'s does (eps 0).
    """
    r = resolution
    centred = points.float() - points.float().mean(dim=2, keepdim=True)
    scale = centred.norm(dim=1, keepdim=True).amax(dim=2, keepdim=True) * 2.0
    coords = torch.clamp((centred / scale + 0.5) * r, 0, r - 1)
    ijk = torch.round(coords).long()
    voxel = (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2]
    count = torch.zeros(points.shape[0], r**3, device=points.device)
    count.scatter_add_(1, voxel, torch.ones_like(voxel, dtype=count.dtype))
    return VoxelizedCloud(coords, voxel, count.clamp(min=1.0)[:, None], r)


def voxelize(features: Tensor, cloud: VoxelizedCloud) -> Tensor:
    """Average point features per voxel: ``(B, C, N)`` → ``(B, C, r, r, r)`` float32 (empty voxels 0).

    Axis order: ``[b, c, i, j, k]`` with ``i, j, k`` along coordinate axes 0, 1, 2 (PC²'s layout).
    Summed in float32 at least, whatever the features' dtype: under fp16 autocast a voxel of hundreds
    of points would lose the mean's low bits (and overflow past 65,504).
    """
    b, c, n = features.shape
    r = cloud.resolution
    features = at_least_float32(features)
    total = features.new_zeros(b, c, r**3).scatter_add_(2, cloud.voxel[:, None, :].expand(b, c, n), features)
    return (total / cloud.count.to(features.dtype)).view(b, c, r, r, r)


def trilinear_devoxelize(voxels: Tensor, cloud: VoxelizedCloud) -> Tensor:
    """Trilinear interpolation of ``(B, C, r, r, r)`` voxel features at the points of ``cloud`` → ``(B, C, N)``.

    Differentiable in ``voxels``.
    """
    b, c = voxels.shape[:2]
    r = cloud.resolution
    x = cloud.coords
    lo = torch.floor(x)
    frac = x - lo  # (B, 3, N)
    step = (frac > 0).long() * torch.tensor([r * r, r, 1], device=x.device)[None, :, None]
    base = (lo.long() * torch.tensor([r * r, r, 1], device=x.device)[None, :, None]).sum(dim=1)  # (B, N)
    index, weight = [], []
    for corner in range(8):
        bits = ((corner >> 2) & 1, (corner >> 1) & 1, corner & 1)  # x, y, z high?
        idx, w = base, None
        for axis, high in enumerate(bits):
            wa = frac[:, axis] if high else 1.0 - frac[:, axis]
            w = wa if w is None else w * wa
            if high:
                idx = idx + step[:, axis]
        index.append(idx)
        weight.append(w)
    n = x.shape[2]
    index = torch.stack(index, dim=1)  # (B, 8, N)
    weight = torch.stack(weight, dim=1).to(voxels.dtype)
    picked = voxels.reshape(b, c, r**3).gather(2, index.view(b, 1, 8 * n).expand(b, c, 8 * n)).view(b, c, 8, n)
    return (picked * weight[:, None]).sum(dim=2)
