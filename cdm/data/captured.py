"""Data sets of captured objects: images with known cameras and a ground-truth cloud (ShapeNet, Co3D).

Unlike :mod:`cdm.data.views`, nothing is rendered here: each object brings

- a **cloud** and cameras in the data set's frame for its category (:mod:`cdm.normalise`: BDM's global
  normalisation on ShapeNet, Co3D's own world units as PC²), never fitted to the object itself;
- a **sequence** of cameras, the object's own views in capture order (a Co3D video, or R2N2's 24
  renderings sorted by azimuth); the H prior views of the 3D constraint are taken from it at even
  spacing starting at the input view (:func:`cdm.cameras.select_sequence_views`, the paper's procedure);
- **input views** of the split: positions in that sequence whose image, mask and (if any) depth decode
  to ``S × S`` together with the camera of that crop.

A subclass reads the published files (the ``_raw_*`` hooks). A ``data.root`` made by
``python -m cdm prepare`` holds the same records as shards (:mod:`cdm.data.cache`); both forms give
the same tensors when the shards were prepared at ``data.image_size``. Raw views are kept decoded in
a process-wide cache (:data:`cdm.data.cache.DECODED`), so the cells of a sweep that run one after
another in a worker process decode each image once.
"""

from __future__ import annotations

import hashlib
from abc import abstractmethod
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
import torch
from torch import Tensor

from cdm.cameras import Cameras, select_sequence_views
from cdm.config import Config, DataConfig
from cdm.data.cache import DECODED, ObjectRecord, PreparedRoot, ViewImages, is_prepared
from cdm.data.condition_images import condition_views
from cdm.data.depth_maps import DepthMaps
from cdm.data.lru import ByteLRU
from cdm.data.priors2d import prior_2d_channels
from cdm.data.sample import ConditionViews, Sample
from cdm.data.views import ObjectDataset, Rendering, Shape, Split, select_categories
from cdm.registry import PRIORS_2D

__all__ = [
    "MAX_CLOUD_POINTS",
    "CapturedDataset",
    "ObjectRecord",
    "cap_cloud",
    "data_root",
    "resize_view",
]

MAX_CLOUD_POINTS = 65_536
"""Points kept of a published cloud (a fixed subset per object, independent of ``data.seed``): the
paper needs 16,384 at most, and a cap keeps Co3D's larger clouds and the prepared shards small."""


def data_root(cfg: Config, expected: str) -> Path:
    """``data.root`` as an existing folder; ValueError naming it and the ``expected`` layout otherwise."""
    if cfg.data.root is None:
        raise ValueError(f"data.root must name the data set folder when data.kind={cfg.data.kind!r} ({expected})")
    root = Path(cfg.data.root).expanduser()
    if not root.is_dir():
        raise ValueError(f"data.root: {root} does not exist or is not a folder; expected {expected}")
    return root


def cap_cloud(points: np.ndarray, object_id: str) -> np.ndarray:
    """At most :data:`MAX_CLOUD_POINTS` of ``points`` ``(P, 3)``, a subset fixed by ``object_id`` alone."""
    if len(points) <= MAX_CLOUD_POINTS:
        return points
    seed = int.from_bytes(hashlib.sha256(object_id.encode()).digest()[:8], "little")
    keep = np.random.default_rng(seed).choice(len(points), MAX_CLOUD_POINTS, replace=False)
    return points[np.sort(keep)]


def resize_view(view: ViewImages, size: int) -> ViewImages:
    """``view`` at ``size`` pixels: the crop and so the camera are unchanged (NDC spans the frame)."""
    if view.image.shape[0] == size:
        return view
    area = size < view.image.shape[0]
    image = cv2.resize(view.image, (size, size), interpolation=cv2.INTER_AREA if area else cv2.INTER_LINEAR)
    mask = cv2.resize(view.mask, (size, size), interpolation=cv2.INTER_AREA if area else cv2.INTER_LINEAR)
    mask = np.where(mask > 127, 255, 0).astype(np.uint8)
    depth = None
    if view.depth is not None:  # nearest: blending across the silhouette would invent depths
        depth = cv2.resize(view.depth.astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST).astype(
            np.float16
        )
    return view._replace(image=image, mask=mask, depth=depth)


# Purposes of the per-object random streams (as in cdm.data.views: spawn keys of the object's seed).
_STREAM_CLOUD, _STREAM_VIEW = 1, 3


class CapturedDataset(ObjectDataset):
    """A ``Dataset[Sample]`` of captured objects, read from the published layout or a prepared root.

    An :class:`~cdm.data.views.ObjectDataset` whose objects are read, not rendered: :meth:`surface`
    and :meth:`sample` take the place of the mesh pipeline. Views: ``val`` always shows an object's
    view 0; ``train`` draws one of the object's input views per view round (a pure function of
    ``data.seed``, the object and the round).
    """

    layout: ClassVar[str]
    """The published layout in words, for error messages."""
    captured: ClassVar[bool] = True
    protocol_fields: ClassVar[tuple[str, ...]] = ()
    """``data`` fields that change what ``python -m cdm prepare`` stores: a prepared root records them
    (:meth:`protocol`) and is read only with the same values."""

    def __init__(self, cfg: Config, split: Split, cache_bytes: int = 512 * 2**20):
        self.published = "train" if split == "train" else cfg.data.eval_split
        """The published split this one reads (``val`` reads ``data.eval_split``)."""
        self.root = data_root(cfg, self.layout)
        self.prepared = PreparedRoot.open(self.root, self.kind) if is_prepared(self.root) else None
        if self.prepared is not None:
            self._check_protocol(self.prepared.manifest.get("protocol", {}), cfg)
        chosen = self.categories(cfg)
        self._refs = (
            self.prepared.objects(self.published, chosen) if self.prepared is not None else self._raw_index(chosen)
        )
        if not self._refs:
            raise ValueError(
                f"data.root: {self.root} has no objects of categories {list(chosen)} in split {self.published!r}"
            )
        super().__init__(cfg, split, cache_bytes)
        p = cfg.priors
        estimated = PRIORS_2D[p.prior_2d].reads_depth and p.depth_source == "maps"
        self.depth_maps = (
            DepthMaps(p.depth_maps, p.depth_maps_disparity) if estimated and p.depth_maps is not None else None
        )
        self.shard_depths = estimated and p.depth_maps is None
        if self.shard_depths and (self.prepared is None or not self.prepared.has_estimated_depths):
            raise ValueError(
                f"priors.depth_maps: not set and data.root {self.root} holds no estimated depth maps; give the folder "
                "of maps, or prepare data.root with `python -m cdm prepare ... --depth-maps DIR`"
            )

    @classmethod
    def protocol(cls, cfg: Config) -> dict[str, Any]:
        """``{"data.<field>": value}`` of :attr:`protocol_fields` in ``cfg`` (what a prepared root records)."""
        return {f"data.{name}": getattr(cfg.data, name) for name in cls.protocol_fields}

    def _check_protocol(self, stored: dict[str, Any], cfg: Config) -> None:
        """ValueError naming the first protocol field whose value differs from the prepared root's
        (a root prepared before it was recorded holds the field's default)."""
        for field, value in self.protocol(cfg).items():
            prepared = stored.get(field, DataConfig.model_fields[field.removeprefix("data.")].default)
            if prepared != value:
                raise ValueError(
                    f"{field}: {value!r}, but {self.root} was prepared with {prepared!r}; prepare the published "
                    f"data set again with --set {field}={value} into another --out, or set it to match"
                )

    @classmethod
    def categories(cls, cfg: Config) -> tuple[str, ...]:
        """Categories of this data set selected by ``cfg.data.categories`` (ValueError if unknown)."""
        root = data_root(cfg, cls.layout)
        if is_prepared(root):
            available = PreparedRoot.open(root, cls.kind).categories
            return select_categories(cls._canonical(cfg.data.categories), available, f"prepared root {root}")
        return select_categories(cls._canonical(cfg.data.categories), cls._raw_categories(root), f"data.root {root}")

    @classmethod
    def _canonical(cls, names: tuple[str, ...]) -> tuple[str, ...]:
        """Category names as the data set spells them (ShapeNet also takes synset ids)."""
        return names

    @classmethod
    @abstractmethod
    def _raw_categories(cls, root: Path) -> tuple[str, ...]:
        """Categories present under a raw ``root``; ValueError naming the path if none."""

    @abstractmethod
    def _raw_index(self, categories: tuple[str, ...]) -> list[tuple[str, str]]:
        """``(category, object_id)`` of each object of ``self.published``, interleaved (:func:`interleave`)."""

    @abstractmethod
    def _raw_record(self, index: int) -> ObjectRecord:
        """Read object ``index`` from the published files."""

    @abstractmethod
    def _raw_view(self, index: int, record: ObjectRecord, view: int, size: int) -> ViewImages:
        """Decode input view ``view`` (an index into ``record.views``) of object ``index`` at ``size``
        (``record.cloud`` may be a subset of the object's cloud)."""

    def _object_ids(self) -> list[tuple[str, str]]:
        return self._refs

    def _shape(self, index: int, rng: np.random.Generator) -> Shape:
        # The base class builds meshes only inside surface(), which this class replaces.
        raise TypeError(f"{type(self).__name__} objects are captured clouds, not meshes; use surface()")

    def __getstate__(self) -> dict:
        # Data-loader workers get the index, not the cached records.
        state = dict(self.__dict__)
        state["_cache"] = ByteLRU(self.cache_bytes)
        return state

    def record(self, index: int) -> ObjectRecord:
        """Object ``index`` as stored: from its shard when prepared, else from the published files."""
        if self.prepared is not None:
            return self.prepared.record(self.published, self.objects[index].object_id)
        return self._raw_record(index)

    def _load_surface(self, index: int) -> ObjectRecord:
        """Object ``index`` with ``data.num_points`` drawn from its cloud (``(N, 3)``); :meth:`surface` caches it."""
        rec = self.record(index)
        n, p = self.cfg.data.num_points, rec.cloud.shape[0]
        pick = self._rng(index, _STREAM_CLOUD).choice(p, n, replace=p < n)
        return rec._replace(cloud=rec.cloud[torch.from_numpy(pick)])

    def export(self, index: int) -> tuple[ObjectRecord, list[ViewImages]]:
        """Object ``index`` and all its input views at ``data.image_size``, read from the published
        files without caching (what ``python -m cdm prepare`` stores)."""
        record = self._raw_record(index)
        return record, [self._raw_view(index, record, v, self.cfg.data.image_size) for v in range(len(record.views))]

    def view(self, index: int, view: int) -> ViewImages:
        """Input view ``view`` of object ``index`` at ``data.image_size`` (decoded once per process)."""
        size = self.cfg.data.image_size
        object_id = self.objects[index].object_id
        if self.prepared is not None:
            return resize_view(self.prepared.view(self.published, object_id, view), size)
        key = (self.kind, str(self.root), self.published, object_id, view, size, self.cfg.data.mask_rgb)
        return DECODED.get(key, lambda: self._raw_view(index, self.surface(index), view, size))

    def sample(self, index: int, view_round: int = 0) -> Sample:
        """Object ``index`` seen from its input view of ``view_round`` (a pure function of both)."""
        self._check_sample_args(index, view_round)
        surface = self.surface(index)
        ref = self.objects[index]
        choice = 0
        if self.split == "train" and self.cfg.data.train_view is not None:
            choice = self._train_view(index, len(surface.views))
        elif self.split == "train":
            choice = int(self._rng(index, _STREAM_VIEW, view_round).integers(len(surface.views)))
        v, image, mask, depth = self._view_tensors(index, choice)
        positions = select_sequence_views(len(surface.sequence), int(surface.views[choice]), self.num_views)
        if self.cfg.data.input_source == "folder":  # a generated input image (Table 8 rows 4, 6, 7)
            image = self.condition_images.read_position(
                ref.object_id, int(surface.views[choice]), self.cfg.data.image_size
            )
        prior_depth = self._prior_depth(ref.object_id, choice, int(surface.views[choice]), depth)
        conditions = None
        if self.split == "train" and self.cfg.data.condition_views:
            conditions = self._conditions(index, surface, choice, view_round)
        return Sample(
            image=image,
            mask=mask,
            depth=depth,
            prior_2d=prior_2d_channels(self.cfg.priors.prior_2d, image, mask, prior_depth),
            camera=v.camera,
            # View 0 is the input view itself, with the intrinsics of the input crop.
            view_cameras=_with_first(surface.sequence[torch.tensor(positions)], v.camera),
            points=surface.cloud,
            category=ref.category,
            object_id=ref.object_id,
            conditions=conditions,
        )

    def _train_view(self, index: int, count: int) -> int:
        """``data.train_view`` as an index into object ``index``'s ``count`` input views (BDM's
        ``which_view_from24``)."""
        view = self.cfg.data.train_view
        if view >= count:
            raise ValueError(f"data.train_view: {view}, but {self.objects[index].object_id} has {count} input views")
        return view

    def _view_tensors(self, index: int, choice: int) -> tuple[ViewImages, Tensor, Tensor, Tensor | None]:
        """Input view ``choice`` as RGB ``(3, S, S)``, mask ``(1, S, S)`` and view depth ``(1, S, S)`` or None."""
        v = self.view(index, choice)
        image = torch.from_numpy(v.image).permute(2, 0, 1).float() / 255.0
        mask = torch.from_numpy(v.mask > 127).float()[None]
        depth = None if v.depth is None else torch.from_numpy(v.depth.astype(np.float32))[None] * v.depth_scale
        return v, image, mask, depth

    def _prior_depth(self, object_id: str, view: int, position: int, depth: Tensor | None) -> Tensor | None:
        """The depth the 2D prior reads for input view ``view`` (sequence ``position``): estimated (the
        paper's DINOv2 route; from the folder or the prepared shards) with ``priors.depth_source: maps``,
        else the measured one."""
        size = self.cfg.data.image_size
        if self.depth_maps is not None:
            return self.depth_maps.read(object_id, position, size)
        if self.shard_depths:
            stored = self.prepared.estimated_depth(self.published, object_id, view)
            return torch.from_numpy(cv2.resize(stored, (size, size), interpolation=cv2.INTER_NEAREST))[None]
        return depth

    def _conditions(self, index: int, surface: ObjectRecord, choice: int, view_round: int) -> ConditionViews:
        """k of the object's input views, evenly spaced through them after the input view (``data.condition_views``)."""
        k, n, size = self.cfg.data.condition_views, len(surface.views), self.cfg.data.image_size
        object_id = self.objects[index].object_id
        views, generated = [], []
        for c in ((choice + round(j * n / (k + 1))) % n for j in range(1, k + 1)):
            v, image, mask, depth = self._view_tensors(index, c)
            position = int(surface.views[c])
            views.append(Rendering(image, mask, self._prior_depth(object_id, c, position, depth), v.camera, v.camera))
            if self.cfg.data.condition_source == "folder":
                generated.append(self.condition_images.read_position(object_id, position, size))
        return condition_views(
            views, generated or None, self.shown_conditions(index, view_round), self.cfg.priors.prior_2d
        )


def _with_first(cameras: Cameras, first: Cameras) -> Cameras:
    """``cameras`` (batch ``(H,)``) with camera 0 replaced by ``first`` (batch ``()``)."""
    fields = []
    for many, one in zip(
        (cameras.R, cameras.T, cameras.focal, cameras.principal), (first.R, first.T, first.focal, first.principal)
    ):
        out = many.clone()
        out[0] = one
        fields.append(out)
    return Cameras(*fields)
