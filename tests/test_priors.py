"""The paper's priors: 2D prior maps (cdm.data.priors2d: contour maps on a known image, depth
normalisation) and the 3D prior loss of the objective (cdm.objective)."""

import pytest
import torch
import torch.nn.functional as F

from cdm.cameras import orbit_cameras
from cdm.data.priors2d import PRIOR_2D_CHANNELS, contour_map, depth_prior_from_map, prior_2d_channels
from cdm.objective import prior_3d_loss


def _square_image(size: int = 32, lo: int = 8, hi: int = 24) -> torch.Tensor:
    """``(3, S, S)``: a white filled square on rows/cols ``[lo, hi)`` on black."""
    image = torch.zeros(3, size, size)
    image[:, lo:hi, lo:hi] = 1.0
    return image


def _near_square_border(size: int, lo: int, hi: int) -> torch.Tensor:
    """``(S, S)`` bool: within one pixel (8-neighbourhood) of the square's 1-px border ring."""
    square = _square_image(size, lo, hi)[:1, None]
    ring = square + F.max_pool2d(-square, 3, stride=1, padding=1)  # square minus its erosion
    return F.max_pool2d(ring, 3, stride=1, padding=1)[0, 0] > 0.5


def test_contour_of_a_filled_square_lies_on_its_border():
    edges = contour_map(_square_image())
    assert edges.shape == (1, 32, 32) and edges.dtype == torch.float32
    assert set(edges.unique().tolist()) == {0.0, 1.0}
    e = edges[0].bool()
    near_border = _near_square_border(32, 8, 24)
    assert not (e & ~near_border).any()  # nothing inside or far outside
    for side in (e[7:9, 10:22], e[23:25, 10:22], e[10:22, 7:9], e[10:22, 23:25]):  # every side found
        assert side.any(dim=0 if side.shape[0] == 2 else 1).all()
    assert contour_map(torch.full((3, 16, 16), 0.5)).sum() == 0  # flat image: no edges


def test_depth_prior_normalises_the_foreground_near_to_one():
    depth = torch.tensor([[[0.0, 2.0, 3.0], [4.0, 2.5, 0.0], [9.0, 3.5, 0.0]]])
    mask = torch.tensor([[[0.0, 1.0, 1.0], [1.0, 1.0, 1.0], [0.0, 1.0, 0.0]]])
    prior = depth_prior_from_map(depth, mask)
    # Foreground depths {2, 3, 4, 2.5, 3.5}: near 2 → 1, far 4 → 0; masked-out 9 and depth holes → 0.
    expected = torch.tensor([[[0.0, 1.0, 0.5], [0.0, 0.75, 0.0], [0.0, 0.25, 0.0]]])
    torch.testing.assert_close(prior, expected)
    torch.testing.assert_close(
        depth_prior_from_map(torch.full((1, 2, 2), 3.0), torch.ones(1, 2, 2)), torch.ones(1, 2, 2)
    )
    torch.testing.assert_close(depth_prior_from_map(depth, torch.zeros_like(mask)), torch.zeros_like(depth))


def test_prior_2d_channels_per_kind():
    image, mask = _square_image(16, 4, 12), torch.zeros(1, 16, 16)
    mask[:, 4:12, 4:12] = 1.0
    depth = torch.linspace(1.0, 2.0, 16).view(1, 1, 16).expand(1, 16, 16) * mask
    for kind, channels in PRIOR_2D_CHANNELS.items():
        out = prior_2d_channels(kind, image, mask, depth)
        assert out.shape == (channels, 16, 16)
    torch.testing.assert_close(prior_2d_channels("contour", image, mask, None), contour_map(image))
    torch.testing.assert_close(prior_2d_channels("depth", image, mask, depth), depth_prior_from_map(depth, mask))
    with pytest.raises(ValueError, match="priors.prior_2d='depth' needs a depth map"):
        prior_2d_channels("depth", image, mask, None)
    with pytest.raises(ValueError, match="priors.prior_2d must be one of"):
        prior_2d_channels("edges", image, mask, depth)


def _cloud(gen: torch.Generator, b: int, n: int) -> torch.Tensor:
    """``(B, N, 3)`` points on ellipsoid surfaces of random radii in [0.3, 0.6]."""
    d = torch.nn.functional.normalize(torch.randn(b, n, 3, generator=gen), dim=-1)
    return d * (0.3 + 0.3 * torch.rand(b, 1, 3, generator=gen))


def _chamfer(a: torch.Tensor, b: torch.Tensor) -> float:
    d = torch.cdist(a, b) ** 2
    return (d.min(dim=2).values.mean() + d.min(dim=1).values.mean()).item()


@pytest.mark.parametrize("kind", ["depth", "planar"])
def test_prior_3d_loss_zero_for_identical_positive_otherwise_and_cacheable(kind):
    gen = torch.Generator().manual_seed(0)
    gt = _cloud(gen, 2, 200)
    views = orbit_cameras(torch.tensor([20.0, 5.0]), torch.tensor([0.0, 90.0]), torch.tensor([2.5, 2.5]), 3)
    same = prior_3d_loss(gt.clone(), gt, views, 24, 0.08, kind)
    assert same.loss.item() == 0.0
    assert same.pred_images.shape == same.target_images.shape == (2, 3, 24, 24)
    pred = (gt + 0.05 * torch.randn(gt.shape, generator=gen)).requires_grad_()
    out = prior_3d_loss(pred, gt, views, 24, 0.08, kind)
    assert out.loss.item() > 0 and not out.target_images.requires_grad
    per_view = (out.pred_images - out.target_images).pow(2).mean(dim=(-2, -1))
    torch.testing.assert_close(out.loss, per_view.sum(dim=1).mean())  # Eq. 6: Σ over views, batch mean
    cached = prior_3d_loss(pred, gt, views, 24, 0.08, kind, target_images=out.target_images)
    torch.testing.assert_close(cached.loss, out.loss)
    with pytest.raises(ValueError, match="target_images must be"):
        prior_3d_loss(pred, gt, views, 16, 0.08, kind, target_images=out.target_images)
    with pytest.raises(ValueError, match="view_cameras must have batch shape"):
        prior_3d_loss(pred, gt, views.flatten(), 24, 0.08, kind)


def test_gradient_descent_on_the_3d_prior_alone_pulls_a_cloud_toward_gt():
    gen = torch.Generator().manual_seed(1)
    gt = _cloud(gen, 2, 256)
    views = orbit_cameras(torch.tensor([25.0, -10.0]), torch.tensor([0.0, 45.0]), torch.tensor([2.2, 2.2]), 4)
    pred = (gt + 0.08 * torch.randn(gt.shape, generator=gen)).requires_grad_()
    before = _chamfer(pred.detach(), gt)
    target = None
    optimiser = torch.optim.Adam([pred], lr=5e-3)
    losses = []
    for _ in range(60):
        out = prior_3d_loss(pred, gt, views, 32, 0.06, "depth", target_images=target)
        target = out.target_images
        optimiser.zero_grad()
        out.loss.backward()
        optimiser.step()
        losses.append(out.loss.item())
    after = _chamfer(pred.detach(), gt)
    assert losses[-1] < 0.5 * losses[0]
    assert after < 0.7 * before
