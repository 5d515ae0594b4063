"""Tests of cdm.model.sparse_conv: the kernel map's pairs; the convolution against the per-offset loop it replaced."""

from __future__ import annotations

import pytest
import torch

from cdm.model.sparse_conv import submanifold_conv
from cdm.model.voxels import SparseGrid
from tests.naive_sparse_conv import naive_conv, offset_pairs


def _cloud(b: int, n: int, seed: int, dtype=torch.float32) -> torch.Tensor:
    return torch.rand(b, n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def _conv_and_grads(conv, grid, x, weight, bias, grad_out):
    x, weight, bias = (t.detach().clone().requires_grad_() for t in (x, weight, bias))
    out = conv(grid, x, weight, bias)
    out.backward(grad_out)
    return out.detach(), x.grad, weight.grad, bias.grad


@pytest.mark.parametrize(
    ("resolution", "points", "channels"), [(16, 512, (32, 32)), (8, 512, (64, 128)), (4, 3, (5, 7))]
)
def test_sparse_conv_and_its_gradients_equal_the_naive_per_offset_loop(resolution, points, channels):
    """The lean convolution against the per-offset loop it replaced: the same sums in another order, so
    equal to float64 rounding (1e-12 relative to the largest value); the (4, 3) grid has offsets without pairs."""
    torch.manual_seed(resolution)
    grid = SparseGrid(_cloud(4, points, seed=resolution, dtype=torch.float64), resolution)
    m = grid.keys.numel()
    x = torch.randn(m, channels[0], dtype=torch.float64)
    weight = torch.randn(channels[1], channels[0], 3, 3, 3, dtype=torch.float64)
    bias = torch.randn(channels[1], dtype=torch.float64)
    grad_out = torch.randn(m, channels[1], dtype=torch.float64)
    lean = _conv_and_grads(SparseGrid.conv, grid, x, weight, bias, grad_out)
    naive = _conv_and_grads(naive_conv, grid, x, weight, bias, grad_out)
    for got, expected in zip(lean, naive):
        assert (got - expected).abs().max() <= 1e-12 * expected.abs().max()
    pairs = offset_pairs(grid.kernel_map, m)
    for k in range(27):  # mirror offsets pair the same voxels the other way round
        assert torch.equal(pairs[k][0], pairs[26 - k][1]) and torch.equal(pairs[k][1], pairs[26 - k][0])
    assert resolution != 4 or any(out_rows.numel() == 0 for out_rows, _ in pairs)


def test_sparse_conv_needs_no_input_gradient():
    grid = SparseGrid(_cloud(2, 40, seed=3), 4)
    x = torch.randn(grid.keys.numel(), 3)
    weight = torch.randn(5, 3, 3, 3, 3, requires_grad=True)
    grid.conv(x, weight, None).sum().backward()
    expected = torch.randn(5, 3, 3, 3, 3, requires_grad=True)
    with torch.no_grad():
        expected.copy_(weight)
    naive_conv(grid, x, expected, None).sum().backward()
    assert torch.allclose(weight.grad, expected.grad, rtol=1e-5, atol=1e-5)


def test_the_kernel_map_pairs_each_voxel_with_its_occupied_neighbours():
    grid = SparseGrid(_cloud(2, 60, seed=4), 5)
    key_of = grid.keys.tolist()
    occupied = set(key_of)
    for k, (out_rows, in_rows) in enumerate(offset_pairs(grid.kernel_map, len(key_of))):
        d = (k // 9 - 1, (k // 3) % 3 - 1, k % 3 - 1)
        expected = []
        for row, key in enumerate(key_of):
            b, local = divmod(key, 125)
            ijk = (local // 25 + d[0], (local // 5) % 5 + d[1], local % 5 + d[2])
            nb = b * 125 + (ijk[0] * 5 + ijk[1]) * 5 + ijk[2]
            if all(0 <= c < 5 for c in ijk) and nb in occupied:
                expected.append((row, key_of.index(nb)))
        assert list(zip(out_rows.tolist(), in_rows.tolist())) == expected


def test_submanifold_conv_without_a_grid_equals_the_grids_conv():
    grid = SparseGrid(_cloud(2, 40, seed=8), 4)
    x = torch.randn(grid.keys.numel(), 3)
    weight = torch.randn(5, 3, 3, 3, 3)
    assert torch.equal(submanifold_conv(x, weight, grid.kernel_map), grid.conv(x, weight, None))
