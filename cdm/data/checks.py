"""Does each ground-truth cloud sit where its own images say it is? The check every data kind passes.

Projected with a sample's own camera, the ground-truth cloud must land on the sample's mask: a cloud
in the wrong frame (ShapeNet's PC15k v2 frame against R2N2's v1 cameras), a mirrored camera or a wrong
distance scale puts a large share of it off the silhouette, silently, for training and evaluation
alike. :func:`check_masks` measures, for one object, the share of its points inside the mask on every
view that has one (all input views of a captured data set; the first view rounds of a rendered one).
An object passes when every view reaches :data:`MIN_INSIDE`; thin parts at the mask's edge and
resampling keep real data a little below 1 (Co3D: 0.92–0.97 measured on published data). The share
does not depend on the data set's frame (:mod:`cdm.normalise` moves cloud and cameras by one
similarity, which changes no projection), so those numbers hold in every frame; on the procedural
eval set of the ``local`` profile (128 objects) it is 0.9996 (box frame) and 0.9999 (fixed frames) on average.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from cdm.cameras import Cameras, ndc_to_pixel, project_points
from cdm.data.captured import CapturedDataset
from cdm.data.views import ObjectDataset

__all__ = ["MIN_INSIDE", "MaskCheck", "check_masks", "inside_mask"]

MIN_INSIDE = 0.9
"""Least share of ground-truth points inside the mask, on every view, for an object to pass."""

Perturb = Callable[[Tensor, Cameras], tuple[Tensor, Cameras]]
"""``(points (N, 3), camera (batch ()))`` → the same, altered: a negative control of the check."""


class MaskCheck(NamedTuple):
    """Share of an object's ground-truth points inside the mask, per view with a mask."""

    object_id: str
    fractions: Tensor
    """``(V,)`` in [0, 1]."""

    @property
    def passed(self) -> bool:
        return bool((self.fractions >= MIN_INSIDE).all())


def inside_mask(points: Tensor, camera: Cameras, mask: Tensor) -> float:
    """Share of ``points`` ``(N, 3)`` (world units) whose projection by ``camera`` (batch ``()``) lands
    on a foreground pixel of ``mask`` ``(1, S, S)``; points outside the image count as outside."""
    one = Cameras(camera.R[None], camera.T[None], camera.focal[None], camera.principal[None])
    size = mask.shape[-1]
    col, row = ndc_to_pixel(project_points(points[None].float(), one)[0, :, :2], size).round().long().unbind(-1)
    ok = (col >= 0) & (col < size) & (row >= 0) & (row < size)
    hits = torch.zeros(len(col))
    hits[ok] = mask[0, row[ok], col[ok]].float()
    return float(hits.mean())


def _views_with_masks(dataset: ObjectDataset, index: int, rounds: int) -> list[tuple[Cameras, Tensor]]:
    if isinstance(dataset, CapturedDataset):
        views = [dataset.view(index, v) for v in range(len(dataset.surface(index).views))]
        return [(v.camera, torch.from_numpy(v.mask > 127)[None]) for v in views]
    samples = [dataset.sample(index, r) for r in range(rounds if dataset.split == "train" else 1)]
    return [(s.camera, s.mask) for s in samples]


def check_masks(dataset: ObjectDataset, index: int, perturb: Perturb | None = None, rounds: int = 3) -> MaskCheck:
    """Object ``index``'s ground truth against every view with a mask (``rounds`` view rounds of a
    rendered training split). ``perturb`` alters cloud and camera first, for negative controls."""
    points = dataset.surface(index).cloud
    fractions = []
    for camera, mask in _views_with_masks(dataset, index, rounds):
        p, c = (points, camera) if perturb is None else perturb(points, camera)
        fractions.append(inside_mask(p, c, mask))
    return MaskCheck(dataset.objects[index].object_id, torch.tensor(fractions))
