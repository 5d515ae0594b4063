"""Co3D v2's annotations read and checked: each category's frames, point clouds and set lists, and the
frames PC²'s loader keeps per sequence (:func:`kept_frames`). The data set built on them is :mod:`cdm.data.co3d`.

Layout under ``data.root`` (as published, one folder per category)::

    <category>/frame_annotations.jgz       gzipped JSON list: one entry per frame (image, mask, depth, viewpoint)
    <category>/sequence_annotations.jgz    gzipped JSON list: one entry per sequence (its point_cloud)
    <category>/set_lists/set_lists_fewview_dev.json   {"train"|"val"|"test": [[sequence, frame_number, image path], …]}
    <category>/<sequence>/images/frame000001.jpg, masks/frame000001.png,
        depths/frame000001.jpg.geometric.png, pointcloud.ply

Paths inside the annotations are relative to ``data.root``; every field is checked as it is read (paths
stay below the root, sizes, intrinsics and depth scale in range) and a bad one is named in a ValueError.
"""

from __future__ import annotations

import hashlib
import math
import random
from collections import defaultdict
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cdm.io.json import read_json
from cdm.io.names import inside, plain_name

__all__ = ["ANNOTATIONS", "LAYOUT", "SET_LIST", "Category", "Frame", "half_sizes", "kept_frames", "load_category"]

SET_LIST = "set_lists_fewview_dev.json"
"""The set list read for splits (PC²'s ``fewview_dev``)."""
ANNOTATIONS = ("frame_annotations.jgz", "sequence_annotations.jgz", f"set_lists/{SET_LIST}")
"""A category folder's annotation files, relative to it."""
LAYOUT = "<root>/<category>/{frame_annotations.jgz, sequence_annotations.jgz, set_lists/, <sequence>/...}"
"""The layout named in errors about a missing file."""


class Frame(NamedTuple):
    """One frame's annotation: files (relative to ``data.root``), image size and camera as published."""

    number: int
    file_order: int
    """Place of the entry among its sequence's entries in ``frame_annotations.jgz``."""
    mask_mass: float | None
    """Foreground pixels of the mask (``mask.mass``), None where the annotation has none."""
    image: str
    size: tuple[int, int]
    mask: str
    depth: str | None
    scale_adjustment: float
    R: np.ndarray
    T: np.ndarray
    focal: tuple[float, float]
    principal: tuple[float, float]
    ndc_format: str


class Category(NamedTuple):
    """One category's annotations: frames per sequence (by frame number), point clouds, set lists."""

    frames: dict[str, list[Frame]]
    clouds: dict[str, str]
    set_lists: dict[str, list[tuple[str, int]]]


MIN_FOCAL, MAX_FOCAL = 0.05, 50.0
"""Accepted NDC focal lengths (Co3D v2's are about 1 to 5): outside, a crop or camera would be degenerate."""
MAX_FRAME_SIDE = 4096
"""Longest image side an annotation may give, in pixels (Co3D v2's frames are at most 1,920): with
:data:`MAX_PIXEL_ASPECT` it bounds the memory of one crop (~170 MB)."""
MAX_PIXEL_ASPECT = 2.0
"""Most ratio between a frame's horizontal and vertical pixel size (``fx·hx : fy·hy``; Co3D's are square),
which sets the crop's width: past it one crop could allocate without bound."""
MAX_PRINCIPAL = 10.0
"""Largest NDC principal-point coordinate accepted (Co3D's are near 0)."""


def _finite(values, count: int, what: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    if array.size != count or not np.isfinite(array).all():
        raise ValueError(f"{what} must be {count} finite numbers")
    return array


def _frame(entry: dict, file_order: int) -> Frame:
    """One entry of ``frame_annotations.jgz``, every field checked: paths stay below the root, sizes,
    intrinsics and depth scale in range (ValueError saying which field)."""
    depth = entry.get("depth") or {}
    view, image, mask = entry["viewpoint"], entry["image"], entry["mask"]
    if not all(isinstance(x, dict) for x in (depth, view, image, mask)):
        raise ValueError("image, mask, depth and viewpoint must be objects")
    mass = mask.get("mass")
    if mass is not None and not (isinstance(mass, (int, float)) and math.isfinite(mass) and mass >= 0):
        raise ValueError(f"mask.mass {mass!r} must be a finite number ≥ 0")
    size = tuple(int(x) for x in _finite(image["size"], 2, "image.size"))
    if not all(0 < x <= MAX_FRAME_SIDE for x in size):
        raise ValueError(f"image.size {list(size)} must be two sides of 1 to {MAX_FRAME_SIDE} pixels")
    focal = _finite(view["focal_length"], 2, "viewpoint.focal_length")
    if not all(MIN_FOCAL <= f <= MAX_FOCAL for f in focal):
        raise ValueError(f"viewpoint.focal_length {focal.tolist()} must lie in [{MIN_FOCAL}, {MAX_FOCAL}] (NDC)")
    principal = _finite(view["principal_point"], 2, "viewpoint.principal_point")
    if np.abs(principal).max() > MAX_PRINCIPAL:
        raise ValueError(
            f"viewpoint.principal_point {principal.tolist()} must lie in [-{MAX_PRINCIPAL}, {MAX_PRINCIPAL}] (NDC)"
        )
    scale = 1.0 if depth.get("scale_adjustment") is None else float(depth["scale_adjustment"])
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"depth.scale_adjustment {scale!r} must be finite and > 0")
    frame = Frame(
        number=int(entry["frame_number"]),
        file_order=file_order,
        mask_mass=None if mass is None else float(mass),
        image=inside(image["path"], "image.path"),
        size=(size[0], size[1]),
        mask=inside(mask["path"], "mask.path"),
        depth=None if depth.get("path") is None else inside(depth["path"], "depth.path"),
        scale_adjustment=scale,
        R=_finite(view["R"], 9, "viewpoint.R").reshape(3, 3),
        T=_finite(view["T"], 3, "viewpoint.T"),
        focal=(float(focal[0]), float(focal[1])),
        principal=(float(principal[0]), float(principal[1])),
        ndc_format=view.get("intrinsics_format", "ndc_norm_image_bounds"),
    )
    hx, hy = half_sizes(frame)
    if not 1 / MAX_PIXEL_ASPECT <= frame.focal[0] * hx / (frame.focal[1] * hy) <= MAX_PIXEL_ASPECT:
        raise ValueError(
            f"viewpoint.focal_length {focal.tolist()} gives pixels {MAX_PIXEL_ASPECT}× wider than high or more"
        )
    return frame


@lru_cache(maxsize=8)
def _category(folder: Path, stamp: tuple[int, ...]) -> Category:
    """Parse one category's annotations (once per process and file version: ``stamp`` = mtimes)."""
    files = [folder / name for name in ANNOTATIONS]
    frames: dict[str, list[Frame]] = defaultdict(list)
    entries = read_json(files[0], "data.root", gzipped=True)
    if not isinstance(entries, list):
        raise ValueError(f"data.root: {files[0]} is not a JSON list of frame entries")
    for number, entry in enumerate(entries):
        try:
            seq = frames[plain_name(entry["sequence_name"], "sequence_name")]
            seq.append(_frame(entry, len(seq)))
        except ValueError as exc:  # the checks say which field; int() and float() say which value
            raise ValueError(f"data.root: {files[0]} entry {number}: {exc}") from None
        except (KeyError, TypeError, IndexError, AttributeError, OverflowError) as exc:
            raise ValueError(
                f"data.root: {files[0]} entry {number} is malformed ({type(exc).__name__}: {exc})"
            ) from None
    for seq in frames.values():
        seq.sort(key=lambda f: f.number)
    sequences, set_lists = read_json(files[1], "data.root", gzipped=True), read_json(files[2], "data.root")
    where = f"data.root: {files[1]}, sequence"
    try:
        clouds = {plain_name(s["sequence_name"], f"{where} name"):
                  inside(s["point_cloud"]["path"], f"{where} {str(s['sequence_name'])[:80]!r}: point_cloud.path")
                  for s in sequences if s.get("point_cloud")}
    except (KeyError, TypeError, IndexError, AttributeError) as exc:
        raise ValueError(
            f"data.root: malformed sequence annotation in {files[1]} ({type(exc).__name__}: {exc})"
        ) from None
    try:
        lists = {k: [(str(e[0]), int(e[1])) for e in v] for k, v in set_lists.items()}
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, OverflowError) as exc:
        raise ValueError(f"data.root: malformed set list {files[2]} ({type(exc).__name__}: {exc})") from None
    return Category(dict(frames), clouds, lists)


def load_category(folder: Path) -> Category:
    """The parsed annotations of ``folder`` (a category), from the process cache when unchanged."""
    stamp = []
    for name in ANNOTATIONS:
        path = folder / name
        if not path.exists():  # a FIFO or a folder there is refused by name when read
            raise ValueError(f"data.root: annotation file {path} is missing; expected {LAYOUT}")
        stamp.append(path.stat().st_mtime_ns)
    return _category(folder, tuple(stamp))


def kept_frames(sequence: str, frames: list[Frame], count: int) -> set[int]:
    """Frame numbers of ``sequence`` that PyTorch3D's ``JsonIndexDataset`` keeps with
    ``n_frames_per_sequence=count`` and ``remove_empty_masks=True``, as PC² builds it (PyTorch3D 0.7.3,
    ``pytorch3d/implicitron/dataset/json_index_dataset.py``, ``_filter_db``): frames whose mask mass is
    over 1 pixel (unknown mass counts as non-empty), in annotation-file order, shuffled by
    ``random.Random(int(sha1(sequence), 16) + 0)`` (``_seq_name_to_seed`` plus its default seed 0),
    the first ``count`` taken. The choice ignores the set lists, which are applied afterwards."""
    eligible = sorted((f for f in frames if f.mask_mass is None or f.mask_mass > 1), key=lambda f: f.file_order)
    seed = int(hashlib.sha1(sequence.encode("utf-8")).hexdigest(), 16)
    return {f.number for f in random.Random(seed).sample(eligible, len(eligible))[:count]}




def half_sizes(frame: Frame) -> tuple[float, float]:
    """The pixels per NDC unit along x and y (``hx, hy``) of the frame's ``intrinsics_format``."""
    h, w = frame.size
    if frame.ndc_format == "ndc_isotropic":
        return min(h, w) / 2.0, min(h, w) / 2.0
    if frame.ndc_format == "ndc_norm_image_bounds":
        return w / 2.0, h / 2.0
    raise ValueError(f"viewpoint.intrinsics_format {str(frame.ndc_format)[:40]!r} is unknown; Co3D uses "
                     "ndc_isotropic (v2) or ndc_norm_image_bounds (v1)")
