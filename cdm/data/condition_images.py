"""Extra condition images (``data.condition_views``, ``data.input_source``; supplementary Table 8).

The paper's "ControlNet" section projects more images than the input onto the points during
training: renderings of the object from other views (GT), or images a fine-tuned ControlNet
generated from point-cloud renderings of those views; sampling sees only the input image (the
train/sample mismatch it calls *model learning drift*). Here the extra views are views 1…k of
k + 1 cameras evenly spaced in azimuth around the input view (same elevation, distance and focal),
each projected onto ``x_t`` like the input (:mod:`cdm.model.network`).

Generated images come from a folder (``data.condition_folder``), written offline by the user's
generator from ``python -m cdm.tools.export_views`` output (same names):

- rendered kinds (``procedural``, ``meshes``): ``<condition_folder>/<object_id>/<round>/<view>.png``
  — ``view`` 0 is the input view (used with ``data.input_source: folder``), 1…k the extra views;
  ``round`` is the training view round (0, 1, … R−1 for as many rounds as were generated; round ``r``
  uses ``r mod R``; held-out samples use round 0);
- captured kinds (``shapenet_r2n2``, ``co3d``): ``<condition_folder>/<object_id>/<position>.png`` —
  one image per input view, ``position`` its place in the object's sequence (as ``export_views``
  names the crops). The extra views of a sample are k of the object's input views evenly spaced
  through them from the input view.

RGB, any size (resized to ``S``). Masks and cameras stay those of the GT view: the paper's
generated images keep the shape of their point-cloud rendering. ``data.condition_grey`` turns the
generated images grey (ITU-R BT.601 luma in all three channels).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from cdm.cameras import Cameras
from cdm.data.priors2d import prior_2d_channels
from cdm.data.sample import ConditionViews
from cdm.io.images import read_image
from cdm.paths import input_path

__all__ = ["ConditionImages", "condition_views", "grey"]

_FIELD = "data.condition_folder"
_LUMA = (0.299, 0.587, 0.114)


def grey(image: Tensor) -> Tensor:
    """``(3, S, S)`` RGB → ``(3, S, S)`` with BT.601 luma in every channel."""
    luma = sum(w * image[c] for c, w in enumerate(_LUMA))
    return luma[None].expand(3, -1, -1).contiguous()


class ConditionImages:
    """Reader of a folder of generated condition images (layout in the module docstring)."""

    def __init__(self, folder: str | Path, grey_images: bool = False, by_position: bool = False):
        self.folder = input_path(folder)
        self.grey = grey_images
        self.by_position = by_position
        if not self.folder.is_dir():
            raise ValueError(
                f"{_FIELD}: {self.folder} is not a folder; write <object_id>/<round>/<view>.png images there"
            )
        self._rounds: dict[str, int] = {}

    def rounds(self, object_id: str) -> int:
        """``R``: consecutive round folders ``0 … R−1`` of an object (0 if it has none)."""
        if object_id not in self._rounds:
            r = 0
            while (self.folder / object_id / str(r)).is_dir():
                r += 1
            self._rounds[object_id] = r
        return self._rounds[object_id]

    def require(self, object_ids: Iterable[str]) -> None:
        """``ValueError`` naming the first object id without round 0."""
        ids = list(object_ids)
        missing = [o for o in ids if not (self.folder / o).is_dir() or (not self.by_position and self.rounds(o) == 0)]
        if missing:
            expected = "<position>.png" if self.by_position else "0/<view>.png"
            raise ValueError(f"{_FIELD}: no images for object id {missing[0]!r} ({len(missing)} of {len(ids)} objects "
                             f"missing; expected {self.folder / missing[0]}/{expected})")

    def read(self, object_id: str, view_round: int, view: int, size: int) -> Tensor:
        """``(3, S, S)`` RGB in [0, 1] of one generated image (grey if asked)."""
        rounds = self.rounds(object_id)
        if rounds == 0:
            raise ValueError(f"{_FIELD}: no images for object id {object_id!r}")
        return self._image(self.folder / object_id / str(view_round % rounds) / f"{view}.png", size)

    def read_position(self, object_id: str, position: int, size: int) -> Tensor:
        """``(3, S, S)`` RGB in [0, 1] of the generated image of a captured object's input view."""
        return self._image(self.folder / object_id / f"{position}.png", size)

    def _image(self, path: Path, size: int) -> Tensor:
        raw = read_image(path, cv2.IMREAD_COLOR, _FIELD)
        if raw is None:
            raise ValueError(f"{_FIELD}: cannot read {path} as an image")
        rgb = cv2.cvtColor(cv2.resize(raw, (size, size), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
        image = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float() / 255.0
        return grey(image) if self.grey else image


def condition_views(views: list, generated: list[Tensor] | None, shown: int, prior_2d: str) -> ConditionViews:
    """The :class:`ConditionViews` of one training sample.

    Args:
        views: the k GT views (anything with ``image``, ``mask``, ``depth`` and ``camera`` as in
            :class:`~cdm.data.views.Rendering`; ``depth`` is what the depth prior reads).
        generated: the k generated images that replace the GT ones (``data.condition_source: folder``), or None.
        shown: how many of the k views this sample uses (the rest are marked invalid).
        prior_2d: ``priors.prior_2d``, computed on each condition image as on the input.
    """
    rgb = [v.image for v in views] if generated is None else generated
    return ConditionViews(
        image=torch.stack(rgb),
        mask=torch.stack([v.mask for v in views]),
        prior_2d=torch.stack([prior_2d_channels(prior_2d, im, v.mask, v.depth) for im, v in zip(rgb, views)]),
        camera=Cameras.stack([v.camera for v in views]),
        valid=torch.arange(len(views)) < shown,
    )
