"""The paper's two kinds of priors: 2D prior maps from the input image (§3.3, Eq. 7) and the 3D
prior constraint between renderings of two clouds (§3.2, Eq. 6).

2D priors are extra image channels concatenated with the image features before they are projected
onto the points (Eq. 7, ``F_I ⊕ F_I*``): a contour map (ShapeNet) or a depth map (Co3D, from a
depth estimator such as DINOv2's). Images are ``(3, S, S)`` RGB in [0, 1] in the pixel layout of
:mod:`cdm.cameras`.

The 3D prior constraint renders a predicted cloud and the ground-truth cloud from the H prior
views with :func:`cdm.render.splat_points` and penalises their squared image difference.
"""

from __future__ import annotations

from typing import Literal, NamedTuple, Protocol, runtime_checkable

import cv2
import kornia
import numpy as np
import torch
from torch import Tensor

from cdm.cameras import Cameras
from cdm.render import splat_points

__all__ = [
    "PRIOR_2D_CHANNELS",
    "DepthEstimator",
    "Prior3DLoss",
    "contour_map",
    "contour_map_soft",
    "depth_prior_from_map",
    "prior_2d_channels",
    "prior_3d_loss",
]

PRIOR_2D_CHANNELS = {"none": 0, "contour": 1, "depth": 1}
"""Channels each ``priors.prior_2d`` kind adds to the conditioning image features (Eq. 7)."""

# Largest normalised-Sobel magnitude of an image in [0, 1]: |gx|, |gy| <= 1/2 each.
_SOBEL_MAX = 0.5 * 2.0**0.5


def contour_map(image: Tensor, low_threshold: float = 100.0, high_threshold: float = 200.0) -> Tensor:
    """Binary contour map of one image with OpenCV's Canny detector (data side, no gradient).

    Args:
        image: ``(3, S, S)`` RGB in [0, 1].
        low_threshold, high_threshold: Canny hysteresis thresholds on the 8-bit grey image's
            (unnormalised 3×3 Sobel) gradient magnitude; OpenCV's documented example values.
    Returns:
        ``(1, S, S)`` in {0, 1} (1 on edges), same dtype and device as ``image``.
    """
    if image.ndim != 3 or image.shape[0] != 3:
        raise ValueError(f"image must be (3, S, S) RGB in [0, 1], got shape {tuple(image.shape)}")
    rgb = (image.detach().clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    edges = cv2.Canny(grey, low_threshold, high_threshold)
    return torch.from_numpy(edges > 0).to(device=image.device, dtype=image.dtype)[None]


def contour_map_soft(images: Tensor) -> Tensor:
    """Differentiable contour map: Sobel gradient magnitude of the grey image, scaled to [0, 1].

    Use where gradients must flow to the image; :func:`contour_map` is the data-side binary map.
    Divides the normalised Sobel magnitude by its maximum for [0, 1] inputs (√2/2), so no clamp
    cuts gradients: an axis-aligned 0→1 step edge gives ≈0.71 on the two pixels beside it.

    Args:
        images: ``(B, 3, S, S)`` RGB in [0, 1].
    Returns:
        ``(B, 1, S, S)`` in [0, 1] (≈1e-3 on flat regions, from Sobel's sqrt ε).
    """
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"images must be (B, 3, S, S) RGB in [0, 1], got shape {tuple(images.shape)}")
    grey = kornia.color.rgb_to_grayscale(images)
    return kornia.filters.sobel(grey, normalized=True) / _SOBEL_MAX


@runtime_checkable
class DepthEstimator(Protocol):
    """A monocular depth model (e.g. a local DINOv2 depth head) used for the depth 2D prior.

    ``__call__(images)``: ``(B, 3, S, S)`` RGB in [0, 1] → ``(B, 1, S, S)`` view depth, larger =
    farther, any positive scale (it is normalised per image by :func:`depth_prior_from_map`).
    A model that outputs disparity must invert it first.
    """

    def __call__(self, images: Tensor) -> Tensor: ...


def depth_prior_from_map(depth: Tensor, mask: Tensor) -> Tensor:
    """Normalise one depth map to a [0, 1] depth prior on the object: near = 1, far = 0, background 0.

    Foreground is ``mask > 0.5`` with a positive depth (holes in real depth maps are 0). The nearest
    foreground pixel maps to 1 and the farthest to 0, linearly in depth; the mask channel of the
    conditioning tells the farthest pixels from the background. A flat foreground maps to 1.

    Args:
        depth: ``(1, S, S)`` view depth (world units, 0 where unknown).
        mask: ``(1, S, S)`` foreground in {0, 1}.
    Returns:
        ``(1, S, S)`` in [0, 1].
    """
    if depth.ndim != 3 or depth.shape[0] != 1 or mask.shape != depth.shape:
        raise ValueError(
            f"depth and mask must both be (1, S, S), got {tuple(depth.shape)} and {tuple(mask.shape)}"
        )
    fg = (mask > 0.5) & (depth > 0)
    if not fg.any():
        return torch.zeros_like(depth)
    near, far = depth[fg].min(), depth[fg].max()
    span = far - near
    nearness = (far - depth) / span if span > 0 else torch.ones_like(depth)
    return torch.where(fg, nearness, torch.zeros_like(depth))


def prior_2d_channels(
    kind: Literal["none", "contour", "depth"],
    image: Tensor,
    mask: Tensor,
    depth: Tensor | None,
    estimator: DepthEstimator | None = None,
) -> Tensor:
    """The 2D-prior channels of one sample (Eq. 7), ``PRIOR_2D_CHANNELS[kind]`` of them.

    ``"depth"`` uses ``estimator`` on the image when given (the paper's DINOv2 route), otherwise the
    sample's own depth map. That map comes from the data (a renderer or a sensor), so it is a cleaner,
    privileged stand-in for an estimate from the image: results with it are an upper bound.

    Args:
        kind: ``priors.prior_2d``.
        image: ``(3, S, S)`` RGB in [0, 1].
        mask: ``(1, S, S)`` foreground in {0, 1}.
        depth: ``(1, S, S)`` view depth (world units, 0 on background) or None.
        estimator: optional :class:`DepthEstimator`.
    Returns:
        ``(C, S, S)`` with ``C = PRIOR_2D_CHANNELS[kind]``, dtype and device of ``image``.
    """
    if kind not in PRIOR_2D_CHANNELS:
        raise ValueError(f"priors.prior_2d must be one of {sorted(PRIOR_2D_CHANNELS)}, got {kind!r}")
    if kind == "none":
        return image.new_zeros(0, *image.shape[1:])
    if kind == "contour":
        return contour_map(image)
    if estimator is not None:
        with torch.no_grad():
            depth = estimator(image[None])[0]
    if depth is None:
        raise ValueError(
            "priors.prior_2d='depth' needs a depth map: this sample has none and no DepthEstimator was "
            "given; use a data set that provides depth, pass an estimator, or set priors.prior_2d='contour'"
        )
    return depth_prior_from_map(depth.to(image.dtype), mask)


class Prior3DLoss(NamedTuple):
    """Result of :func:`prior_3d_loss`.

    Attributes:
        loss: scalar, Eq. 6's prior term averaged over the batch.
        pred_images: ``(B, H, S, S)`` renderings of the compared cloud (with gradient).
        target_images: ``(B, H, S, S)`` renderings of the ground truth (no gradient); pass them back
            as ``target_images`` to skip re-rendering the same shape and views.
    """

    loss: Tensor
    pred_images: Tensor
    target_images: Tensor


def prior_3d_loss(
    pred_points: Tensor,
    gt_points: Tensor,
    view_cameras: Cameras,
    render_size: int,
    point_size: float,
    kind: Literal["depth", "planar"],
    target_images: Tensor | None = None,
) -> Prior3DLoss:
    """3D prior constraint (Eq. 6): ``Σ_{i=1..H} ‖proj(x, v_i) − proj(x₀, v_i)‖²``, batch mean.

    Each view's term is the mean squared pixel difference of the two S×S renderings, so the loss
    does not grow with the image size; views are summed as in Eq. 6.

    Which cloud ``x`` is compared is the caller's choice (``priors.target``). Eq. 6 writes the
    noised cloud ``x_t``, but ``x_t`` is made from ``x₀`` and noise, not by the network, so that term
    has no gradient and cannot train anything. The default therefore passes the predicted clean
    cloud ``x̂₀ = (x_t − √(1−ᾱ_t)·ε̂)/√ᾱ_t``, which depends on the network through ``ε̂``; ``x_t``
    stays selectable for the ablation (NOTES §1).

    Args:
        pred_points: ``(B, N, 3)`` world coordinates of the compared cloud (x̂₀ or x_t).
        gt_points: ``(B, M, 3)`` world coordinates of the ground truth x₀.
        view_cameras: batch ``(B, H)``, the H prior views per sample.
        render_size: ``S`` in pixels (paper: 224).
        point_size: splat size in NDC units (paper: 0.04).
        kind: ``"depth"`` (Co3D) or ``"planar"`` (ShapeNet) renderings (Fig. 3).
        target_images: optional cached ``(B, H, S, S)`` renderings of ``gt_points``.
    Returns:
        :class:`Prior3DLoss`.
    """
    if pred_points.ndim != 3 or gt_points.ndim != 3 or pred_points.shape[0] != gt_points.shape[0]:
        raise ValueError(
            f"pred_points and gt_points must be (B, N, 3) with the same B, got {tuple(pred_points.shape)} "
            f"and {tuple(gt_points.shape)}"
        )
    b = pred_points.shape[0]
    if len(view_cameras.batch_shape) != 2 or view_cameras.batch_shape[0] != b:
        raise ValueError(
            f"view_cameras must have batch shape (B, H) with B = {b}, got {tuple(view_cameras.batch_shape)}"
        )
    h = view_cameras.batch_shape[1]
    s = render_size
    cameras = view_cameras.flatten()

    def render(points: Tensor) -> Tensor:
        return splat_points(points.repeat_interleave(h, 0), cameras, s, point_size, kind).view(b, h, s, s)

    pred_images = render(pred_points)
    if target_images is None:
        with torch.no_grad():
            target_images = render(gt_points)
    elif target_images.shape != (b, h, s, s):
        raise ValueError(
            f"target_images must be (B, H, S, S) = {(b, h, s, s)}, got {tuple(target_images.shape)}; "
            "pass the target_images of an earlier call with the same views and render_size"
        )
    target_images = target_images.detach()
    per_view = (pred_images - target_images).pow(2).mean(dim=(-2, -1))  # (B, H)
    loss = per_view.sum(dim=1).mean()  # Eq. 6: sum over the H views
    return Prior3DLoss(loss=loss, pred_images=pred_images, target_images=target_images)
