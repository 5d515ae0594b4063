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


def test_mask_distance_transform_matches_scipy():
    g = torch.Generator().manual_seed(0)
    mask = (torch.rand(3, 1, 20, 20, generator=g) > 0.93).float()
    mask[2] = 0.0
    got = mask_distance_transform(mask)
    for b in range(2):
        expected = distance_transform_edt(1 - mask[b, 0].numpy()) / 20
        np.testing.assert_allclose(got[b, 0].numpy(), expected, atol=1e-6)
    assert torch.allclose(got[2], torch.full((1, 20, 20), math.sqrt(2.0)))
    assert torch.equal(mask_distance_transform(torch.ones(1, 1, 5, 5)), torch.zeros(1, 1, 5, 5))


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


@pytest.mark.parametrize("backend", ["dense", "sparse"])
@pytest.mark.parametrize("global_feature", ["none", "concat", "cross_attention"])
def test_network_forward_shapes(tiny, backend, global_feature):
    torch.manual_seed(0)
    batch = tiny_batch()
    net = CDMNetwork(_model_config(tiny, voxel_backend=backend, global_feature=global_feature), prior_2d_channels=1)
    assert net.voxel_backend == backend
    context = net.encode(batch)
    assert context.pixel.shape == (2, conditioning_channels(8, 1), 16, 16)
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
