"""PC² projection conditioning: lift per-pixel image channels onto the points of ``x_t``.

Per image, once: the conditioning map stacks ``[image features, 2D prior (Eq. 7), RGB, mask, mask
distance transform]`` into ``(B, C, S, S)`` (:func:`conditioning_map`); the last two only with
``model.mask_channels`` (PC²'s ``use_mask`` and ``use_distance_transform``, on in its Co3D runs; BDM
turns both off for ShapeNet in its ``experiments/config/structured.py``). Per diffusion step: the
points of ``x_t`` are rasterized from the input camera with a hard z-buffer (one point per pixel,
radius 0.0075 NDC in PC²); each point that is front-most at the pixel containing its projection
gets that pixel's channels, every hidden or off-image point gets zeros (:func:`project_conditioning`).
The denoiser appends xyz.

Pixel layout and NDC conventions are those of :mod:`cdm.cameras` / :mod:`cdm.render`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from cdm.cameras import Cameras
from cdm.render import rasterize_points

__all__ = [
    "conditioning_channels",
    "conditioning_map",
    "features_at_pixels",
    "mask_distance_transform",
    "project_conditioning",
    "project_views",
]

def conditioning_channels(feature_dim: int, prior_2d_channels: int, mask_channels: bool = True) -> int:
    """Channels of :func:`conditioning_map`: features + 2D prior + RGB (3), + mask (1) + distance (1)
    with ``mask_channels``."""
    return feature_dim + prior_2d_channels + 3 + (2 if mask_channels else 0)


@torch.no_grad()
def mask_distance_transform(mask: Tensor) -> Tensor:
    """Exact Euclidean distance from each pixel to the nearest foreground pixel, divided by ``S``.

    PC² feeds this channel (OpenCV's ``distanceTransform`` of the background) so points just outside
    the silhouette know how far out they are. Computed in pure torch in two exact passes: along rows
    by cumulative max/min of foreground column indices, then ``d²(i, j) = min_k (i − k)² + g(k, j)²``
    over rows (``O(S³)`` per image). OpenCV's precise transform is 2.7–12.6× faster but returned
    different values for the same mask from one call to the next inside training, so a training no
    longer repeated bit for bit (``benchmarks/RESULTS.md``, "kornia and OpenCV (issue 59)").

    Args:
        mask: ``(B, 1, S, S)`` foreground where ``> 0.5``.
    Returns:
        ``(B, 1, S, S)``: 0 on the foreground, ``distance_in_pixels / S`` elsewhere; an image without
        foreground gets ``√2`` everywhere (beyond any distance inside the image). No gradient; dtype and
        device of ``mask``.
    """
    if mask.ndim != 4 or mask.shape[1] != 1 or mask.shape[2] != mask.shape[3]:
        raise ValueError(f"mask must be (B, 1, S, S), got shape {tuple(mask.shape)}")
    fg = mask[:, 0] > 0.5
    s = fg.shape[-1]
    idx = torch.arange(s, device=mask.device)
    far = 2 * s  # farther than any distance inside the image
    left = torch.where(fg, idx, -far).cummax(dim=2).values  # last foreground column <= j
    right = torch.where(fg, idx, s + far).flip(2).cummin(dim=2).values.flip(2)  # first one >= j
    g2 = torch.minimum(idx - left, right - idx).to(torch.float32).square()  # (B, S_k, S_j)
    di2 = (idx[:, None] - idx[None, :]).to(torch.float32).square()  # (S_i, S_k)
    # A running minimum over source rows k keeps the temporaries at (B, S, S); materialising the
    # (B, S_i, S_k, S_j) sums was 3-9x slower on CPU.
    d2 = g2.clone()
    candidate = torch.empty_like(g2)
    for k in range(s):
        torch.add(g2[:, k : k + 1, :], di2[None, :, k : k + 1], out=candidate)
        torch.minimum(d2, candidate, out=d2)
    dist = torch.where(d2 >= far * far, math.sqrt(2.0) * s, d2.sqrt()) / s
    return dist[:, None].to(mask.dtype)


def conditioning_map(
    features: Tensor | None, prior_2d: Tensor, image: Tensor, mask: Tensor, mask_channels: bool = True
) -> Tensor:
    """Stack the per-pixel conditioning channels, once per image.

    Args:
        features: ``(B, F, S, S)`` image features (encoder output), or ``None`` for a map without them
            (:func:`project_conditioning` then samples coarse features at the points).
        prior_2d: ``(B, C2, S, S)`` 2D-prior channels (contour or depth, Eq. 7).
        image: ``(B, 3, S, S)`` RGB in [0, 1].
        mask: ``(B, 1, S, S)`` foreground in {0, 1}.
        mask_channels: ``model.mask_channels``: append the mask and its distance transform.
    Returns:
        ``(B, F + C2 + 5, S, S)``: ``[features, prior_2d, RGB, mask, distance transform]``, or
        ``(B, F + C2 + 3, S, S)`` without the last two (``F`` = 0 without features).
    """
    maps = [prior_2d, image] if features is None else [features, prior_2d, image]
    if not mask_channels:
        return torch.cat(maps, dim=1)
    return torch.cat([*maps, mask, mask_distance_transform(mask)], dim=1)


def features_at_pixels(coarse: Tensor, pixel: Tensor, size: int) -> Tensor:
    """The bilinear upsampling of ``coarse`` to ``size × size`` (``align_corners=False``,
    :func:`cdm.model.encoder.upsample_features`), read only at the flat pixel indices ``pixel``.

    ``grid_sample`` at those pixels' centres: source coordinate ``(col + ½)·s/size − ½`` in both, the
    border clamped in both (``padding_mode="border"``), so the same function as upsampling the
    whole map and gathering, equal up to float rounding; a step then touches ``N`` points, not ``size²``
    pixels, forward and backward.

    Args:
        coarse: ``(B, F, s, s)`` features.
        pixel: ``(B, N)`` long flat indices ``row·size + col`` in ``[0, size²)``.
        size: ``S``, the side of the upsampled map.
    Returns:
        ``(B, N, F)``.
    """
    row = torch.div(pixel, size, rounding_mode="floor")
    col = pixel - row * size
    centre = torch.stack([col, row], dim=-1).to(coarse.dtype)
    grid = (2.0 * centre + 1.0) / size - 1.0  # x (column) first, as grid_sample reads it
    sampled = F.grid_sample(coarse, grid[:, None], mode="bilinear", padding_mode="border", align_corners=False)
    return sampled[:, :, 0].transpose(1, 2)


def project_conditioning(
    cond_map: Tensor,
    points: Tensor,
    cameras: Cameras,
    radius: float,
    features: Tensor | None = None,
    feature_slot: int = 0,
) -> Tensor:
    """Gather each visible point's conditioning channels at its own pixel; zeros for hidden points.

    Runs every diffusion step on ``x_t``: one hard rasterization (no gradient) and one gather
    (differentiable w.r.t. ``cond_map`` and ``features``, so a trainable encoder learns through it).

    Args:
        cond_map: ``(B, C, S, S)`` from :func:`conditioning_map`.
        points: ``(B, N, 3)`` world coordinates (``x_t``).
        cameras: input cameras, batch ``(B,)``.
        radius: rasterization radius, NDC units (``model.raster_radius``; PC²: 0.0075).
        features: ``(B, F, s, s)`` coarse image features that ``cond_map`` lacks: each point gets
            their bilinear upsampling to ``S`` at its pixel (:func:`features_at_pixels`).
        feature_slot: the channel at which those ``F`` channels are inserted.
    Returns:
        ``(B, N, C)`` per-point conditioning (``C + F`` with ``features``).
    """
    b, c, s, _ = cond_map.shape
    frags = rasterize_points(points.detach(), cameras, s, radius)
    pixel = frags.pixel.clamp(min=0)
    gathered = cond_map.flatten(2).gather(2, pixel[:, None, :].expand(b, c, -1)).transpose(1, 2)  # (B, N, C)
    if features is not None:
        sampled = features_at_pixels(features, pixel, s)
        gathered = torch.cat([gathered[..., :feature_slot], sampled, gathered[..., feature_slot:]], dim=-1)
    return gathered * frags.visible[..., None].to(gathered.dtype)


def project_views(cond_maps: Tensor, points: Tensor, cameras: Cameras, valid: Tensor, radius: float) -> Tensor:
    """Several condition images per sample (supplementary Table 8): each point gets the mean of the
    channels it gathers from the views it is front-most in; points seen by none get zeros (as PC²).

    Args:
        cond_maps: ``(B, V, C, S, S)`` conditioning maps, view 0 the input image.
        points: ``(B, N, 3)`` world coordinates (``x_t``).
        cameras: batch ``(B, V)``.
        valid: ``(B, V)`` bool, views that take part.
        radius: rasterization radius, NDC units.
    Returns:
        ``(B, N, C)``.
    """
    b, v, c, s, _ = cond_maps.shape
    seen_channel = cond_maps.new_ones(b, v, 1, s, s)  # gathers 1 exactly where a point is visible
    gathered = project_conditioning(
        torch.cat([cond_maps, seen_channel], dim=2).flatten(0, 1),
        points.repeat_interleave(v, 0),
        cameras.flatten(),
        radius,
    ).unflatten(0, (b, v)) * valid[:, :, None, None].to(cond_maps.dtype)  # (B, V, N, C + 1)
    seen = gathered[..., -1:].sum(dim=1)
    return gathered[..., :-1].sum(dim=1) / seen.clamp(min=1.0)
