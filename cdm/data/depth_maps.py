"""Estimated depth maps from a folder (``priors.depth_source: maps``): the paper's depth 2D prior.

The paper estimates the depth of the input image with DINOv2; any estimator (DINOv2's depth head,
Depth Anything, ZoeDepth, …) runs offline on the user's side and writes one map per input view:

``<priors.depth_maps>/<object_id>/<position>.npy`` — a 2-D float array ``(h, w)`` of the input
crop exactly as the data set yields it (``python -m cdm.tools.export_views`` writes those crops
as ``<object_id>/<position>.png``, same names), any resolution (resized nearest-neighbour to
``data.image_size``); ``position`` is the view's place in the object's sequence; 0 or non-finite =
unknown.

Scale and shift: the depth prior is normalised per image to [0, 1] on the object by its own
nearest and farthest foreground values (:func:`cdm.data.priors2d.depth_prior_from_map`), so a map is used
up to any positive scale and any shift — relative depth needs no alignment with the ground truth,
and none is done. Disparity maps (larger = nearer; ``priors.depth_maps_disparity``) are inverted
first (``1 / d``); that is exact for disparity proportional to inverse depth, an approximation for
affine-invariant disparity with a non-zero shift.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from cdm.io.arrays import load_npy
from cdm.io.json import read_json
from cdm.paths import input_path

__all__ = ["ESTIMATOR_FILE", "DepthMaps"]

_FIELD = "priors.depth_maps"
ESTIMATOR_FILE = "estimator.json"
"""Written beside the maps by ``python -m cdm.tools.estimate_depth``: ``{"model": ..., "disparity": bool}``."""


class DepthMaps:
    """Reader of a depth-map folder (layout in the module docstring).

    Args:
        folder: ``priors.depth_maps``.
        disparity: ``priors.depth_maps_disparity``.
    """

    def __init__(self, folder: str | Path, disparity: bool = False):
        self.folder = input_path(folder)
        self.disparity = disparity
        if not self.folder.is_dir():
            raise ValueError(f"{_FIELD}: {self.folder} is not a folder; write <object_id>/<position>.npy maps there")
        record = self.folder / ESTIMATOR_FILE
        if record.is_file():
            said = read_json(record, _FIELD)
            written = said.get("disparity") if isinstance(said, dict) else None
            if written is not disparity:
                raise ValueError(
                    f"priors.depth_maps_disparity: {self.folder} holds {'disparity' if written else 'depth'} "
                    f"maps ({record}); set priors.depth_maps_disparity={str(bool(written)).lower()}"
                )

    def require(self, object_ids: Iterable[str]) -> None:
        """``ValueError`` naming the first object id without a folder of maps."""
        ids = list(object_ids)
        missing = [o for o in ids if not (self.folder / o).is_dir()]
        if missing:
            raise ValueError(f"{_FIELD}: no maps for object id {missing[0]!r} ({len(missing)} of {len(ids)} objects "
                             f"missing; expected {self.folder / missing[0]}/<position>.npy)")

    def read(self, object_id: str, position: int, size: int) -> Tensor:
        """``(1, S, S)`` float32 view depth (larger = farther, 0 = unknown) of one input view."""
        path = self.folder / object_id / f"{position}.npy"
        if not path.exists():
            raise ValueError(f"{_FIELD}: {path} does not exist (object {object_id!r}, sequence position {position})")
        raw = load_npy(path, _FIELD)
        if raw.ndim != 2 or not np.issubdtype(raw.dtype, np.floating) or min(raw.shape) < 1:
            raise ValueError(f"{_FIELD}: {path} must be a 2-D float array (h, w), got {raw.dtype} {raw.shape}")
        depth = np.where(np.isfinite(raw) & (raw > 0), raw, 0.0).astype(np.float32)
        if self.disparity:
            depth = np.divide(1.0, depth, out=np.zeros_like(depth), where=depth > 0)
        depth = cv2.resize(depth, (size, size), interpolation=cv2.INTER_NEAREST)
        return torch.from_numpy(depth)[None]
