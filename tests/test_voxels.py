"""Tests of cdm.model.voxels: both back-ends against dense / naive references, gradients, edge cases."""

from __future__ import annotations

import itertools

import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from cdm.model.voxels import (
    DenseGrid,
    SparseGrid,
    VoxelBranch,
    build_grid,
    normalize_coords,
    resolve_voxel_backend,
)


def _cloud(b: int, n: int, seed: int, dtype=torch.float32) -> torch.Tensor:
    return torch.rand(b, n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def _dense_rows(voxels: torch.Tensor) -> torch.Tensor:
    """``(B, C, r, r, r)`` → ``(B·r³, C)`` rows indexed by global voxel key."""
    return voxels.permute(0, 2, 3, 4, 1).reshape(-1, voxels.shape[1])


@pytest.mark.parametrize("resolution", [8, 16, 32])
@pytest.mark.parametrize("channels", [(1, 4), (5, 7), (16, 8)])
def test_sparse_conv_equals_dense_conv3d_at_occupied_sites(resolution, channels):
    torch.manual_seed(resolution + channels[0])
    coords = _cloud(2, 150, seed=resolution)
    features = torch.randn(2, 150, channels[0])
    conv = nn.Conv3d(*channels, 3, padding=1)
    dense, sparse = DenseGrid(coords, resolution), SparseGrid(coords, resolution)
    vd, vs = dense.voxelize(features), sparse.voxelize(features)
    expected = F.conv3d(vd, conv.weight, conv.bias, padding=1)
    got = sparse.conv(vs, conv.weight, conv.bias)
    assert torch.allclose(_dense_rows(vd)[sparse.keys], vs, atol=1e-6)
    assert (_dense_rows(expected)[sparse.keys] - got).abs().max() <= 1e-5


def test_voxelize_is_the_mean_of_each_voxels_points():
    coords = _cloud(2, 40, seed=1)
    features = torch.randn(2, 40, 3)
    r = 4
    sparse = SparseGrid(coords, r)
    dense_rows = _dense_rows(DenseGrid(coords, r).voxelize(features))
    rows = sparse.voxelize(features)
    idx = (coords * r).floor().long().clamp(0, r - 1)
    for b in range(2):
        for i, j, k in {tuple(v.tolist()) for v in idx[b]}:
            members = (idx[b] == torch.tensor([i, j, k])).all(-1)
            key = b * r**3 + (i * r + j) * r + k
            mean = features[b, members].mean(0)
            assert torch.allclose(dense_rows[key], mean, atol=1e-6)
            assert torch.allclose(rows[(sparse.keys == key).nonzero().item()], mean, atol=1e-6)
    assert sparse.keys.numel() == len({(b, *v.tolist()) for b in range(2) for v in idx[b]})


def test_sparse_group_norm_equals_masked_dense_reference():
    torch.manual_seed(0)
    coords = _cloud(3, 60, seed=2, dtype=torch.float64)
    r, c, groups = 8, 12, 4
    sparse = SparseGrid(coords, r)
    rows = torch.randn(sparse.keys.numel(), c, dtype=torch.float64) * 3 + 1
    weight, bias = torch.randn(c, dtype=torch.float64), torch.randn(c, dtype=torch.float64)
    got = sparse.group_norm(rows, groups, weight, bias, 1e-5)
    # Reference: scatter into a dense grid, normalise each (sample, group) over its occupied voxels only.
    grid = torch.zeros(3 * r**3, c, dtype=torch.float64)
    grid[sparse.keys] = rows
    occupied = torch.zeros(3 * r**3, dtype=torch.bool)
    occupied[sparse.keys] = True
    grid, occupied = grid.view(3, r**3, c), occupied.view(3, r**3)
    expected = torch.zeros_like(grid)
    per = c // groups
    for b in range(3):
        for g in range(groups):
            block = grid[b][occupied[b]][:, g * per : (g + 1) * per]
            mean, var = block.mean(), block.var(unbiased=False)
            normed = (grid[b][:, g * per : (g + 1) * per] - mean) / torch.sqrt(var + 1e-5)
            expected[b][:, g * per : (g + 1) * per] = (
                normed * weight[g * per : (g + 1) * per] + bias[g * per : (g + 1) * per]
            )
    assert (expected.view(-1, c)[sparse.keys] - got).abs().max() <= 1e-9


def test_sparse_fused_norm_silu_equals_group_norm_then_silu_with_its_gradients():
    """The fused rows' norm (per-sample sums as one-hot products, hand-written backward) against the
    per-row reference ``group_norm`` then SiLU: the same function, in float64 to 1e-10, gradients
    checked numerically; in float32 the rows' features off-centre (a one-pass variance would fail)."""
    coords = _cloud(3, 60, seed=2, dtype=torch.float64)
    sparse = SparseGrid(coords, 8)
    m, c = sparse.keys.numel(), 12
    g = torch.Generator().manual_seed(0)
    norm = nn.GroupNorm(4, c).double()
    with torch.no_grad():
        norm.weight.copy_(torch.randn(c, generator=g, dtype=torch.float64))
        norm.bias.copy_(torch.randn(c, generator=g, dtype=torch.float64))
    rows = (torch.randn(m, c, generator=g, dtype=torch.float64) * 3 + 5).requires_grad_()
    params = (rows, norm.weight, norm.bias)
    upstream = torch.randn(m, c, generator=g, dtype=torch.float64)
    fused = sparse.norm_silu(rows, norm)
    naive = F.silu(sparse.group_norm(rows, 4, norm.weight, norm.bias, norm.eps))
    torch.testing.assert_close(fused, naive, rtol=1e-10, atol=1e-10)
    for got, want in zip(torch.autograd.grad(fused, params, upstream), torch.autograd.grad(naive, params, upstream)):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
    assert torch.autograd.gradcheck(lambda *p: sparse.norm_silu(p[0], norm), (rows,), eps=1e-6, atol=1e-6)
    low = sparse.norm_silu(rows.detach().float(), norm.float())
    assert low.dtype == torch.float32
    torch.testing.assert_close(low, naive.float(), rtol=1e-5, atol=1e-5)


def test_dense_trilinear_devoxelisation_matches_grid_sample_with_border_padding():
    torch.manual_seed(0)
    coords = _cloud(2, 50, seed=3)
    coords[0, :6] = torch.tensor(
        [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 0.5], [0.01, 0.99, 0.3], [0.5, 0.5, 0.5], [1, 0, 0]]
    )
    voxels = torch.randn(2, 3, 6, 6, 6)
    got = DenseGrid(coords, 6).devoxelize(voxels, "trilinear")
    grid = (coords * 2 - 1).flip(-1)[:, :, None, None, :]  # grid_sample wants (x, y, z) = (axis 2, 1, 0)
    expected = F.grid_sample(voxels, grid, mode="bilinear", padding_mode="border", align_corners=False)
    assert torch.allclose(got, expected[:, :, :, 0, 0].transpose(1, 2), atol=1e-6)


def test_sparse_trilinear_devoxelisation_matches_naive_renormalised_corners():
    coords = _cloud(2, 30, seed=4, dtype=torch.float64)
    r = 4
    sparse = SparseGrid(coords, r)
    rows = torch.randn(sparse.keys.numel(), 2, dtype=torch.float64)
    got = sparse.devoxelize(rows, "trilinear")
    lookup = {k: i for i, k in enumerate(sparse.keys.tolist())}
    for b, n in itertools.product(range(2), range(30)):
        u = coords[b, n] * r - 0.5
        lo = torch.floor(u)
        total, wsum = torch.zeros(2, dtype=torch.float64), 0.0
        for corner in itertools.product((0, 1), repeat=3):
            c = lo + torch.tensor(corner, dtype=torch.float64)
            if ((c < 0) | (c >= r)).any():
                continue
            key = b * r**3 + int((c[0] * r + c[1]) * r + c[2])
            if key not in lookup:
                continue
            w = torch.prod(torch.where(torch.tensor(corner).bool(), u - lo, 1 - (u - lo)))
            total += w * rows[lookup[key]]
            wsum += w
        assert torch.allclose(got[b, n], total / wsum, atol=1e-12)


@pytest.mark.parametrize("backend", ["dense", "sparse"])
@pytest.mark.parametrize("mode", ["trilinear", "nearest"])
def test_gradcheck_voxelise_conv_norm_devoxelise(backend, mode):
    torch.manual_seed(0)
    coords = _cloud(2, 7, seed=5, dtype=torch.float64)
    grid = build_grid(backend, coords, 3)
    features = torch.randn(2, 7, 2, dtype=torch.float64, requires_grad=True)
    weight = (0.3 * torch.randn(4, 2, 3, 3, 3, dtype=torch.float64)).requires_grad_()
    bias = torch.randn(4, dtype=torch.float64, requires_grad=True)
    gamma = torch.randn(4, dtype=torch.float64, requires_grad=True)

    def branch(feat, w, b, g):
        v = grid.conv(grid.voxelize(feat), w, b)
        return grid.devoxelize(F.silu(grid.group_norm(v, 2, g, b, 1e-5)), mode)

    assert torch.autograd.gradcheck(branch, (features, weight, bias, gamma), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("backend", ["dense", "sparse"])
def test_all_points_in_one_voxel(backend):
    torch.manual_seed(0)
    coords = 0.55 + 0.01 * _cloud(2, 20, seed=6)  # one voxel of r = 4 per sample
    grid = build_grid(backend, coords, 4)
    features = torch.randn(2, 20, 3)
    branch = VoxelBranch(3, 8, 4, devoxelize="nearest")
    out = branch(features, grid)
    assert out.shape == (2, 20, 8) and torch.isfinite(out).all()
    assert torch.allclose(out, out[:, :1].expand_as(out), atol=1e-6)
    if backend == "sparse":
        # Trilinear over the present corners renormalises onto the only occupied voxel.
        branch.devoxelize = "trilinear"
        assert torch.allclose(out, branch(features, grid), atol=1e-6)
        assert grid.keys.numel() == 2 and grid.kernel_map.out_rows.numel() == 0  # no neighbours off the centre
        voxel_mean = features.mean(1)
        assert torch.allclose(grid.voxelize(features), voxel_mean, atol=1e-6)


@pytest.mark.parametrize("backend", ["dense", "sparse"])
def test_single_point_cloud(backend):
    points = torch.tensor([[[0.3, -2.0, 5.0]], [[0.0, 0.0, 0.0]]])
    coords = normalize_coords(points)
    assert torch.equal(coords, torch.full_like(coords, 0.5))
    torch.manual_seed(0)
    out = VoxelBranch(2, 8, 6)(torch.randn(2, 1, 2), build_grid(backend, coords, 6))
    assert out.shape == (2, 1, 8) and torch.isfinite(out).all()


def test_points_on_the_grid_boundary():
    torch.manual_seed(0)
    corners = torch.tensor(list(itertools.product((0.0, 1.0), repeat=3)))  # the 8 cube corners
    coords = torch.cat([corners, torch.rand(12, 3)])[None].repeat(2, 1, 1)
    r = 5
    dense, sparse = DenseGrid(coords, r), SparseGrid(coords, r)
    own = dense.point_keys[:8] % r**3
    assert own.tolist() == [(i * r + j) * r + k for i, j, k in itertools.product((0, r - 1), repeat=3)]
    features = torch.randn(2, 20, 3)
    conv = nn.Conv3d(3, 4, 3, padding=1)
    expected = _dense_rows(dense.conv(dense.voxelize(features), conv.weight, conv.bias))[sparse.keys]
    assert torch.allclose(sparse.conv(sparse.voxelize(features), conv.weight, conv.bias), expected, atol=1e-5)
    # A constant field devoxelises to the constant: out-of-grid corners are dropped and renormalised.
    for grid, voxels in (
        (dense, torch.full((2, 3, r, r, r), 2.5)),
        (sparse, torch.full((sparse.keys.numel(), 3), 2.5)),
    ):
        assert torch.allclose(grid.devoxelize(voxels, "trilinear"), torch.full((2, 20, 3), 2.5))


def test_normalize_coords_fills_the_unit_cube_and_ignores_translation_and_scale():
    points = 3.0 * torch.randn(2, 100, 3, generator=torch.Generator().manual_seed(7))
    coords = normalize_coords(points)
    assert coords.min() >= 0 and coords.max() <= 1
    # The largest centred |coordinate| reaches the cube's face.
    assert torch.allclose((coords - 0.5).abs().amax(dim=(1, 2)), torch.full((2,), 0.5), atol=1e-5)
    assert torch.allclose(normalize_coords(0.2 * points + 4.0), coords, atol=1e-5)


def test_both_backends_have_identical_parameters():
    dense, sparse = VoxelBranch(3, 8, 4), VoxelBranch(3, 8, 4)
    sparse.load_state_dict(dense.state_dict())
    assert {k: v.shape for k, v in dense.state_dict().items()} == {k: v.shape for k, v in sparse.state_dict().items()}
    coords, features = _cloud(2, 30, seed=8), torch.randn(2, 30, 3)
    out_d = dense(features, DenseGrid(coords, 4))
    out_s = sparse(features, SparseGrid(coords, 4))
    assert out_d.shape == out_s.shape and not torch.allclose(out_d, out_s)  # different functions


def test_resolve_voxel_backend():
    assert resolve_voxel_backend("auto", "cpu") == "sparse"
    assert resolve_voxel_backend("auto", "cuda") == "dense"
    assert resolve_voxel_backend("dense", "cpu") == "dense"
    with pytest.raises(ValueError, match="voxel_backend"):
        resolve_voxel_backend("fast", "cpu")
    with pytest.raises(ValueError, match="resolve 'auto' first"):
        build_grid("auto", _cloud(1, 4, seed=0), 4)
