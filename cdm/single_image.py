"""One photo made into the batch the network samples from: resized, its mask found, seen by a look-at camera.

``cdm-lab reconstruct`` (a file) and the MLflow model of a sweep trial (:mod:`sweeps.mlflow_model`, an array)
share it, so a photo becomes the same condition either way. The camera is given as a :class:`LookAt` in
:mod:`cdm.cameras`' conventions (on a sphere around the object, looking at its centre, world +Y up).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
import torch

from cdm.cameras import look_at_cameras, orbit_cameras
from cdm.config import Config
from cdm.data.priors2d import prior_2d_channels
from cdm.data.sample import Batch, Sample, collate

__all__ = ["DEFAULT_VIEW", "MIN_IMAGE_SIDE", "LookAt", "image_batch", "image_tensors"]

MIN_IMAGE_SIDE = 16
"""Smallest input image side accepted, in pixels (``data.image_size``'s lower bound)."""

_BACKGROUND_GAP = 0.06
"""Summed RGB difference (of [0, 1] values) from the corners' median above which a pixel is the object."""


class LookAt(NamedTuple):
    """The input camera (:func:`cdm.cameras.look_at_cameras`): on a sphere around the object, looking at it."""

    elev: float = 20.0
    """Elevation in degrees, towards world +Y."""
    azim: float = 0.0
    """Azimuth in degrees about world +Y; 0 puts the camera on world +Z."""
    dist: float = 3.5
    """Distance from the object's centre, in world units."""
    focal: float = 2.0
    """Focal length in NDC units (2 ↔ a 53° field of view)."""


DEFAULT_VIEW = LookAt()
"""The camera ``reconstruct`` and the MLflow model assume when none is given."""


def image_tensors(pixels: np.ndarray, size: int, field: str, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """RGB ``(3, S, S)`` in [0, 1] and mask ``(1, S, S)`` in {0, 1} of an image at ``S = size``.

    Args:
        pixels: ``(H, W)`` grey, ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA, 8 or 16 bits (scaled by its own
            full scale); the mask is alpha above half scale if present, else the pixels unlike the median of
            the four corners (the background of a product photo or a rendering).
        size: the side the network sees (``data.image_size``), resized with area averaging.
        field, name: the input and the image named in an error (``--image``, the file).
    Raises:
        ValueError: another pixel type, channel count, or a side under :data:`MIN_IMAGE_SIDE`.
    """
    if pixels.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{field}: {name} holds {pixels.dtype} pixels; give an 8- or 16-bit image")
    if pixels.ndim not in (2, 3) or (pixels.ndim == 3 and pixels.shape[2] not in (3, 4)):
        raise ValueError(f"{field}: {name} has shape {tuple(pixels.shape)}; give H×W grey, H×W×3 RGB or H×W×4 RGBA")
    height, width = pixels.shape[:2]
    if min(height, width) < MIN_IMAGE_SIDE:
        raise ValueError(f"{field}: {name} is {width}×{height} pixels; give at least {MIN_IMAGE_SIDE}×{MIN_IMAGE_SIDE} "
                         f"(the model sees {size}×{size})")
    full_scale = float(np.iinfo(pixels.dtype).max)  # 255 or 65535: a 16-bit PNG is not divided by 255
    raw = cv2.resize(pixels, (size, size), interpolation=cv2.INTER_AREA)
    if raw.ndim == 2:
        raw = np.repeat(raw[..., None], 3, axis=2)
    rgb = raw[..., :3].astype(np.float32) / full_scale
    if raw.shape[2] == 4:
        mask = (raw[..., 3] > full_scale / 2).astype(np.float32)
    else:
        background = np.median(np.stack([rgb[0, 0], rgb[0, -1], rgb[-1, 0], rgb[-1, -1]]), axis=0)
        mask = (np.abs(rgb - background).sum(-1) > _BACKGROUND_GAP).astype(np.float32)
    return torch.from_numpy(rgb).permute(2, 0, 1).contiguous(), torch.from_numpy(mask)[None]


def image_batch(image: torch.Tensor, mask: torch.Tensor, cfg: Config, view: LookAt = DEFAULT_VIEW,
                object_id: str = "image") -> Batch:
    """A batch of one sample (``B = 1``) seeing ``image`` ``(3, S, S)`` with ``mask`` ``(1, S, S)`` from
    ``view``; its 2D-prior channels as ``cfg.priors.prior_2d`` makes them, no depth, no ground truth (zeros)."""
    elev, azim, dist = (torch.tensor([float(v)]) for v in (view.elev, view.azim, view.dist))
    sample = Sample(
        image=image,
        mask=mask,
        depth=None,
        prior_2d=prior_2d_channels(cfg.priors.prior_2d, image, mask, None),
        camera=look_at_cameras(elev, azim, dist, view.focal)[0],
        view_cameras=orbit_cameras(elev, azim, dist, 1, view.focal)[0],
        points=torch.zeros(cfg.data.num_points, 3),
        category="unknown",
        object_id=object_id,
    )
    return collate([sample])
