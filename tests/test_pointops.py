"""PC²'s geometric operations (cdm.model.pointops) against naive loops written from its CUDA kernels.

Each reference below transcribes one kernel of lukemelas/projection-conditioned-point-cloud-diffusion,
``experiments/model/pvcnn/modules/functional/src/`` (commit 64fd55a0d00b52735cf02e11c5112374c7104ece),
point by point in Python: index outputs must be equal, float outputs equal to float32 rounding.
"""

from __future__ import annotations

import math

import pytest
import torch

from cdm.model import pointops


def _sq(a: list[float], b: list[float]) -> float:
    """The kernels' squared distance in float32: x, then y, then z."""
    f = torch.tensor
    dx, dy, dz = (f(a[i], dtype=torch.float32) - f(b[i], dtype=torch.float32) for i in range(3))
    return float(dx * dx + dy * dy + dz * dz)


def _naive_fps(xyz: torch.Tensor, m: int, threads: int = 512) -> list[int]:
    """``sampling.cu``: start at 0; per step every thread ``t`` scans ``k ≡ t (mod threads)`` keeping its
    first strict maximum; the tree reduction keeps the lower thread on ties."""
    n = xyz.shape[1]
    pts = xyz.T.tolist()
    dist = [1e38] * n
    out, old = [0], 0
    for _ in range(1, m):
        best_per_thread = []
        for t in range(threads):
            best, besti = -1.0, 0
            for k in range(t, n, threads):
                dist[k] = min(_sq(pts[k], pts[old]), dist[k])
                if dist[k] > best:
                    best, besti = dist[k], k
            best_per_thread.append((best, besti))
        top = max(b for b, _ in best_per_thread)
        old = next(i for b, i in best_per_thread if b == top)
        out.append(old)
    return out


def _naive_ball_query(centers: torch.Tensor, points: torch.Tensor, radius: float, u: int) -> list[list[int]]:
    """``ball_query.cu``: scan points in order; the first hit fills every slot, later hits overwrite in turn."""
    r2 = float(torch.tensor(radius, dtype=torch.float32) ** 2)
    out = []
    for c in centers.T.tolist():
        row, cnt = [0] * u, 0
        for k, p in enumerate(points.T.tolist()):
            if cnt >= u:
                break
            if _sq(c, p) < r2:
                if cnt == 0:
                    row = [k] * u
                row[cnt] = k
                cnt += 1
        out.append(row)
    return out


def _naive_three_nn(points: torch.Tensor, centers: torch.Tensor) -> tuple[list[list[int]], list[list[float]]]:
    """``neighbor_interpolate.cu``: insertion with strict <, clamp to [1e-10, 1e10], inverse-distance weights."""
    idx, wts = [], []
    for p in points.T.tolist():
        best, besti = [1e40, 1e40, 1e40], [0, 0, 0]
        for k, c in enumerate(centers.T.tolist()):
            d = _sq(p, c)
            if d < best[2]:
                best[2], besti[2] = d, k
                if d < best[1]:
                    best[2], besti[2], best[1], besti[1] = best[1], besti[1], d, k
                    if d < best[0]:
                        best[1], besti[1], best[0], besti[0] = best[0], besti[0], d, k
        b = [max(min(1e10, v), float(torch.tensor(1e-10, dtype=torch.float32))) for v in best]
        inv = [b[1] * b[2], b[0] * b[2], b[0] * b[1]]
        wts.append([v / sum(inv) for v in inv])
        idx.append(besti)
    return idx, wts


def test_fps_matches_the_kernel_on_random_clouds_and_starts_at_zero():
    g = torch.Generator().manual_seed(0)
    xyz = torch.randn(2, 3, 40, generator=g)
    got = pointops.farthest_point_sample(xyz, 12)
    for b in range(2):
        assert got[b].tolist() == _naive_fps(xyz[b], 12)
    assert got[:, 0].tolist() == [0, 0]


def test_fps_ties_follow_the_kernels_thread_order():
    # 8 corners of a cube seen from the centre point 0: all tie at every step until the set is full.
    corners = torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    xyz = torch.cat([torch.zeros(1, 3), corners]).T[None]  # (1, 3, 9)
    assert pointops.farthest_point_sample(xyz, 9)[0].tolist() == _naive_fps(xyz[0], 9)
    # With fewer threads than points the scan order (k mod threads, k div threads) decides the tie:
    # with 4 "threads", point 5 (thread 1) beats point 2 (thread 2) although 2 < 5.
    line = torch.zeros(1, 3, 8)
    line[0, 0, 2] = line[0, 0, 5] = 1.0
    assert _naive_fps(line[0], 2, threads=4) == [0, 5]
    assert _naive_fps(line[0], 2, threads=512) == [0, 2]
    assert pointops.farthest_point_sample(line, 2)[0].tolist() == [0, 2]


def test_fps_thread_order_beyond_512_points():
    # Two tied farthest points at k = 1 (thread 1) and k = 512 (thread 0): thread 0 wins.
    xyz = torch.zeros(1, 3, 600)
    xyz[0, 0, 1] = xyz[0, 0, 512] = 1.0
    assert pointops.farthest_point_sample(xyz, 2)[0].tolist() == [0, 512]


def test_fps_more_centres_than_points_repeats_point_zero():
    xyz = torch.tensor([[[0.0, 1.0, 3.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])
    got = pointops.farthest_point_sample(xyz, 6)[0].tolist()
    assert got == _naive_fps(xyz[0], 6) == [0, 2, 1, 0, 0, 0]


def test_ball_query_matches_the_kernel_with_padding_and_empty_balls():
    g = torch.Generator().manual_seed(1)
    points = torch.rand(2, 3, 50, generator=g)
    centers = torch.cat([points[:, :, :6], torch.full((2, 3, 1), 9.0)], dim=2)  # last centre has no neighbour
    for radius, k in ((0.3, 8), (0.15, 4), (2.0, 60)):  # 60 > N: slots beyond N pad too
        got = pointops.ball_query(centers, points, radius, k)
        for b in range(2):
            assert got[b].tolist() == _naive_ball_query(centers[b], points[b], radius, k)
    assert got[:, -1].eq(0).all()


def test_ball_query_boundary_is_strict():
    points = torch.tensor([[[0.0, 0.5, 0.25, 0.5000001], [0.0] * 4, [0.0] * 4]])
    got = pointops.ball_query(points[:, :, :1], points, 0.5, 4)[0, 0].tolist()
    assert got == _naive_ball_query(points[0, :, :1], points[0], 0.5, 4)[0] == [0, 2, 0, 0]


def test_group_gathers_and_backpropagates_sums():
    feats = torch.arange(12.0).view(1, 2, 6).requires_grad_(True)
    idx = torch.tensor([[[0, 5, 5], [3, 3, 3]]])
    out = pointops.group(feats, idx)
    assert out.tolist() == [[[[0.0, 5.0, 5.0], [3.0, 3.0, 3.0]], [[6.0, 11.0, 11.0], [9.0, 9.0, 9.0]]]]
    out.sum().backward()
    assert feats.grad.tolist() == [[[1.0, 0.0, 0.0, 3.0, 0.0, 2.0]] * 2]


def test_three_nn_matches_the_kernel_including_ties_and_few_centres():
    g = torch.Generator().manual_seed(2)
    points = torch.randn(1, 3, 30, generator=g)
    # Centres on a grid: many exact distance ties for points placed on it.
    grid = torch.tensor([[x, y, 0.0] for x in (0.0, 1.0, 2.0) for y in (0.0, 1.0)]).T[None]
    on_grid = torch.tensor([[0.5, 0.5, 0.0], [1.0, 0.5, 0.0], [1.5, 1.0, 0.0]]).T[None]
    cases = [
        (points, torch.randn(1, 3, 9, generator=g)),
        (on_grid, grid),
        (points, points[:, :, :2]),
        (points, points[:, :, :1]),
    ]
    for pts, ctr in cases:
        nn3 = pointops.three_nn(pts, ctr)
        idx, wts = _naive_three_nn(pts[0], ctr[0])
        assert nn3.index[0].T.tolist() == idx
        torch.testing.assert_close(nn3.weight[0].T, torch.tensor(wts), rtol=1e-6, atol=1e-7)


def test_three_nn_interpolate_weights_features():
    points = torch.tensor([[[0.0], [0.0], [0.0]]])
    centers = torch.tensor([[[1.0, 0.0, 2.0, 5.0], [0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]])  # d² = 1, 4, 4, 25
    feats = torch.tensor([[[10.0, 20.0, 40.0, 1000.0]]], requires_grad=True)
    out = pointops.three_nn_interpolate(points, centers, feats)
    w = torch.tensor([1.0, 0.25, 0.25]) / 1.5
    torch.testing.assert_close(out[0, 0, 0], w[0] * 10 + w[1] * 20 + w[2] * 40)
    out.sum().backward()
    torch.testing.assert_close(feats.grad[0, 0], torch.cat([w, torch.zeros(1)]))


def _naive_voxel_coords(xyz: torch.Tensor, r: int) -> torch.Tensor:
    """``modules/voxelization.py``: centre, divide by 2 × the largest norm, + 0.5, × r, clamp."""
    pts = xyz.T.double()
    centred = pts - pts.mean(0)
    scale = max(math.sqrt(float((p * p).sum())) for p in centred) * 2.0
    return ((centred / scale + 0.5) * r).clamp(0, r - 1).T


def test_voxelize_averages_points_per_rounded_voxel():
    g = torch.Generator().manual_seed(3)
    xyz = torch.randn(2, 3, 60, generator=g)
    feats = torch.randn(2, 5, 60, generator=g, dtype=torch.float64)
    r = 4
    cloud = pointops.voxelize_coords(xyz, r)
    vox = pointops.voxelize(feats, cloud)
    for b in range(2):
        ref_coords = _naive_voxel_coords(xyz[b], r)
        torch.testing.assert_close(cloud.coords[b].double(), ref_coords, rtol=1e-6, atol=1e-5)
        ijk = torch.round(cloud.coords[b]).long()
        sums, counts = {}, {}
        for p in range(60):
            key = tuple(ijk[:, p].tolist())
            sums[key] = sums.get(key, 0) + feats[b, :, p]
            counts[key] = counts.get(key, 0) + 1
        ref = torch.zeros(5, r, r, r, dtype=torch.float64)
        for key, s in sums.items():
            ref[(slice(None),) + key] = s / counts[key]
        torch.testing.assert_close(vox[b], ref)
    assert cloud.coords.min() >= 0 and cloud.coords.max() <= r - 1


def test_voxelize_rounds_half_to_even_and_clamps():
    # Normalised x of the three points: 0, 0.5, 1 → × r = 5: 0, 2.5, 5 → clamp 4; y = z = 0.5 → 2.5.
    # torch.round (as PC²'s Voxelization) rounds 2.5 to 2, not 3.
    xyz = torch.tensor([[[-1.0, 0.0, 1.0], [0.0] * 3, [0.0] * 3]])
    cloud = pointops.voxelize_coords(xyz, 5)
    assert cloud.coords[0, 0].tolist() == [0.0, 2.5, 4.0]
    assert cloud.voxel[0].tolist() == [0 * 25 + 2 * 5 + 2, 2 * 25 + 2 * 5 + 2, 4 * 25 + 2 * 5 + 2]


def _naive_devoxelize(vox: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """``trilinear_devox.cu``: floor corner plus, per axis with a positive fraction, the next voxel."""
    c = vox.shape[0]
    out = torch.zeros(c, coords.shape[1], dtype=vox.dtype)
    for p, (x, y, z) in enumerate(coords.T.tolist()):
        lo = [math.floor(v) for v in (x, y, z)]
        fr = [v - f for v, f in zip((x, y, z), lo)]
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    w = (fr[0] if dx else 1 - fr[0]) * (fr[1] if dy else 1 - fr[1]) * (fr[2] if dz else 1 - fr[2])
                    i, j, k = lo[0] + dx * (fr[0] > 0), lo[1] + dy * (fr[1] > 0), lo[2] + dz * (fr[2] > 0)
                    out[:, p] += w * vox[:, i, j, k]
    return out


def test_trilinear_devoxelize_matches_the_kernel_at_grid_edges():
    g = torch.Generator().manual_seed(4)
    xyz = torch.randn(1, 3, 25, generator=g)
    r = 5
    cloud = pointops.voxelize_coords(xyz, r)
    # Add points exactly on voxel centres and on the last plane r - 1, where the high corner is not read.
    extra = torch.tensor([[0.0, 4.0, 2.0], [0.0, 4.0, 3.5], [4.0, 4.0, 0.25]])
    coords = torch.cat([cloud.coords, extra[None]], dim=2)
    cloud = cloud._replace(coords=coords)
    vox = torch.randn(1, 3, r, r, r, generator=g, dtype=torch.float64, requires_grad=True)
    out = pointops.trilinear_devoxelize(vox, cloud)
    torch.testing.assert_close(out[0], _naive_devoxelize(vox[0].detach(), coords[0]))
    assert torch.autograd.gradcheck(lambda v: pointops.trilinear_devoxelize(v, cloud), (vox,))


@pytest.mark.parametrize("n", [5, 700])
def test_voxelize_gradient_is_the_mean_backward(n: int):
    g = torch.Generator().manual_seed(5)
    xyz = torch.randn(1, 3, n, generator=g)
    cloud = pointops.voxelize_coords(xyz, 3)
    feats = torch.randn(1, 2, n, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f: pointops.voxelize(f, cloud), (feats,))
