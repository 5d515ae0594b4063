"""Tests for cdm.render: hand-computed projections, a naive rasterizer reference, splat gradchecks."""

import math

import pytest
import torch
import torch.nn.functional as F

from cdm.cameras import Cameras, look_at_cameras, orbit_cameras, pixel_centers_ndc, project_points
from cdm.render import (
    SPLAT_DEPTH_EPS,
    _bilinear_deposit,
    _footprint,
    _ShiftedTaps,
    _window_min,
    rasterize_points,
    splat_points,
)


def _front_camera(dist: float = 3.0, batch: int = 1) -> Cameras:
    """Camera on world +Z at ``dist`` looking at the origin, focal 2, batch ``(batch,)``."""
    return look_at_cameras(torch.zeros(batch), torch.zeros(batch), torch.full((batch,), dist))


def _unproject(ndc_xy: torch.Tensor, depth: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """``(B, N, 2)`` NDC and ``(B, N)`` view depth → ``(B, N, 3)`` world points (test helper)."""
    f, p = cameras.focal[:, None, None], cameras.principal[:, None, :]
    view = torch.cat([(ndc_xy - p) * depth[..., None] / f, depth[..., None]], dim=-1)
    return (view - cameras.T[:, None, :]) @ cameras.R.transpose(1, 2)


def _naive_rasterize(points, cameras, image_size, radius):
    """Loop reference: per pixel, the covering point of least depth, ties to the smaller index.

    A loop over pixels, each testing every point (in float64, as Python's floats would)."""
    b, _, _ = points.shape
    s = image_size
    proj = project_points(points, cameras).to(torch.float64)
    x, y, z = proj.unbind(-1)  # (B, N) each
    centres = pixel_centers_ndc(s).to(points.dtype).to(torch.float64)
    own_col, own_row = torch.floor((1 - x) * s / 2), torch.floor((1 - y) * s / 2)
    idx = torch.full((b, s, s), -1, dtype=torch.long)
    zbuf = torch.zeros(b, s, s, dtype=points.dtype)
    for bi in range(b):
        for i in range(s):
            for j in range(s):
                cx, cy = centres[i, j].tolist()
                own = (own_col[bi] == j) & (own_row[bi] == i)
                covers = (z[bi] > 1e-6) & (((cx - x[bi]) ** 2 + (cy - y[bi]) ** 2 <= radius**2) | own)
                if covers.any():
                    nearest = z[bi][covers].min()
                    k = int((covers & (z[bi] == nearest)).nonzero()[0])
                    zbuf[bi, i, j], idx[bi, i, j] = z[bi, k].item(), k
    return idx, zbuf


def test_known_points_land_on_hand_computed_pixels():
    cam = _front_camera(3.0)
    # From test_cameras: (0.45, 0.75, 0) → NDC (−0.3, 0.5) → (row 2, col 6) at S = 10, depth 3;
    # (−0.45, −0.75, 0) → (row 7, col 3).
    points = torch.tensor([[[0.45, 0.75, 0.0], [-0.45, -0.75, 0.0]]])
    frags = rasterize_points(points, cam, 10, radius=0.0)
    assert frags.pixel.tolist() == [[2 * 10 + 6, 7 * 10 + 3]]
    assert frags.visible.tolist() == [[True, True]]
    expected_idx = torch.full((1, 10, 10), -1)
    expected_idx[0, 2, 6], expected_idx[0, 7, 3] = 0, 1
    torch.testing.assert_close(frags.idx, expected_idx)
    assert frags.zbuf[0, 2, 6] == pytest.approx(3.0) and frags.zbuf[0, 7, 3] == pytest.approx(3.0)
    assert frags.zbuf.abs().sum() == pytest.approx(6.0)


def test_nearer_point_wins_regardless_of_index_and_ties_go_to_the_smaller_index():
    cam = _front_camera(3.0)
    far = [0.45, 0.75, 0.0]  # depth 3, NDC (−0.3, 0.5)
    near = [0.3, 0.5, 1.0]  # depth 2, same ray
    for order, winner in (([far, near], 1), ([near, far], 0)):
        frags = rasterize_points(torch.tensor([order]), cam, 10, radius=0.0)
        assert frags.idx[0, 2, 6] == winner
        assert frags.zbuf[0, 2, 6] == pytest.approx(2.0)
        assert frags.visible[0].tolist() == [winner == 0, winner == 1]
        assert frags.pixel[0].tolist() == [26, 26]
    tied = rasterize_points(torch.tensor([[far, near, near]]), cam, 10, radius=0.0)
    assert tied.idx[0, 2, 6] == 1 and tied.visible[0].tolist() == [False, True, False]


def test_points_behind_the_camera_or_off_image_are_not_drawn():
    cam = _front_camera(3.0)
    points = torch.tensor([[[0.0, 0.0, 4.0], [5.0, 0.0, 0.0], [0.1, 0.1, 0.0]]])  # behind, off-image, drawn
    frags = rasterize_points(points, cam, 16, radius=0.05)
    assert frags.pixel[0, :2].tolist() == [-1, -1]
    assert frags.visible[0].tolist() == [False, False, True]
    assert set(frags.idx.unique().tolist()) == {-1, 2}


@pytest.mark.parametrize("radius", [0.0, 0.1, 0.3])
def test_rasterizer_matches_naive_loop_reference(radius):
    gen = torch.Generator().manual_seed(3)
    b, n, s = 2, 12, 10
    cams = look_at_cameras(torch.tensor([15.0, -30.0]), torch.tensor([40.0, 200.0]), torch.tensor([2.2, 2.6]))
    points = (torch.rand(b, n, 3, generator=gen, dtype=torch.float64) * 2.0 - 1.0) * 1.1  # some off-image
    points[0, 0] = torch.tensor([-2.0, 0.5, 3.0], dtype=torch.float64) * 2.0  # behind camera 0
    cams = Cameras(cams.R.double(), cams.T.double(), cams.focal.double(), cams.principal.double())
    frags = rasterize_points(points, cams, s, radius)
    idx, zbuf = _naive_rasterize(points, cams, s, radius)
    torch.testing.assert_close(frags.idx, idx)
    torch.testing.assert_close(frags.zbuf, zbuf)
    assert (frags.idx >= 0).sum() == (idx >= 0).sum()  # coverage count
    own_only = rasterize_points(points, cams, s, 0.0).idx >= 0
    assert ((frags.idx >= 0) | ~own_only).all()  # a disc always covers its own pixel
    if radius >= 2.0 / s:  # at least a pixel: discs reach beyond their own pixels
        assert (frags.idx >= 0).sum() > own_only.sum()
    own = frags.pixel >= 0
    seen = idx.view(b, -1).gather(1, frags.pixel.clamp(min=0))
    assert frags.visible.tolist() == (own & (seen == torch.arange(n))).tolist()


def test_rasterizer_is_batched_per_camera():
    points = torch.tensor([[0.45, 0.75, 0.0]]).expand(2, 1, 3)
    cams = look_at_cameras(torch.zeros(2), torch.tensor([0.0, 180.0]), torch.tensor([3.0, 3.0]))
    frags = rasterize_points(points, cams, 10, radius=0.0)
    # Seen from behind (azimuth 180°) world +X is on the image's left: NDC x = +0.3 → col 3.
    assert frags.pixel.tolist() == [[26], [23]]


def test_rasterizer_rejects_bad_shapes():
    with pytest.raises(ValueError, match="batch shape"):
        rasterize_points(torch.zeros(2, 4, 3), _front_camera(), 8, 0.01)
    with pytest.raises(ValueError, match=r"\(B, N, 3\)"):
        rasterize_points(torch.zeros(4, 3), _front_camera(), 8, 0.01)


def _double(cams: Cameras) -> Cameras:
    return Cameras(cams.R.double(), cams.T.double(), cams.focal.double(), cams.principal.double())


@pytest.mark.parametrize("size", [0.4, 0.2, 0.05])  # radius 1.6, 0.8, 0.2 px: banded products, shifted adds, sub-pixel
@pytest.mark.parametrize("kind", ["depth", "planar"])
def test_splat_gradcheck_float64(kind, size):
    gen = torch.Generator().manual_seed(0)
    cams = _double(look_at_cameras(torch.tensor([20.0]), torch.tensor([35.0]), torch.tensor([2.5])))
    points = (torch.rand(1, 3, 3, generator=gen, dtype=torch.float64) - 0.5).requires_grad_()

    def render(p):
        return splat_points(p, cams, 8, size, kind)

    assert torch.autograd.gradcheck(render, (points,), eps=1e-6, atol=1e-5)


def test_splat_depth_equals_hard_zbuf_at_isolated_points():
    """An isolated point's soft depth is z·Σw/(Σw + eps) exactly; planar gives Σw = −log(1 − image)."""
    gen = torch.Generator().manual_seed(1)
    cams = _double(look_at_cameras(torch.tensor([10.0, 30.0]), torch.tensor([0.0, 120.0]), torch.tensor([3.0, 2.5])))
    s, size = 32, 0.06  # σ ≈ 1 px, cut at 2 px; points ≥ 6 px apart
    grid = torch.tensor([(r, c) for r in (4, 12, 20, 28) for c in (5, 13, 21)], dtype=torch.float64)
    pix = grid + torch.rand(2, 12, 2, generator=gen, dtype=torch.float64) - 0.5
    ndc = 1.0 - (2.0 * pix.flip(-1) + 1.0) / s  # (col, row) → (x, y)
    depth = 2.0 + torch.rand(2, 12, generator=gen, dtype=torch.float64)
    points = _unproject(ndc, depth, cams)
    frags = rasterize_points(points, cams, s, radius=0.0)
    assert frags.visible.all()
    soft = splat_points(points, cams, s, size, "depth").view(2, -1).gather(1, frags.pixel)
    wsum = -torch.log1p(-splat_points(points, cams, s, size, "planar")).view(2, -1).gather(1, frags.pixel)
    hard = frags.zbuf.view(2, -1).gather(1, frags.pixel)
    torch.testing.assert_close(hard, depth)
    torch.testing.assert_close(soft * (wsum + SPLAT_DEPTH_EPS) / wsum, hard)
    # A point exactly on a pixel centre has there Σw = its footprint's integral over that pixel.
    centred = _unproject(ndc.new_tensor([[[1.0 - 25.0 / s, 1.0 - 9.0 / s]]]), depth.new_tensor([[2.5]]), cams[:1])
    img = splat_points(centred, cams[:1], s, size, "depth")
    w = _naive_footprint(centred, cams[:1], s, size)[0, 4, 12].item()
    assert img[0, 4, 12].item() == pytest.approx(2.5 * w / (w + SPLAT_DEPTH_EPS), rel=1e-4)


def _naive_footprint(points, cameras, image_size, radius, sub=48):
    """PyTorch3D's point footprint, loop reference: per pixel and point, ``max(0, 1 − d²/r²)`` (``d`` the
    NDC distance from the projection, ``r`` the radius) averaged over ``sub²`` samples of the pixel,
    summed over in-front points → ``(B, S, S)``."""
    s = image_size
    proj = project_points(points, cameras)
    offsets = (torch.arange(sub, dtype=points.dtype) + 0.5) / sub - 0.5  # within a pixel, in pixels
    out = torch.zeros(points.shape[0], s, s, dtype=points.dtype)
    for b in range(points.shape[0]):
        for x, y, z in proj[b].tolist():
            if z <= 0:
                continue
            for row in range(s):
                for col in range(s):
                    # Pixel [row, col] spans NDC x ∈ 1 − (2·col + 1 ± 1)/S (+X left), likewise y.
                    cx, cy = 1.0 - (2.0 * col + 1.0) / s, 1.0 - (2.0 * row + 1.0) / s
                    if abs(cx - x) > radius + 2.0 / s or abs(cy - y) > radius + 2.0 / s:
                        continue
                    sx = cx - 2.0 * offsets / s - x
                    sy = cy - 2.0 * offsets / s - y
                    d2 = sx[None, :] ** 2 + sy[:, None] ** 2
                    out[b, row, col] += (1.0 - d2 / radius**2).clamp(min=0.0).mean()
    return out


def test_splat_matches_a_naive_pytorch3d_footprint_reference():
    """Projections on pixel centres: equal to the naive reference; anywhere: the same total weight
    (πr²/2 pixels per point) and close pixel by pixel (measured: within 12–18 % of the peak for radii
    of 0.8–2 px, 34 % for 0.24 px, where the bilinear deposit spreads the point over a pixel's width)."""
    gen = torch.Generator().manual_seed(3)
    cam = _double(_front_camera(3.0))
    s = 16
    for size in (0.1, 0.25, 0.03):  # radius 0.8, 2 and 0.24 px
        cols = torch.tensor([3.0, 8.0, 12.0], dtype=torch.float64)
        centred = torch.stack([1.0 - (2.0 * cols + 1.0) / s, 1.0 - (2.0 * cols.flip(0) + 1.0) / s], dim=-1)[None]
        depth = torch.full((1, 3), 3.0, dtype=torch.float64)
        on_centres = _unproject(centred, depth, cam)
        want = _naive_footprint(on_centres, cam, s, size)
        got = -torch.log1p(-splat_points(on_centres, cam, s, size, "planar"))
        torch.testing.assert_close(got, want, atol=2e-3, rtol=1e-3)
        anywhere = _unproject(torch.rand(1, 3, 2, generator=gen, dtype=torch.float64) * 1.2 - 0.6, depth, cam)
        want = _naive_footprint(anywhere, cam, s, size)
        got = -torch.log1p(-splat_points(anywhere, cam, s, size, "planar"))
        r_px = size * s / 2
        assert got.sum().item() == pytest.approx(3 * math.pi * r_px**2 / 2, rel=1e-3)
        assert want.sum().item() == pytest.approx(3 * math.pi * r_px**2 / 2, rel=2e-2)
        # Between centres the deposit is bilinear: a sub-pixel point spreads over a pixel-wide square.
        assert (got - want).abs().max() < (0.2 if r_px > 0.5 else 0.4) * want.max()


def test_every_point_size_of_the_sweep_draws_its_own_image():
    """Sub-pixel radii still draw (their footprint integrated over the pixel), so no two sizes coincide."""
    gen = torch.Generator().manual_seed(4)
    points = torch.rand(1, 256, 3, generator=gen) - 0.5
    cam = _front_camera(3.0)
    for s in (32, 64, 224):
        images = [splat_points(points, cam, s, size, kind) for size in (0.0075, 0.01, 0.02, 0.04, 0.08)
                  for kind in ("planar",)]
        for i in range(len(images)):
            for j in range(i + 1, len(images)):
                assert (images[i] - images[j]).abs().max() > 1e-3, (s, i, j)


def test_splat_depth_is_nearly_unbiased_inside_a_dense_cloud():
    cam = _front_camera(3.0)
    lin = torch.linspace(-0.5, 0.5, 48)
    y, x = torch.meshgrid(lin, lin, indexing="ij")
    plane = torch.stack([x, y, torch.full_like(x, 0.5)], dim=-1).view(1, -1, 3)  # view depth 2.5
    depth = splat_points(plane, cam, 32, 0.1, "depth")
    planar = splat_points(plane, cam, 32, 0.1, "planar")
    frags = rasterize_points(plane, cam, 32, radius=0.1)
    covered = (frags.idx >= 0).to(plane.dtype)[None]
    inner = (-F.max_pool2d(-covered, 7, stride=1, padding=3) > 0.5)[0, 0]  # covered with a 3-px margin
    assert inner.sum() >= 64
    assert (depth[0][inner] - 2.5).abs().max() < 0.01 * 2.5
    assert planar[0][inner].min() > 0.99
    assert depth[0, 0, 0] < 1e-3 and planar[0, 0, 0] < 1e-3  # background corner


def test_splat_ignores_points_behind_the_camera_and_blurs_in_from_off_image():
    cam = _front_camera(3.0)
    base = torch.tensor([[[0.2, -0.1, 0.0]]])
    behind = torch.tensor([[[0.2, -0.1, 3.5]]], requires_grad=True)
    both = torch.cat([base, behind], dim=1)
    for kind in ("depth", "planar"):
        torch.testing.assert_close(splat_points(both, cam, 16, 0.2, kind), splat_points(base, cam, 16, 0.2, kind))
        splat_points(both, cam, 16, 0.2, kind).sum().backward()
        assert behind.grad.abs().max() == 0
    # Projected one pixel past the left edge (NDC x = 1 + 1/S): σ = 1.6 px still reaches column 0.
    off = _unproject(torch.tensor([[[1.0 + 1.0 / 16, 0.0]]]), torch.tensor([[3.0]]), cam)
    img = splat_points(off, cam, 16, 0.2, "planar")
    assert img[0, :, 0].max() > 0.1 and img[0, :, 0].max() > img[0, :, 1].max()


def test_splat_is_batched_and_validates_kind():
    gen = torch.Generator().manual_seed(2)
    points = torch.rand(3, 20, 3, generator=gen) - 0.5
    cams = orbit_cameras(torch.tensor([15.0]), torch.tensor([0.0]), torch.tensor([2.5]), 3).flatten()
    together = splat_points(points, cams, 24, 0.05, "depth")
    apart = torch.cat([splat_points(points[i : i + 1], cams[i : i + 1], 24, 0.05, "depth") for i in range(3)])
    torch.testing.assert_close(together, apart)
    with pytest.raises(ValueError, match="kind"):
        splat_points(points, cams, 24, 0.05, "silhouette")


def _plane(depth: float, half: float = 0.5, side: int = 48) -> torch.Tensor:
    lin = torch.linspace(-half, half, side)
    y, x = torch.meshgrid(lin, lin, indexing="ij")
    return torch.stack([x, y, torch.full_like(x, 3.0 - depth)], dim=-1).view(1, -1, 3)  # camera at z = 3


def test_depth_front_layer_shows_the_nearest_surface_as_a_zbuffered_reference():
    """A plane at view depth 2.4 in front of a wider one at 3.0: PyTorch3D's z-buffer (the naive loop
    reference) sees 2.4 where both overlap and 3.0 around; the front layer matches it, the average not."""
    cam = _front_camera(3.0)
    scene = torch.cat([_plane(2.4, 0.3, 30), _plane(3.0, 1.2, 80)], dim=1)
    s, r = 24, 0.1
    _, ref = _naive_rasterize(scene, cam, s, r)
    layered = splat_points(scene, cam, s, r, "depth", depth_layer=0.4)[0]
    averaged = splat_points(scene, cam, s, r, "depth")[0]
    front = _naive_rasterize(_plane(2.4, 0.3, 30), cam, s, r)[0][0] >= 0
    inner = (-F.max_pool2d(-front[None, None].float(), 5, stride=1, padding=2) > 0.5)[0, 0]  # 2 px inside its edge
    assert inner.sum() >= 9
    torch.testing.assert_close(ref[0][inner], torch.full((int(inner.sum()),), 2.4))
    assert (layered[inner] - 2.4).abs().max() < 0.02 * 2.4
    assert (averaged[inner] - 2.4).abs().min() > 0.1  # the back plane pulls the average away
    back = _naive_rasterize(_plane(3.0, 1.2, 80), cam, s, r)[0][0] >= 0
    back_inner = -F.max_pool2d(-back[None, None].float(), 5, stride=1, padding=2)[0, 0] > 0.5
    away = F.max_pool2d(front[None, None].float(), 7, stride=1, padding=3)[0, 0] < 0.5  # 3 px from the front plane
    back_only = back_inner & away
    assert back_only.sum() >= 9
    assert (layered[back_only] - 3.0).abs().max() < 0.02 * 3.0


def test_depth_front_layer_gradcheck_float64():
    gen = torch.Generator().manual_seed(0)
    cams = _double(look_at_cameras(torch.tensor([20.0]), torch.tensor([35.0]), torch.tensor([2.5])))
    points = (torch.rand(1, 4, 3, generator=gen, dtype=torch.float64) - 0.5).requires_grad_()
    assert torch.autograd.gradcheck(lambda p: splat_points(p, cams, 8, 0.2, "depth", depth_layer=0.3), (points,),
                                    eps=1e-6, atol=1e-5)


def test_depth_layer_is_refused_for_planar_images_and_non_positive_values():
    points = torch.rand(1, 5, 3) - 0.5
    for kind, layer in (("planar", 0.4), ("depth", 0.0)):
        with pytest.raises(ValueError, match="depth_layer"):
            splat_points(points, _front_camera(), 16, 0.1, kind, depth_layer=layer)


@pytest.mark.parametrize("radius_px", [0.6, 1.28])  # 1.28: the local profile's 0.04 NDC at 64²
def test_shifted_taps_backward_is_the_sliced_sums_gradient(radius_px):
    """The naive reference sums the shifted slices under autograd (each slice's gradient zero-filled);
    the hand-written adjoint (the flipped taps over the zero-padded gradient) agrees to 1e-6."""
    taps = _footprint(radius_px).table.tolist()
    width = len(taps)
    assert width == 3
    g = torch.Generator().manual_seed(0)
    canvas = torch.rand(5, 2, 20, 20, generator=g, requires_grad=True)
    upstream = torch.randn(5, 2, 21 - width, 21 - width, generator=g)
    out_size = 21 - width
    naive = sum(
        canvas[..., i : i + out_size, j : j + out_size] * taps[i][j] for i in range(width) for j in range(width)
    )
    fast = _ShiftedTaps.apply(canvas, taps)
    torch.testing.assert_close(fast, naive, rtol=0, atol=1e-6)
    (grad_naive,) = torch.autograd.grad(naive, canvas, upstream)
    (grad_fast,) = torch.autograd.grad(fast, canvas, upstream)
    torch.testing.assert_close(grad_fast, grad_naive, rtol=0, atol=1e-6)


def test_bilinear_deposit_equals_the_corner_by_corner_loop():
    """The naive reference deposits corner by corner (four passes); the vectorised deposit gives the same
    weights and indices bit for bit, and gradients to 1e-6 (summed in another order)."""
    g = torch.Generator().manual_seed(0)
    side = 20
    col = (torch.rand(3, 50, generator=g) * (side + 6) - 3).requires_grad_()  # some off the canvas
    row = (torch.rand(3, 50, generator=g) * (side + 6) - 3).requires_grad_()
    front = (torch.rand(3, 50, generator=g) > 0.2).float()
    col0, row0 = torch.floor(col).detach(), torch.floor(row).detach()
    values, indices = [], []
    for dr, wr in ((0, 1.0 - (row - row0)), (1, row - row0)):
        for dc, wc in ((0, 1.0 - (col - col0)), (1, col - col0)):
            r, c = row0 + dr, col0 + dc
            on_canvas = ((r >= 0) & (r < side) & (c >= 0) & (c < side)).to(front.dtype)
            values.append(wr * wc * front * on_canvas)
            indices.append((r.clamp(0, side - 1) * side + c.clamp(0, side - 1)).long())
    naive_values, naive_indices = torch.cat(values, dim=1), torch.cat(indices, dim=1)
    got_values, got_indices = _bilinear_deposit(col, row, front, side)
    assert torch.equal(got_values, naive_values) and torch.equal(got_indices, naive_indices)
    upstream = torch.randn(3, 200, generator=g)
    for got, want in zip(torch.autograd.grad(got_values, (col, row), upstream),
                         torch.autograd.grad(naive_values, (col, row), upstream)):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-6)


@pytest.mark.parametrize("half", [0, 1, 3, 9])  # windows 1–19 px: point sizes 0.0075–0.08 at 64²–224²
def test_window_minimum_equals_the_negated_max_pool_it_replaced(half):
    """kornia's erosion (``_window_min``, the nearest surface of ``_front_layer``) against the formula it
    replaced, ``-max_pool2d(-z)``: the same values bit for bit on z-buffers with empty (+inf) pixels,
    edges included."""
    g = torch.Generator().manual_seed(half)
    zbuf = torch.rand(3, 1, 30, 34, generator=g) * 4.0 + 1.0
    zbuf[torch.rand(zbuf.shape, generator=g) < 0.6] = math.inf
    window = 2 * half + 1
    want = -F.max_pool2d(-zbuf, window, stride=1, padding=half)
    got = _window_min(zbuf, half)
    assert torch.equal(got, want)
    assert torch.equal(got, zbuf) == (half == 0)  # a wider window pulls nearer depths in
