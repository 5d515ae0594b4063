"""Frames of the data: one similarity per data set and category, never one per object.

Every cloud and camera a data set hands out is expressed in its :class:`Frame`, ``x' = (x − c)·s``,
with ``c`` and ``s`` fixed by the data set and the category alone: nothing about one object's ground
truth reaches its own input cameras, and the metrics (:mod:`cdm.metrics`, which centre each cloud on
its own mean) score prediction and ground truth in these units as they are, with no per-object factor.

- ``shapenet_r2n2``: BDM's global normalisation (``experiments/dataset/shapenet_r2n2.py`` in
  mlpc-ucsd/BDM, ``normalize_per_shape=False``, as PointFlow): ``x' = (x_v1 − μ)/σ``, μ the mean point
  and σ the standard deviation (n − 1) of every coordinate of every full PC15k cloud of the category
  after the v2 → v1 map (:func:`bdm_frame`). BDM takes μ and σ of the split it loads, its test split
  included; here both splits take the **training** split's (PointFlow's ``get_datasets`` passes the
  training set's ``all_points_mean``/``all_points_std`` to its test set), so no held-out cloud moves
  another's frame. Cameras follow by the exact similarity (:meth:`Frame.translation`); BDM's
  ``build_camera_from_R2N2`` forms ``R·σ`` and ``T + μ@R/σ``, which equals it only when μ = 0.
- ``co3d``: PC²'s frame and units, the sequence's own world frame times PC²'s ``scale_factor = 1.0``
  (``experiments/config/structured.py``; ``projection_model.py`` scales points and ``camera.T`` by it):
  :data:`IDENTITY`.
- ``procedural``: :data:`cdm.data.procedural.FRAMES`, a box per category measured once on the
  generator (every object it makes fits ``[-1, 1]³``).
- ``meshes``: the union bounding box of the category's training meshes (:func:`box_frame`), read from
  the files alone.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

__all__ = ["FRAME_VERSION", "IDENTITY", "Frame", "bdm_frame", "bdm_moments", "box_frame"]

FRAME_VERSION = 2
"""Raised whenever the frames change (1: each object's own bounding box); part of every data set's and
evaluation set's fingerprint, so runs in different frames never compare as equal."""


class Frame(NamedTuple):
    """The similarity ``x' = (x − centre)·scale`` from a data set's published units to the ones it hands out."""

    centre: tuple[float, float, float]
    """``c``, published units."""
    scale: float
    """``s``, handed-out units per published unit."""

    def points(self, x: np.ndarray) -> Tensor:
        """``(P, 3)`` float32 ``x'`` of published points ``x`` ``(P, 3)`` (summed in float64)."""
        return torch.from_numpy((np.asarray(x, dtype=np.float64) - np.asarray(self.centre)) * self.scale).float()

    def translation(self, R: Tensor, T: Tensor) -> Tensor:
        """``T'`` ``(F, 3)`` of world→view cameras ``X = x @ R + T`` (``R (F, 3, 3)``, ``T (F, 3)``, published
        world) in this frame: ``x @ R + T = (x'/s + c) @ R + T``, and scaling the view frame by ``s``
        changes no projection, so R stays and ``T' = s·(c @ R + T)``; view depths come out in ``x'`` units."""
        c = torch.tensor(self.centre, dtype=R.dtype)
        return self.scale * ((c[None, None, :] @ R)[:, 0, :] + T)


IDENTITY = Frame((0.0, 0.0, 0.0), 1.0)
"""The published units unchanged (Co3D, as PC²)."""


def bdm_moments(clouds: Iterable[np.ndarray]) -> tuple[np.ndarray, float]:
    """Mean point ``(3,)`` and σ of BDM's global normalisation over ``clouds`` (each ``(P, 3)``): the mean of
    all points (``all_points.reshape(-1, 3).mean(0)``) and the std (n − 1) of all their coordinates
    flattened into one vector (``all_points.reshape(-1).std()``). Sums in float64, one cloud at a time."""
    count, total, squares, mean = 0, 0.0, 0.0, np.zeros(3)
    for cloud in clouds:
        c = np.asarray(cloud, dtype=np.float64)
        count += c.size
        total += float(c.sum())
        squares += float(np.square(c).sum())
        mean += c.sum(0)
    if count < 2:
        raise ValueError("bdm_moments needs at least two coordinates")
    return mean / (count // 3), float(np.sqrt(max(squares - total * total / count, 0.0) / (count - 1)))


def bdm_frame(clouds: Iterable[np.ndarray]) -> Frame:
    """BDM's global normalisation over ``clouds`` (published units, each ``(P, 3)``): ``Frame(μ, 1/σ)``."""
    mean, std = bdm_moments(clouds)
    return Frame(tuple(float(v) for v in mean), 1.0 / std)


def box_frame(bounds: Iterable[np.ndarray]) -> Frame:
    """The frame mapping the union of bounding boxes ``bounds`` (each ``(2, 3)``: min and max corner)
    onto ``[-1, 1]`` along its longest side: centre the union box's, scale 1 / its largest half-extent."""
    boxes = np.stack([np.asarray(b, dtype=np.float64) for b in bounds])
    lo, hi = boxes[:, 0].min(0), boxes[:, 1].max(0)
    half = float((hi - lo).max() / 2)
    if not (np.isfinite(half) and half > 0):
        raise ValueError("box_frame needs bounding boxes of positive, finite size")
    return Frame(tuple(float(v) for v in (lo + hi) / 2), 1.0 / half)
