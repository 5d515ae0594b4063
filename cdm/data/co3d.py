"""Co3D v2 (Common Objects in 3D) as PC² and the paper use it: one object per video sequence.

An object is a sequence with a point cloud, read from its category's annotations
(:mod:`cdm.data.co3d_annotations`, which gives the layout); its split is the ``fewview_dev`` set list
(``train`` for training, ``data.eval_split`` held out), and its input views are the frames listed there
(held-out input: the first). The prior views are H frames evenly spaced through the whole sequence from
the input frame (the paper's procedure).

PC²'s protocol (its ``experiments/dataset/__init__.py``, through PyTorch3D 0.7's ``JsonIndexDataset``)
is four switches here, all set by the paper profile on Co3D: ``data.exclude_sequences`` leaves out its
listed sequences (:mod:`cdm.data.co3d_lists`); ``data.frames_per_sequence`` (PC²: 1) keeps the frames
PyTorch3D keeps (:func:`cdm.data.co3d_annotations.kept_frames`), so each sequence has one fixed input
frame in every split it is still in; ``data.mask_rgb`` blacks out the background;
``data.drop_outliers: false`` keeps every point of the published cloud.

Units and frames. Depth PNGs are 16-bit images whose bits are float16 values; × ``scale_adjustment``
they are view depths in the sequence's world units, like its cameras and point cloud. Cloud, cameras
and depths stay in those units, PC²'s frame (:data:`cdm.normalise.IDENTITY`: nothing is fitted to the
cloud). With ``data.drop_outliers`` the cloud loses the points outside its robust bounding box (0.5–99.5 %
quantiles widened by 10 %). ``data.num_points`` are drawn from it (the paper: 16,384).

Cameras. Co3D stores PyTorch3D cameras: ``X_view = X_world @ R + T`` (row vectors), +X left, +Y up,
+Z forward — our convention (:mod:`cdm.cameras`) — with ``focal_length (fx, fy)`` and
``principal_point`` in NDC of the full, non-square image: ``ndc_isotropic`` (v2) scales both axes by
half the shorter side, ``ndc_norm_image_bounds`` (v1) each axis by its own half-size. In pixels
(u right from the left edge, v down from the top), with ``hx, hy`` those half-sizes:
``u = W/2 − (fx·X/Z + px)·hx`` and ``v = H/2 − (fy·Y/Z + py)·hy``. The input view is cropped around
the mask's bounding box (side × 1.3, a box of aspect ``fx·hx : fy·hy`` so square pixels come out
square) and resized to ``S × S``; for a crop ``(left, top, Bw, Bh)`` the square camera is
``focal = fx·hx·2/Bw`` (= ``fy·hy·2/Bh`` up to rounding; the mean is used),
``principal = (1 − 2·(u₀ − left)/Bw, 1 − 2·(v₀ − top)/Bh)`` with ``u₀, v₀`` the principal point in
pixels. Prior-view cameras keep each frame's pose and get the intrinsics of the largest square crop
centred on the frame (:func:`centred_box`): from the annotation alone, no image or cloud is read for them.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import torch

from cdm.cameras import Cameras
from cdm.config import Config
from cdm.data.cache import ObjectRecord, ViewImages
from cdm.data.captured import CapturedDataset, cap_cloud
from cdm.data.co3d_annotations import ANNOTATIONS, LAYOUT, SET_LIST, Frame, half_sizes, kept_frames, load_category
from cdm.data.co3d_lists import excluded_sequences
from cdm.data.views import Split, interleave
from cdm.io.images import read_image
from cdm.io.meshes import read_vertices
from cdm.io.names import PLAIN_NAME
from cdm.normalise import IDENTITY
from cdm.normalise import Frame as NormalisedFrame

__all__ = ["CROP_MARGIN", "Co3DDataset", "centred_box", "crop_camera", "load_depth"]

CROP_MARGIN = 0.3
"""The input crop is the mask's bounding box widened by this fraction of its longer side."""


def load_depth(path: Path) -> np.ndarray:
    """``(H, W)`` float16 published depth values of a Co3D depth PNG (×``scale_adjustment`` = world units)."""
    raw = read_image(path, cv2.IMREAD_UNCHANGED, "data.root")
    if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
        raise ValueError(f"data.root: cannot read depth {path} (missing, corrupt or not a 16-bit single-channel PNG)")
    return raw.view(np.float16)


def crop_camera(frame: Frame, box: tuple[int, int, int, int]) -> tuple[float, tuple[float, float]]:
    """NDC focal and principal point of the square camera of crop ``box`` (left, top, width, height; pixels)."""
    hx, hy = half_sizes(frame)
    h, w = frame.size
    u0, v0 = w / 2.0 - frame.principal[0] * hx, h / 2.0 - frame.principal[1] * hy
    left, top, bw, bh = box
    focal = (frame.focal[0] * hx * 2.0 / bw + frame.focal[1] * hy * 2.0 / bh) / 2.0
    return focal, (1.0 - 2.0 * (u0 - left) / bw, 1.0 - 2.0 * (v0 - top) / bh)


def _box(frame: Frame, cx: float, cy: float, side: float) -> tuple[int, int, int, int]:
    """The crop (left, top, width, height; pixels) centred on ``(cx, cy)``, ``side`` pixels high, of the
    width that makes its pixels square (aspect ``fx·hx : fy·hy``)."""
    hx, hy = half_sizes(frame)
    aspect = frame.focal[0] * hx / (frame.focal[1] * hy)
    bh, bw = max(1, round(side)), max(1, round(side * aspect))
    return round(cx - bw / 2.0), round(cy - bh / 2.0), bw, bh


def centred_box(frame: Frame) -> tuple[int, int, int, int]:
    """The largest square-pixel crop centred on the frame: the prior views' and an empty mask's crop."""
    hx, hy = half_sizes(frame)
    h, w = frame.size
    return _box(frame, w / 2.0, h / 2.0, float(min(h, w * frame.focal[1] * hy / (frame.focal[0] * hx))))


def _crop_box(frame: Frame, mask: np.ndarray) -> tuple[int, int, int, int]:
    """The input crop around the mask (:func:`centred_box` when the mask is empty)."""
    hx, hy = half_sizes(frame)
    aspect = frame.focal[0] * hx / (frame.focal[1] * hy)  # box width / height giving square pixels
    rows, cols = np.nonzero(mask > 127)
    if not len(rows):
        return centred_box(frame)
    cy, cx = (rows.min() + rows.max() + 1) / 2.0, (cols.min() + cols.max() + 1) / 2.0
    return _box(
        frame, cx, cy, max(rows.max() + 1 - rows.min(), (cols.max() + 1 - cols.min()) / aspect) * (1.0 + CROP_MARGIN)
    )


def _crop(array: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    """``array[top:top+bh, left:left+bw]`` with zeros where the box leaves the image."""
    left, top, bw, bh = box
    out = np.zeros((bh, bw, *array.shape[2:]), dtype=array.dtype)
    y0, x0 = max(top, 0), max(left, 0)
    y1, x1 = min(top + bh, array.shape[0]), min(left + bw, array.shape[1])
    if y1 > y0 and x1 > x0:
        out[y0 - top : y1 - top, x0 - left : x1 - left] = array[y0:y1, x0:x1]
    return out


def _read_cloud(path: Path) -> np.ndarray:
    points = read_vertices(path, "data.root")
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 16 or not np.isfinite(points).all():
        raise ValueError(f"data.root: {path} holds no usable point cloud (expected ≥16 finite xyz vertices)")
    return points


class Co3DDataset(CapturedDataset):
    """Co3D v2 sequences with point clouds; object ids ``co3d/<category>/<sequence>``."""

    kind = "co3d"
    protocol_fields = ("exclude_sequences", "frames_per_sequence", "mask_rgb", "drop_outliers")
    layout = LAYOUT

    def __init__(self, cfg: Config, split: Split, cache_bytes: int = 512 * 2**20):
        self._sequences: dict[str, tuple[list[Frame], list[int], str]] = {}
        self._frames_per_sequence = cfg.data.frames_per_sequence  # read by _raw_index, before self.cfg is set
        super().__init__(cfg, split, cache_bytes)

    @classmethod
    def _raw_categories(cls, root: Path) -> tuple[str, ...]:
        try:
            folders = sorted(p for p in root.iterdir() if p.is_dir())
        except OSError as exc:
            raise ValueError(f"data.root: cannot list {root}: {exc.strerror}") from None
        # A category folder is recognised by any of its annotation files, so one missing file is
        # reported by name rather than hiding the category.
        found = tuple(
            p.name
            for p in folders
            if PLAIN_NAME.fullmatch(p.name) and any((p / name).exists() for name in ANNOTATIONS)
        )
        if not found:
            raise ValueError(
                f"data.root: {root} has no Co3D category folder (no frame_annotations.jgz); expected {cls.layout}"
            )
        return found

    def _raw_index(self, categories: tuple[str, ...]) -> list[tuple[str, str]]:
        per_category = []
        for name in categories:
            folder = self.root / name
            annotations = load_category(folder)
            if self.published not in annotations.set_lists:
                raise ValueError(f"data.eval_split: {folder / 'set_lists' / SET_LIST} has no {self.published!r} list "
                                 f"(it has {sorted(annotations.set_lists)})")
            listed: dict[str, set[int]] = defaultdict(set)
            for seq, number in annotations.set_lists[self.published]:
                listed[seq].add(number)
            refs = []
            for seq in sorted(listed):
                frames = annotations.frames.get(seq, [])
                if self._frames_per_sequence is not None:
                    listed[seq] &= kept_frames(seq, frames, self._frames_per_sequence)
                views = [i for i, f in enumerate(frames) if f.number in listed[seq]]
                # Sequences without a point cloud have no ground truth: PC² skips them too.
                if views and seq in annotations.clouds:
                    object_id = f"co3d/{name}/{seq}"
                    self._sequences[object_id] = (frames, views, annotations.clouds[seq])
                    refs.append((name, object_id))
            if not refs:
                raise ValueError(
                    f"data.root: no sequence of {folder} with a cloud is in the {self.published!r} list of {SET_LIST}"
                )
            per_category.append(refs)
        return interleave(per_category)

    def _object_ids(self) -> list[tuple[str, str]]:
        if not self.cfg.data.exclude_sequences:
            return self._refs
        kept = [(c, o) for c, o in self._refs if o.rsplit("/", 1)[1] not in excluded_sequences(c)]
        if not kept:
            raise ValueError(f"data.exclude_sequences: every {self.published!r} sequence of {self.root} is on PC²'s "
                             "exclusion lists (cdm/data/co3d_lists.py)")
        return kept

    def _raw_record(self, index: int) -> ObjectRecord:
        object_id = self.objects[index].object_id
        frames, views, cloud_path = self._sequences[object_id]
        cloud = cap_cloud(_read_cloud(self.root / cloud_path), object_id)
        if self.cfg.data.drop_outliers:
            lo, hi = np.quantile(cloud, 0.005, axis=0), np.quantile(cloud, 0.995, axis=0)
            pad = 0.1 * (hi - lo)
            cloud = cloud[np.all((cloud >= lo - pad) & (cloud <= hi + pad), axis=1)]
        units = self.frame(self.objects[index].category)  # a coordinate frame, not a video frame
        R = torch.from_numpy(np.stack([f.R for f in frames])).float()
        T = units.translation(R, torch.from_numpy(np.stack([f.T for f in frames])).float())
        intrinsics = [crop_camera(f, centred_box(f)) for f in frames]
        focal = torch.tensor([focal for focal, _ in intrinsics], dtype=torch.float32)
        principal = torch.tensor([principal for _, principal in intrinsics], dtype=torch.float32)
        sequence = Cameras(R, T, focal, principal)
        return ObjectRecord(units.points(cloud), sequence, torch.tensor(views, dtype=torch.long), units.scale)

    def frame(self, category: str) -> NormalisedFrame:
        """PC²'s frame: the sequence's world units (times its ``scale_factor = 1.0``)."""
        return IDENTITY

    def _raw_view(self, index: int, record: ObjectRecord, view: int, size: int) -> ViewImages:
        frames = self._sequences[self.objects[index].object_id][0]
        position = int(record.views[view])
        frame = frames[position]
        path = self.root / frame.image
        bgr = read_image(path, cv2.IMREAD_COLOR, "data.root")
        if bgr is None:
            raise ValueError(
                f"data.root: cannot read image {path} (missing or corrupt); expected {frame.size[1]}×{frame.size[0]}"
            )
        if bgr.shape[:2] != frame.size:
            raise ValueError(
                f"data.root: {path} is {bgr.shape[1]}×{bgr.shape[0]}, annotated as {frame.size[1]}×{frame.size[0]}"
            )
        mask = read_image(self.root / frame.mask, cv2.IMREAD_GRAYSCALE, "data.root")
        if mask is None:
            raise ValueError(
                f"data.root: cannot read mask {self.root / frame.mask} (missing or corrupt); expected a grey PNG"
            )
        if mask.shape != frame.size:
            mask = cv2.resize(mask, frame.size[::-1], interpolation=cv2.INTER_LINEAR)
        box = _crop_box(frame, mask)
        shrink = box[2] > size
        interp = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        rgb = bgr[..., ::-1]
        if self.cfg.data.mask_rgb:
            # PyTorch3D's mask_images: the soft mask times the full-resolution image, before the crop
            # (rounded to 8 bits here, as every image is stored).
            rgb = (rgb * (mask[..., None] / np.float32(255.0))).round().astype(np.uint8)
        image = cv2.resize(_crop(rgb, box), (size, size), interpolation=interp)
        mask = np.where(cv2.resize(_crop(mask, box), (size, size), interpolation=interp) > 127, 255, 0).astype(np.uint8)
        depth = np.zeros((size, size), dtype=np.float16)  # 0 = unknown, for a frame published without depth
        if frame.depth is not None:
            raw = load_depth(self.root / frame.depth)
            if raw.shape != frame.size:  # nearest: blending would invent depths across edges
                raw = cv2.resize(raw.astype(np.float32), frame.size[::-1], interpolation=cv2.INTER_NEAREST).astype(
                    np.float16
                )
            depth = cv2.resize(
                _crop(raw, box).astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST
            ).astype(np.float16)
            depth[mask == 0] = 0  # the sample format: depth 0 off the object
        focal, principal = crop_camera(frame, box)
        pose = record.sequence[position]
        camera = Cameras(
            pose.R, pose.T, torch.tensor(focal, dtype=torch.float32), torch.tensor(principal, dtype=torch.float32)
        )
        return ViewImages(np.ascontiguousarray(image), mask, depth, frame.scale_adjustment * record.scale, camera)
