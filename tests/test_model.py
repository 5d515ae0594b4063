"""Tests of cdm.model: encoders, projection conditioning, global features, denoiser and network."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.ndimage import distance_transform_edt

from cdm.cameras import Cameras, look_at_cameras, pixel_centers_ndc
from cdm.config import Config, ModelConfig
from cdm.data.sample import Batch
from cdm.model import (
    CDMNetwork,
    ImageEncoder,
    conditioning_channels,
    conditioning_map,
    mask_distance_transform,
    project_conditioning,
    timestep_embedding,
)
from cdm.model.conditioning import features_at_pixels
from cdm.model.encoder import upsample_features
from cdm.model.pvcnn import point_norm_silu
from cdm.model.voxels import norm_groups


def _model_config(tiny: Config, **changes) -> ModelConfig:
    """The shared tiny config's model group (tests/conftest.py) with ``changes``, validated."""
    return ModelConfig.model_validate({**tiny.model.model_dump(), **changes})


def tiny_batch(b: int = 2, n: int = 64, s: int = 16, prior_channels: int = 1, seed: int = 0) -> Batch:
    """A reproducible batch: disc masks, random images/priors, points on a sphere, cameras around it."""
    g = torch.Generator().manual_seed(seed)
    cams = look_at_cameras(torch.full((b,), 15.0), 360.0 * torch.rand(b, generator=g), torch.full((b,), 2.5))
    rows, cols = torch.meshgrid(torch.arange(s), torch.arange(s), indexing="ij")
    mask = (((rows - s / 2) ** 2 + (cols - s / 2) ** 2) < (s / 3) ** 2).float()
    points = F.normalize(torch.randn(b, n, 3, generator=g), dim=-1) * 0.8
    return Batch(
        image=torch.rand(b, 3, s, s, generator=g),
        mask=mask.expand(b, 1, s, s).clone(),
        depth=None,
        prior_2d=torch.rand(b, prior_channels, s, s, generator=g),
        camera=cams,
        view_cameras=cams,
        points=points,
        category=("sphere",) * b,
        object_id=tuple(f"o{i}" for i in range(b)),
    )


def test_timestep_embedding_values():
    emb = timestep_embedding(torch.tensor([0, 7]), 9)
    assert emb.shape == (2, 9)
    assert torch.equal(emb[0], torch.tensor([0.0] * 4 + [1.0] * 4 + [0.0]))
    freqs = torch.exp(-math.log(10_000.0) * torch.arange(4) / 4)
    assert torch.allclose(emb[1, :4], torch.sin(7 * freqs)) and torch.allclose(emb[1, 4:8], torch.cos(7 * freqs))


@pytest.mark.parametrize("size", [16, 30])
def test_image_encoder_shape_and_gradient(size):
    torch.manual_seed(0)
    encoder = ImageEncoder(prior_2d_channels=2, feature_dim=6)
    image = torch.rand(2, 3, size, size, requires_grad=True)
    out = encoder(image, torch.ones(2, 1, size, size), torch.rand(2, 2, size, size))
    assert out.shape == (2, 6, size, size)
    out.square().sum().backward()
    assert image.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="prior_2d has 1 channels"):
        encoder(image, torch.ones(2, 1, size, size), torch.rand(2, 1, size, size))


@pytest.mark.parametrize("size", [16, 30])
def test_image_encoder_coarse_equals_projecting_the_concatenated_maps(size):
    """The naive reference: upsample the S/4 map, concatenate it with the S/2 map and project with the 1×1
    ``out`` convolution. The encoder projects before upsampling (linear maps commute with bilinear
    weights that sum to 1): the same function, equal to float rounding; gradients too."""
    torch.manual_seed(0)
    encoder = ImageEncoder(prior_2d_channels=1, feature_dim=6)
    image, mask, prior = torch.rand(2, 3, size, size), torch.ones(2, 1, size, size), torch.rand(2, 1, size, size)

    def naive() -> torch.Tensor:
        half = encoder.down1(torch.cat([image, mask, prior], dim=1))
        quarter = encoder.mid(encoder.down2(half))
        up = F.interpolate(quarter, size=half.shape[-2:], mode="bilinear", align_corners=False)
        return encoder.out(torch.cat([up, half], dim=1))

    upstream = torch.randn(2, 6, (size + 1) // 2, (size + 1) // 2)
    params = list(encoder.parameters())
    got, want = encoder.coarse(image, mask, prior), naive()
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    for g, w in zip(torch.autograd.grad(got, params, upstream), torch.autograd.grad(want, params, upstream)):
        torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-5 * w.abs().max().item())


@pytest.mark.parametrize("size, density", [(20, 0.07), (33, 0.01), (64, 0.3)])
def test_mask_distance_transform_matches_scipy(size, density):
    """OpenCV's precise L2 transform is exact: scipy's Euclidean transform to float32 rounding, on sparse
    and dense random masks, a single foreground pixel in a corner, and masks with no foreground."""
    g = torch.Generator().manual_seed(size)
    mask = (torch.rand(4, 1, size, size, generator=g) < density).float()
    mask[2] = 0.0
    mask[3] = 0.0
    mask[3, 0, -1, 0] = 1.0
    got = mask_distance_transform(mask)
    assert got.shape == mask.shape and got.dtype == mask.dtype
    for b in (0, 1, 3):
        expected = distance_transform_edt(1 - mask[b, 0].numpy()) / size
        np.testing.assert_allclose(got[b, 0].numpy(), expected, rtol=0, atol=1e-6)
    assert torch.equal(got[mask > 0.5], torch.zeros(int((mask > 0.5).sum())))
    assert torch.allclose(got[2], torch.full((1, size, size), math.sqrt(2.0)))
    assert torch.equal(mask_distance_transform(torch.ones(1, 1, 5, 5)), torch.zeros(1, 1, 5, 5))
    assert mask_distance_transform(mask.double()).dtype == torch.float64


def _point_at_pixel(cams: Cameras, image_size: int, row: int, col: int, depth: float) -> torch.Tensor:
    """World point of view depth ``depth`` projecting onto the centre of pixel (row, col) of camera 0."""
    x, y = pixel_centers_ndc(image_size)[row, col]
    view = torch.stack([x * depth / cams.focal[0], y * depth / cams.focal[0], torch.tensor(depth)])
    return (view - cams.T[0]) @ cams.R[0].T


def test_projection_conditioning_visible_point_gets_its_pixel_and_hidden_points_zeros():
    s = 16
    cams = look_at_cameras(torch.tensor([10.0]), torch.tensor([30.0]), torch.tensor([3.0]))
    front = _point_at_pixel(cams, s, 5, 9, 2.5)
    behind = _point_at_pixel(cams, s, 5, 9, 3.5)  # same pixel, farther: occluded
    other = _point_at_pixel(cams, s, 12, 2, 3.0)
    off_image = _point_at_pixel(cams, s, 3, 3, 3.0) + 100.0 * cams.R[0][:, 0]  # far left of the frustum
    points = torch.stack([behind, front, other, off_image])[None]
    cond_map = torch.randn(1, 7, s, s)
    cond = project_conditioning(cond_map, points, cams, radius=0.0075)
    assert cond.shape == (1, 4, 7)
    assert torch.equal(cond[0, 1], cond_map[0, :, 5, 9])
    assert torch.equal(cond[0, 2], cond_map[0, :, 12, 2])
    assert torch.equal(cond[0, 0], torch.zeros(7)) and torch.equal(cond[0, 3], torch.zeros(7))


def test_conditioning_map_channel_layout():
    batch = tiny_batch(prior_channels=2)
    features = torch.randn(2, 4, 16, 16)
    cmap = conditioning_map(features, batch.prior_2d, batch.image, batch.mask)
    assert cmap.shape[1] == conditioning_channels(4, 2) == 11
    assert torch.equal(cmap[:, :4], features) and torch.equal(cmap[:, 4:6], batch.prior_2d)
    assert torch.equal(cmap[:, 6:9], batch.image) and torch.equal(cmap[:, 9:10], batch.mask)
    assert torch.equal(cmap[:, 10:], mask_distance_transform(batch.mask))


@pytest.mark.parametrize(("coarse_size", "size"), [(8, 16), (4, 64), (5, 9)])
def test_features_at_pixels_are_the_upsampled_map_at_those_pixels(coarse_size, size):
    """The naive reference upsamples the whole map (PC²'s feature_model.py), then gathers: the same
    function. The two round the source coordinate differently (~1e-7 of it), which moves a value by
    that times the map's slope: 1e-5 on values of order 1, gradients too."""
    g = torch.Generator().manual_seed(0)
    coarse = torch.randn(2, 5, coarse_size, coarse_size, generator=g, requires_grad=True)
    pixel = torch.randint(0, size * size, (2, 300), generator=g)
    pixel[:, :4] = torch.tensor([0, size - 1, size * (size - 1), size * size - 1])  # corners: clamped borders
    upstream = torch.randn(2, 300, 5, generator=g)
    full = upsample_features(coarse, size).flatten(2).gather(2, pixel[:, None].expand(2, 5, -1)).transpose(1, 2)
    sampled = features_at_pixels(coarse, pixel, size)
    torch.testing.assert_close(sampled, full, rtol=0, atol=1e-5)
    (grad_full,) = torch.autograd.grad(full, coarse, upstream)
    (grad_sampled,) = torch.autograd.grad(sampled, coarse, upstream)
    torch.testing.assert_close(grad_sampled, grad_full, rtol=0, atol=1e-5)


@pytest.mark.parametrize("denoiser", ["pointvoxel", "pvcnn2"])
def test_network_with_coarse_features_equals_the_full_conditioning_map(tiny, denoiser):
    """The naive reference puts the whole upsampled feature map into the conditioning map (the context
    without ``features``); output and every gradient agree with the sampled features to float rounding."""
    torch.manual_seed(0)
    pc2 = {"width_multiplier": 0.25, "voxel_resolution_multiplier": 0.25} if denoiser == "pvcnn2" else {}
    net = CDMNetwork(_model_config(tiny, denoiser=denoiser, **pc2), prior_2d_channels=1).eval()  # no dropout
    batch = tiny_batch(n=300)
    t = torch.tensor([3, 700])
    params = [p for p in net.parameters() if p.requires_grad]

    def run(naive: bool):
        context = net.encode(batch)
        if naive:
            full = upsample_features(context.features, 16)
            maps = conditioning_map(full, batch.prior_2d, batch.image, batch.mask, net.mask_channels)
            context = context._replace(pixel=net._arrange(maps), features=None)
        out = net(batch.points, t, context, batch.camera)
        return out, torch.autograd.grad(out.square().sum(), params, allow_unused=True)

    (out, grads), (naive_out, naive_grads) = run(False), run(True)
    torch.testing.assert_close(out, naive_out, rtol=1e-5, atol=1e-6)
    assert [g is None for g in grads] == [g is None for g in naive_grads]
    # Some gradients cancel to ~0, so the scale is the largest gradient of the network.
    scale = max(g.abs().max().item() for g in naive_grads if g is not None)
    for grad, naive_grad in zip(grads, naive_grads, strict=True):
        if naive_grad is not None:
            torch.testing.assert_close(grad, naive_grad, rtol=1e-4, atol=1e-5 * scale)


@pytest.mark.parametrize("channels", [8, 32, 128])
def test_point_norm_silu_equals_group_norm_then_silu(channels):
    """The naive reference is ``nn.GroupNorm`` on the transposed ``(B, C, N)`` features, then SiLU: the
    same function, summed in another order, so equal to 1e-5 relative (features off-centre, where a
    one-pass variance would not be)."""
    g = torch.Generator().manual_seed(0)
    h = (torch.randn(3, 200, channels, generator=g) * 3 + 5).requires_grad_()
    norm = torch.nn.GroupNorm(norm_groups(channels), channels)
    with torch.no_grad():
        norm.weight.copy_(torch.randn(channels, generator=g))
        norm.bias.copy_(torch.randn(channels, generator=g))
    upstream = torch.randn(3, 200, channels, generator=g)
    naive = F.silu(norm(h.transpose(1, 2)).transpose(1, 2))
    fused = point_norm_silu(h, norm)
    torch.testing.assert_close(fused, naive, rtol=1e-5, atol=1e-5)
    params = (h, norm.weight, norm.bias)
    for got, want in zip(torch.autograd.grad(fused, params, upstream), torch.autograd.grad(naive, params, upstream)):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5 * want.abs().max().item())
    # as autocast runs GroupNorm: float32 whatever the input's dtype
    low = point_norm_silu(h.detach().bfloat16(), norm)
    assert low.dtype == torch.float32
    torch.testing.assert_close(low, F.silu(norm(h.detach().bfloat16().float().transpose(1, 2)).transpose(1, 2)))


@pytest.mark.parametrize("backend", ["dense", "sparse"])
@pytest.mark.parametrize("global_feature", ["none", "concat", "cross_attention"])
def test_network_forward_shapes(tiny, backend, global_feature):
    torch.manual_seed(0)
    batch = tiny_batch()
    net = CDMNetwork(_model_config(tiny, voxel_backend=backend, global_feature=global_feature), prior_2d_channels=1)
    assert net.voxel_backend == backend
    context = net.encode(batch)
    # The map holds the other channels; the features stay coarse (S/2) and are sampled at the points.
    assert context.pixel.shape == (2, conditioning_channels(0, 1), 16, 16)
    assert context.features.shape == (2, 8, 8, 8)
    assert (context.embedding is None) == (global_feature != "concat")
    assert (context.tokens is None) == (global_feature != "cross_attention")
    if context.tokens is not None:
        assert context.tokens.shape == (2, 64, 8)
    out = net(batch.points, torch.tensor([0, 999]), context, batch.camera)
    assert out.shape == (2, 64, 3) and torch.isfinite(out).all()
    # The time embedding reaches the output.
    assert not torch.allclose(out, net(batch.points, torch.tensor([500, 1]), context, batch.camera))


def test_network_single_point_and_backend_resolution(tiny):
    net = CDMNetwork(_model_config(tiny), prior_2d_channels=0, device="cpu")
    assert net.voxel_backend == "sparse"
    assert CDMNetwork(_model_config(tiny), prior_2d_channels=0, device="cuda").voxel_backend == "dense"
    batch = tiny_batch(n=1, prior_channels=0)
    out = net(batch.points, torch.tensor([3, 4]), net.encode(batch), batch.camera)
    assert out.shape == (2, 1, 3) and torch.isfinite(out).all()


def test_network_validates_its_inputs(tiny):
    net = CDMNetwork(_model_config(tiny), prior_2d_channels=1)
    with pytest.raises(ValueError, match="prior_2d has 2 channels"):
        net.encode(tiny_batch(prior_channels=2))
    batch = tiny_batch()
    with pytest.raises(ValueError, match="must match"):
        net(batch.points, torch.tensor([1]), net.encode(batch), batch.camera)
    with pytest.raises(ValueError, match="feature_dim"):
        CDMNetwork(_model_config(tiny), 1, encoder=ImageEncoder(1, 4))


@pytest.mark.parametrize("backend", ["dense", "sparse"])
def test_a_few_optimizer_steps_reduce_the_loss(tiny, backend):
    torch.manual_seed(0)
    batch = tiny_batch()
    net = CDMNetwork(_model_config(tiny, voxel_backend=backend), prior_2d_channels=1)
    opt = torch.optim.AdamW(net.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(1)
    noise = torch.randn(batch.points.shape, generator=g)
    t = torch.tensor([100, 600])
    x_t = 0.8 * batch.points + 0.6 * noise
    losses = []
    for _ in range(25):
        loss = F.mse_loss(net(x_t, t, net.encode(batch), batch.camera), noise)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0]
