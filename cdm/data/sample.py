"""The common sample format every data set produces, and its batched form.

Images are channel-first float tensors in [0, 1] at ``S × S`` (``data.image_size``), in the pixel
layout of :mod:`cdm.cameras` (row 0 at the top, column 0 at NDC +X). Points and cameras are in the
data set's frame for the object's category (:mod:`cdm.normalise`), fixed per data set, not per object.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cdm.cameras import Cameras

__all__ = ["Batch", "ConditionViews", "Sample", "collate"]


@dataclass(frozen=True)
class ConditionViews:
    """Extra condition images of a training sample (``data.condition_views``, supplementary Table 8).

    Attributes (``K`` views; a batch adds a leading ``B``):
        image: ``(K, 3, S, S)`` RGB in [0, 1] (renderings or generated images).
        mask: ``(K, 1, S, S)`` foreground of the object from that view, in {0, 1}.
        prior_2d: ``(K, C2, S, S)`` 2D-prior channels of each image (as the input's, Eq. 7).
        camera: batch ``(K,)``, the camera each image was taken from.
        valid: ``(K,)`` bool, False for views left out of this sample (a random count per sample).
    """

    image: Tensor
    mask: Tensor
    prior_2d: Tensor
    camera: Cameras
    valid: Tensor

    def to(self, device: torch.device | str) -> ConditionViews:
        return ConditionViews(self.image.to(device), self.mask.to(device), self.prior_2d.to(device),
                              self.camera.to(device), self.valid.to(device))

    @staticmethod
    def stack(views: list[ConditionViews]) -> ConditionViews:
        return ConditionViews(*(torch.stack([getattr(v, f) for v in views]) for f in ("image", "mask", "prior_2d")),
                              Cameras.stack([v.camera for v in views]), torch.stack([v.valid for v in views]))


@dataclass(frozen=True)
class Sample:
    """One object seen from one input view.

    Attributes:
        image: ``(3, S, S)`` RGB in [0, 1].
        mask: ``(1, S, S)`` foreground in {0, 1}.
        depth: ``(1, S, S)`` view depth (world units, 0 on background), or None when unknown.
        prior_2d: ``(C2, S, S)`` 2D-prior channels (contour or depth, Eq. 7); ``C2 = 0`` for none.
        camera: input camera, batch shape ``()``.
        view_cameras: the H prior-view cameras (batch shape ``(H,)``), view 0 = input view.
        points: ``(N, 3)`` ground-truth cloud, world units.
        category: category name.
        object_id: stable id of the object (same across its views and runs).
        conditions: extra condition views (training with ``data.condition_views``), else None.
    """

    image: Tensor
    mask: Tensor
    depth: Tensor | None
    prior_2d: Tensor
    camera: Cameras
    view_cameras: Cameras
    points: Tensor
    category: str
    object_id: str
    conditions: ConditionViews | None = None


@dataclass(frozen=True)
class Batch:
    """``B`` samples stacked; tensor shapes gain a leading ``B``; cameras are ``(B,)`` and ``(B, H)``."""

    image: Tensor
    mask: Tensor
    depth: Tensor | None
    prior_2d: Tensor
    camera: Cameras
    view_cameras: Cameras
    points: Tensor
    category: tuple[str, ...]
    object_id: tuple[str, ...]
    conditions: ConditionViews | None = None

    def __len__(self) -> int:
        return self.points.shape[0]

    def to(self, device: torch.device | str) -> Batch:
        return Batch(
            image=self.image.to(device),
            mask=self.mask.to(device),
            depth=None if self.depth is None else self.depth.to(device),
            prior_2d=self.prior_2d.to(device),
            camera=self.camera.to(device),
            view_cameras=self.view_cameras.to(device),
            points=self.points.to(device),
            category=self.category,
            object_id=self.object_id,
            conditions=None if self.conditions is None else self.conditions.to(device),
        )


def collate(samples: list[Sample]) -> Batch:
    """Stack samples into a :class:`Batch` (use as a DataLoader ``collate_fn``)."""
    depths = [s.depth for s in samples]
    return Batch(
        image=torch.stack([s.image for s in samples]),
        mask=torch.stack([s.mask for s in samples]),
        depth=None if any(d is None for d in depths) else torch.stack(depths),
        prior_2d=torch.stack([s.prior_2d for s in samples]),
        camera=Cameras.stack([s.camera for s in samples]),
        view_cameras=Cameras.stack([s.view_cameras for s in samples]),
        points=torch.stack([s.points for s in samples]),
        category=tuple(s.category for s in samples),
        object_id=tuple(s.object_id for s in samples),
        conditions=None
        if any(s.conditions is None for s in samples)
        else ConditionViews.stack([s.conditions for s in samples]),
    )
