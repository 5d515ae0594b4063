"""Prepared data roots (one shard per object) and the per-process cache of decoded views.

``python -m cdm prepare --set data.kind=KIND --root RAW --out OUT`` (:mod:`cdm.data.prepare`) reads every
object of the training split and of ``data.eval_split`` once and writes

- ``OUT/<published split>/<object_id>.safetensors``: the object's shard: its cloud and sequence cameras in
  the data set's frame (:mod:`cdm.normalise`) and every input view of the split already cropped and resized
  (``data.image_size``, 224 by default):
  RGB and mask as uint8, depth as the published float16 values with their scale, and the crop camera;
- ``OUT/cdm_prepared.json``: the manifest (kind, image size, categories, objects per split);
- ``OUT/.cdm_prepare_scratch/``: the temporary files of shards being written (:data:`SCRATCH`).

A shard is one safetensors file (:mod:`cdm.io.safetensors`): the arrays as its tensors, ``meta`` as JSON
and the format in its metadata (``cdm.meta``, ``cdm.format``). Reading maps the file and copies only
the view asked for, so a sample costs one small read instead of decoding a JPEG, a PNG mask, a 16-bit
depth PNG and a PLY. Every file is written under a temporary name and renamed when complete (a crash
leaves no half-written shard); preparing again skips finished shards and empties the scratch folder of
what a killed run left, so an interrupted run resumes.
Point ``data.root`` at ``OUT`` to train from it.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from cdm.cameras import Cameras
from cdm.data.lru import ByteLRU
from cdm.data.views import interleave
from cdm.io.json import parse_json, read_json
from cdm.io.names import object_id_parts
from cdm.io.safetensors import read_safetensors, write_safetensors

__all__ = [
    "DECODED",
    "ESTIMATED_DEPTHS",
    "FORMAT",
    "MANIFEST",
    "SCRATCH",
    "SHARD_SUFFIX",
    "ObjectRecord",
    "PreparedRoot",
    "ViewImages",
    "is_prepared",
    "read_shard",
    "write_shard",
]

MANIFEST = "cdm_prepared.json"
"""Name of the manifest file that marks a prepared root."""
FORMAT = 3
"""Version of the manifest and shards; 2: clouds and cameras in the data set's frame, not the object's box;
3: shards in safetensors (roots of earlier formats are refused: prepare them again)."""
SHARD_SUFFIX = ".safetensors"
"""A shard's file name is its object id and this."""
SCRATCH = ".cdm_prepare_scratch"
"""Folder in a prepared root holding the temporary files of shards being written: the only place
``prepare`` removes files it finds (:data:`cdm.io.write.TEMP_NAME` names only)."""
ESTIMATED_DEPTHS = "estimated_depths"
"""Shard array (and manifest key) of the estimated depth maps stored by ``prepare --depth-maps``."""
_META, _FORMAT_KEY = "cdm.meta", "cdm.format"
_REDO = "delete it and rerun `python -m cdm prepare`"


class ObjectRecord(NamedTuple):
    """One object as stored, before ``data.num_points`` is drawn.

    Attributes:
        cloud: ``(P, 3)`` float32 ground truth in the data set's frame (:mod:`cdm.normalise`).
        sequence: cameras of batch ``(F,)``, the object's views in order, in that frame,
            each framing the whole object (the prior views are taken from it).
        views: ``(V,)`` int64 sequence positions of the split's input views (view 0: the held-out one).
        scale: the frame's scale, frame units per published world unit (:attr:`cdm.normalise.Frame.scale`).
    """

    cloud: Tensor
    sequence: Cameras
    views: Tensor
    scale: float

    def nbytes(self) -> int:
        """Memory held by the record's tensors, in bytes (the record cache's budget unit)."""
        cams = self.sequence
        return sum(
            t.numel() * t.element_size() for t in (self.cloud, self.views, cams.R, cams.T, cams.focal, cams.principal)
        )


class ViewImages(NamedTuple):
    """One input view cropped to the square frame of ``camera`` and resized to ``S × S``.

    Attributes:
        image: ``(S, S, 3)`` uint8 RGB.
        mask: ``(S, S)`` uint8, 255 on the object and 0 elsewhere.
        depth: ``(S, S)`` float16 published depth values (0 = unknown), or None for data without depth.
        depth_scale: multiply ``depth`` by this for view depth in the data set's frame units.
        camera: the crop's camera, batch ``()``, in the data set's frame (:mod:`cdm.cameras`).
    """

    image: np.ndarray
    mask: np.ndarray
    depth: np.ndarray | None
    depth_scale: float
    camera: Cameras

    def nbytes(self) -> int:
        return self.image.nbytes + self.mask.nbytes + (0 if self.depth is None else self.depth.nbytes)


DECODED: ByteLRU[ViewImages] = ByteLRU(256 * 2**20)
"""This process's decoded raw views (256 MiB: ~850 views at 224² with depth), by a key naming the file
and the decoding (data set, root, object, view, size). A sweep runs its cells one after another in
reused worker processes, so later cells find their images here."""


def write_shard(path: Path, arrays: dict[str, np.ndarray], meta: dict, scratch: Path) -> None:
    """Write one shard (format in the module docstring) atomically, its temporary file in ``scratch``
    (:func:`cdm.io.write.write_atomic`)."""
    write_safetensors(path, {name: torch.from_numpy(np.ascontiguousarray(a)) for name, a in arrays.items()},
                      {_FORMAT_KEY: str(FORMAT), _META: json.dumps(meta)}, "--out", scratch=scratch)


class Shard(NamedTuple):
    """A shard's ``meta`` and its arrays (views of the mapped file)."""

    meta: dict
    arrays: dict[str, np.ndarray]


@lru_cache(maxsize=64)
def read_shard(path: Path) -> Shard:
    """Map one shard; ValueError naming the file if it is not a complete shard of this format."""
    try:
        tensors, metadata = read_safetensors(path, "data.root", mapped=True)
    except ValueError as exc:
        raise ValueError(f"{exc}; {_REDO}") from None
    if metadata.get(_FORMAT_KEY) != str(FORMAT) or _META not in metadata:
        raise ValueError(f"data.root: {path} is not a CDM shard of format {FORMAT}; {_REDO}")
    return Shard(parse_json(metadata[_META].encode(), "data.root", path), {k: t.numpy() for k, t in tensors.items()})


def _cameras(arrays: dict[str, np.ndarray], prefix: str, index: int | slice = slice(None)) -> Cameras:
    return Cameras(
        *(torch.from_numpy(np.array(arrays[f"{prefix}_{k}"][index])) for k in ("R", "T", "focal", "principal"))
    )


def is_prepared(root: Path) -> bool:
    """Whether ``root`` was written by ``python -m cdm prepare``."""
    return (root / MANIFEST).is_file()


class PreparedRoot:
    """A prepared root's manifest and the shards it lists."""

    def __init__(self, root: Path, manifest: dict):
        self.root = root
        self.manifest = manifest
        self.categories: tuple[str, ...] = tuple(manifest["categories"])

    @classmethod
    def open(cls, root: Path, kind: str) -> PreparedRoot:
        """Read ``root``'s manifest; ValueError if it is damaged or was prepared for another kind."""
        path = root / MANIFEST
        manifest = read_json(path, "data.root")
        if not isinstance(manifest, dict):
            raise ValueError(f"data.root: {path} is not a manifest of `python -m cdm prepare`; prepare the root again")
        if manifest.get("format") != FORMAT:
            raise ValueError(
                f"data.root: {path} has format {manifest.get('format')!r}, this version reads {FORMAT}; prepare again"
            )
        if manifest["kind"] != kind:
            raise ValueError(
                f"data.kind: {kind!r}, but {root} was prepared from data.kind={manifest['kind']!r}; set it to match"
            )
        return cls(root, manifest)

    def shard_path(self, published: str, object_id: str) -> Path:
        return self.root / published / f"{object_id}{SHARD_SUFFIX}"

    def objects(self, published: str, categories: tuple[str, ...]) -> list[tuple[str, str]]:
        """``(category, object_id)`` of split ``published`` in ``categories``, interleaved; every shard must exist."""
        splits = self.manifest["splits"]
        if published not in splits:
            raise ValueError(
                f"data.eval_split: {self.root} was prepared with splits {sorted(splits)}, not {published!r}; "
                f"run `python -m cdm prepare ... --set data.eval_split={published}` into another --out"
            )
        for c, oid in splits[published]:  # ids become shard paths: none may leave the root
            object_id_parts(oid, f"data.root: {self.root / MANIFEST}, split {published!r}, category {str(c)[:40]!r}")
        per_category = [[(c, oid) for c, oid in splits[published] if c == category] for category in categories]
        refs = interleave(per_category)
        missing = [p for p in (self.shard_path(published, oid) for _, oid in refs) if not p.is_file()]
        if missing:
            raise ValueError(
                f"data.root: {self.root} is incomplete: {len(missing)} of {len(refs)} shards missing "
                f"(first: {missing[0]}); "
                "run the same `python -m cdm prepare` command again to finish it"
            )
        return refs

    def record(self, published: str, object_id: str) -> ObjectRecord:
        shard = read_shard(self.shard_path(published, object_id))
        a = shard.arrays
        cloud = torch.from_numpy(np.array(a["cloud"]))
        return ObjectRecord(
            cloud, _cameras(a, "seq"), torch.from_numpy(np.array(a["views"])), float(shard.meta["scale"])
        )

    @property
    def has_estimated_depths(self) -> bool:
        """Prepared with ``--depth-maps``: every shard holds its views' estimated depth."""
        return ESTIMATED_DEPTHS in self.manifest

    def estimated_depth(self, published: str, object_id: str, view: int) -> np.ndarray:
        """``(S, S)`` float32 estimated view depth of input view ``view`` (0 = unknown)."""
        return np.array(read_shard(self.shard_path(published, object_id)).arrays[ESTIMATED_DEPTHS][view])

    def view(self, published: str, object_id: str, view: int) -> ViewImages:
        a = read_shard(self.shard_path(published, object_id)).arrays
        depth = np.array(a["depths"][view]) if "depths" in a else None
        return ViewImages(np.array(a["images"][view]), np.array(a["masks"][view]), depth, float(a["depth_scale"][view]),
                          _cameras(a, "cam", view))
