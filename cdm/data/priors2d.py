"""2D prior maps of the input image (paper §3.3, Eq. 7), made on the data side with each sample.

They are extra image channels concatenated with the image features before these are projected onto
the points (Eq. 7, ``F_I ⊕ F_I*``): a contour map (ShapeNet) or a depth map (Co3D). Images are
``(3, S, S)`` RGB in [0, 1] in the pixel layout of :mod:`cdm.cameras`. No gradient flows through
them: they are inputs, like the image.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import Tensor

from cdm.config import Prior2D
from cdm.registry import PRIORS_2D, load

__all__ = [
    "PRIOR_2D_CHANNELS", "contour_map", "contour_prior", "depth_prior", "depth_prior_from_map", "no_prior",
    "prior_2d_channels",
]

PRIOR_2D_CHANNELS = {kind: entry.channels for kind, entry in PRIORS_2D.items()}
"""Channels each ``priors.prior_2d`` kind adds to the conditioning image features (Eq. 7), from
:data:`cdm.registry.PRIORS_2D`."""


def contour_map(image: Tensor, low_threshold: float = 100.0, high_threshold: float = 200.0) -> Tensor:
    """Binary contour map of one image with OpenCV's Canny detector.

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


def no_prior(image: Tensor, mask: Tensor, depth: Tensor | None) -> Tensor:
    """``priors.prior_2d=none``: ``(0, S, S)``, no channel."""
    return image.new_zeros(0, *image.shape[1:])


def contour_prior(image: Tensor, mask: Tensor, depth: Tensor | None) -> Tensor:
    """``priors.prior_2d=contour`` (ShapeNet in the paper): :func:`contour_map` of the image, ``(1, S, S)``."""
    return contour_map(image)


def depth_prior(image: Tensor, mask: Tensor, depth: Tensor | None) -> Tensor:
    """``priors.prior_2d=depth`` (Co3D in the paper): :func:`depth_prior_from_map` of the sample's depth map.

    That map comes from the data (a renderer or a sensor), not from a monocular estimate of the image as
    in the paper (DINOv2), so it is a cleaner, privileged prior: results with it are an upper bound.
    """
    if depth is None:
        raise ValueError(
            "priors.prior_2d='depth' needs a depth map: this sample has none; use a data set that provides "
            "depth or set priors.prior_2d='contour'"
        )
    return depth_prior_from_map(depth.to(image.dtype), mask)


def prior_2d_channels(
    kind: Prior2D, image: Tensor, mask: Tensor, depth: Tensor | None
) -> Tensor:
    """The 2D-prior channels of one sample (Eq. 7) by the maker :data:`cdm.registry.PRIORS_2D` names for ``kind``.

    Args:
        kind: ``priors.prior_2d``.
        image: ``(3, S, S)`` RGB in [0, 1].
        mask: ``(1, S, S)`` foreground in {0, 1}.
        depth: ``(1, S, S)`` view depth (world units, 0 on background) or None.
    Returns:
        ``(C, S, S)`` with ``C = PRIOR_2D_CHANNELS[kind]``, dtype and device of ``image``.
    """
    if kind not in PRIORS_2D:
        raise ValueError(f"priors.prior_2d must be one of {sorted(PRIORS_2D)}, got {kind!r}")
    return load(PRIORS_2D[kind].builder)(image, mask, depth)
