"""From an object's surface to a :class:`~cdm.data.sample.Sample`: sampling, cameras, shading.

Shared by every data set made of meshes (procedural shapes, mesh folders). Per object, once:

1. normalise into the data set's frame for the object's category (:mod:`cdm.normalise`: fixed per
   data set and category, never fitted to the object, so the input cameras say nothing of where the
   ground truth sits or how large it is; every object of the frame lies in about [-1, 1]³);
2. sample ``data.num_points`` surface points (the ground-truth cloud) and a denser cloud with face
   normals and material ids (:func:`dense_point_count`: enough to look solid at ``data.image_size``);
3. draw a colour per material.

Per view: a random camera looking at the frame's origin (elevation −10…40°, azimuth 0…360°, distance
3…4 frame units), its focal fitted so the rendered surface reaches a random 70–90 % of the half-frame in
the widest of its prior views (a photographer's zoom: the image shows the object at about one size, and
the focal, an input, carries how large it is), a random light and background; the dense cloud is
rasterized by :func:`cdm.render.rasterize_points` with discs of 1.5 px and the front-most point of each
pixel is Lambert-shaded (two-sided normals).

:class:`ObjectDataset` holds what every such data set shares: ids, seeding, an LRU cache of
surfaces, views per split. Seeding is a pure function of ``data.seed`` and the object id, so the
same config always gives the same tensors. Held-out (``val``) samples show each object from one
fixed view; training samples draw a fresh view per *view round* (``set_epoch``), fixed within it.
"""

from __future__ import annotations

import colorsys
import hashlib
from abc import ABC, abstractmethod
from typing import ClassVar, Literal, NamedTuple

import numpy as np
import torch
import trimesh
from torch import Tensor
from torch.utils.data import Dataset

from cdm.cameras import Cameras, orbit_cameras, project_points
from cdm.config import Config
from cdm.data.condition_images import ConditionImages, condition_views
from cdm.data.lru import ByteLRU
from cdm.data.priors2d import prior_2d_channels
from cdm.data.sample import ConditionViews, Sample
from cdm.digest import json_digest
from cdm.normalise import FRAME_VERSION, Frame
from cdm.render import rasterize_points

__all__ = [
    "RASTER_RADIUS_PX",
    "ObjectDataset",
    "ObjectRef",
    "ObjectSurface",
    "Rendering",
    "Shape",
    "Split",
    "View",
    "dense_point_count",
    "draw_palette",
    "draw_view",
    "interleave",
    "render_view",
    "sample_surface",
    "select_categories",
]

Split = Literal["train", "val"]

RASTER_RADIUS_PX = 1.5
"""Disc radius of the dense surface points when rendering the input image, in pixels."""

_FIT_POINTS = 2048
"""Dense points (an i.i.d. subset) projected to fit the focal; the frame margin covers the rest."""

# Purposes of the per-object random streams (spawn keys of one SeedSequence per object).
_STREAM_SHAPE, _STREAM_SURFACE, _STREAM_PALETTE, _STREAM_VIEW, _STREAM_CONDITIONS = range(5)


class Shape(NamedTuple):
    """A mesh as built or loaded, before normalisation.

    Attributes:
        mesh: triangle mesh, world frame (+Y up), any units.
        material: ``(F,)`` int material index per face (0 = main colour, 1 = accent).
    """

    mesh: trimesh.Trimesh
    material: np.ndarray


class ObjectSurface(NamedTuple):
    """One normalised object, ready to be viewed. Frame: its category's (:mod:`cdm.normalise`).

    Attributes:
        cloud: ``(N, 3)`` float32 ground-truth surface samples (``data.num_points``).
        points: ``(M, 3)`` float32 dense surface samples used for rendering.
        normals: ``(M, 3)`` float32 unit face normals of ``points`` (orientation arbitrary).
        material: ``(M,)`` uint8 material index of ``points``.
        palette: ``(K, 3)`` RGB in [0, 1] per material.
    """

    cloud: Tensor
    points: Tensor
    normals: Tensor
    material: Tensor
    palette: Tensor

    def nbytes(self) -> int:
        """Memory held by the tensors, in bytes (the cache's budget unit)."""
        return sum(t.numel() * t.element_size() for t in self)


class View(NamedTuple):
    """How one sample sees its object.

    Attributes:
        elev, azim: camera elevation and azimuth, degrees (:func:`cdm.cameras.look_at_cameras`).
        dist: camera distance from the origin, world units.
        fill: fraction of the frame's half-width the object reaches in its widest prior view (0–1).
        light: ``(3,)`` unit direction towards the light, view frame (+Z into the screen).
        ambient: ambient share of the shading, in [0, 1).
        background: grey level of the background, in [0, 1].
    """

    elev: float
    azim: float
    dist: float
    fill: float
    light: Tensor
    ambient: float
    background: float


class Rendering(NamedTuple):
    """Images and cameras of one view; shapes as in :class:`~cdm.data.sample.Sample`."""

    image: Tensor
    mask: Tensor
    depth: Tensor
    camera: Cameras
    view_cameras: Cameras


class ObjectRef(NamedTuple):
    """Category and stable id of one object of a data set."""

    category: str
    object_id: str


def dense_point_count(image_size: int) -> int:
    """Dense surface samples for rendering at ``image_size``: 0.6 per pixel, 2,048–30,000.

    Discs of 1.5 px cover ~7 px; an object covers a third of the frame or less and about half its
    points face away. Against a 300k-point reference render, pixels showing a hidden surface through
    a hole fell from 4.0/5.3/6.4 % (0.4·S², at 64/128/224 px) to 3.2/4.0/4.7 % (0.6·S²); 0.8·S²
    gained under 1 point more. Discs of 2 px instead spill over edges (7–9 %).
    """
    return int(min(30_000, max(2_048, round(0.6 * image_size**2))))


def sample_surface(
    shape: Shape, frame: Frame, num_points: int, num_dense: int, rng: np.random.Generator, palette: Tensor
) -> ObjectSurface:
    """Sample the surface of ``shape`` (area-uniform, seeded by ``rng``) in ``frame``.

    Args:
        shape: the mesh and its per-face materials.
        frame: the data set's frame for the object's category (not fitted to this mesh).
        num_points: ``N``, ground-truth cloud size.
        num_dense: ``M``, dense samples for rendering.
        rng: the object's surface stream.
        palette: ``(K, 3)`` colour per material.
    Raises:
        ValueError: the mesh has no area or non-finite vertices.
    """
    mesh = shape.mesh
    if not (np.all(np.isfinite(mesh.vertices)) and mesh.area > 0):
        raise ValueError("mesh has no faces with area or non-finite vertices")
    cloud, _ = trimesh.sample.sample_surface(mesh, num_points, seed=rng)
    points, face = trimesh.sample.sample_surface(mesh, num_dense, seed=rng)
    return ObjectSurface(
        cloud=frame.points(cloud),
        points=frame.points(points),
        normals=torch.from_numpy(mesh.face_normals[face]).float(),
        material=torch.from_numpy(shape.material[face].astype(np.uint8)),
        palette=palette,
    )


def draw_palette(rng: np.random.Generator, num_materials: int = 2) -> Tensor:
    """``(K, 3)`` RGB colours: a random main colour; accents are another colour or a shade of it."""
    base = colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.15, 0.85), rng.uniform(0.35, 0.95))
    colours = [base]
    for _ in range(num_materials - 1):
        if rng.random() < 0.5:
            colours.append(colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.0, 0.8), rng.uniform(0.2, 0.95)))
        else:
            colours.append(tuple(min(1.0, c * rng.uniform(0.5, 1.4)) for c in base))
    return torch.tensor(colours, dtype=torch.float32)


def draw_view(rng: np.random.Generator) -> View:
    """A random camera pose, framing, light and background (ranges in the module docstring)."""
    light = torch.tensor([rng.uniform(-1.0, 1.0), rng.uniform(-0.3, 1.0), -1.0], dtype=torch.float32)
    return View(
        elev=rng.uniform(-10.0, 40.0),
        azim=rng.uniform(0.0, 360.0),
        dist=rng.uniform(3.0, 4.0),
        fill=rng.uniform(0.7, 0.9),
        light=light / light.norm(),
        ambient=rng.uniform(0.2, 0.45),
        background=1.0 if rng.random() < 0.5 else rng.uniform(0.25, 0.9),
    )


_FIT_AZIMUTHS = 24
"""Azimuths (15° apart) the focal is fitted over, whatever H is: the input image must not depend on
the number of prior views or on whether the 3D prior is on, or ablations over H and ``prior_3d``
would compare differently zoomed images. ``view.fill`` < 1 leaves margin for azimuths in between."""


def _fitted_cameras(points: Tensor, view: View, num_views: int) -> Cameras:
    """The ``(H,)`` orbit cameras of ``view`` with the focal that puts the farthest projected point,
    over a fixed orbit of :data:`_FIT_AZIMUTHS` views, at ``view.fill`` of the half-frame, so the
    object fits every prior view. ``points`` ``(P, 3)``: a random subset of the surface is enough."""
    one = torch.ones(1)
    fit = orbit_cameras(one * view.elev, one * view.azim, one * view.dist, _FIT_AZIMUTHS, focal=1.0).flatten()
    reach = project_points(points.expand(_FIT_AZIMUTHS, -1, -1), fit)[..., :2].abs().max()
    focal = view.fill / float(reach)
    return orbit_cameras(one * view.elev, one * view.azim, one * view.dist, num_views, focal=focal).flatten()


def render_view(surface: ObjectSurface, view: View, image_size: int, num_views: int) -> Rendering:
    """Render ``surface`` from ``view``: shaded image, mask and depth at ``image_size``.

    Args:
        surface: the normalised object.
        view: camera, light and background.
        image_size: ``S`` in pixels.
        num_views: ``H``, prior-view cameras to return (evenly spaced in azimuth, view 0 = input).
    Returns:
        :class:`Rendering`: image ``(3, S, S)`` in [0, 1] (background grey where mask is 0), mask
        ``(1, S, S)`` in {0, 1}, depth ``(1, S, S)`` view depth in world units (0 on background),
        input camera (batch ``()``) and prior-view cameras (batch ``(H,)``).
    """
    view_cameras = _fitted_cameras(surface.points[:_FIT_POINTS], view, num_views)
    camera = view_cameras[:1]
    frags = rasterize_points(surface.points[None], camera, image_size, radius=RASTER_RADIUS_PX * 2.0 / image_size)
    idx = frags.idx[0]
    hit = idx >= 0
    seen = idx[hit]
    R, T = camera.R[0], camera.T[0]
    normals = surface.normals[seen] @ R
    to_camera = -(surface.points[seen] @ R + T)
    normals = normals * torch.where((normals * to_camera).sum(-1, keepdim=True) < 0, -1.0, 1.0)  # two-sided
    lambert = (normals @ view.light).clamp(min=0.0)  # cosine law
    shade = view.ambient + (1.0 - view.ambient) * lambert
    colour = (surface.palette[surface.material[seen].long()] * shade[:, None]).clamp(0.0, 1.0)
    image = torch.full((image_size, image_size, 3), view.background)
    image[hit] = colour
    return Rendering(
        image=image.permute(2, 0, 1).contiguous(),
        mask=hit[None].float(),
        depth=frags.zbuf[0][None],
        camera=camera[0],
        view_cameras=view_cameras,
    )


def select_categories(requested: tuple[str, ...], available: tuple[str, ...], source: str) -> tuple[str, ...]:
    """``requested`` (``data.categories``) checked against what ``source`` has; all of them when empty."""
    unknown = [c for c in requested if c not in available]
    if unknown:
        raise ValueError(f"data.categories: {unknown} not in {source}; allowed: {', '.join(available)}")
    if len(set(requested)) != len(requested):
        raise ValueError(f"data.categories: {list(requested)} names a category twice; list each once")
    return requested or available


def interleave(per_category: list[list[tuple[str, str]]]) -> list[tuple[str, str]]:
    """Round-robin over categories (first object of each, then the second, ...), so any prefix of a
    data set covers every category evenly (evaluation and the category-mean oracle read prefixes)."""
    longest = max((len(refs) for refs in per_category), default=0)
    return [refs[i] for i in range(longest) for refs in per_category if i < len(refs)]


def _object_entropy(seed: int, object_id: str) -> list[int]:
    digest = hashlib.sha256(object_id.encode()).digest()
    return [seed % 2**64, int.from_bytes(digest[:16], "little")]


class ObjectDataset(Dataset, ABC):
    """A data set of objects each seen through :func:`render_view`; a ``Dataset[Sample]``.

    Subclasses name their objects (:meth:`_object_ids`) and build or load their shapes
    (:meth:`_shape`). Surfaces are cached in memory (least recently used first out, within
    ``cache_bytes``), so a repeated object costs only its rendering.

    Views: ``val`` shows each object from one fixed view. ``train`` draws the view from the object
    and the current view round (:meth:`set_epoch`, default 0): the same in every process for the
    same round, fresh in each round. :meth:`sample` takes any round explicitly.
    """

    kind: ClassVar[str]
    captured: ClassVar[bool] = False
    """Objects read from captured input views (named by sequence position), not rendered views."""

    def __init__(self, cfg: Config, split: Split, cache_bytes: int = 512 * 2**20):
        if split not in ("train", "val"):
            raise ValueError(f"split must be 'train' or 'val', got {split!r}")
        self.cfg = cfg
        self.split: Split = split
        self.objects: tuple[ObjectRef, ...] = tuple(ObjectRef(*ref) for ref in self._object_ids())
        self.num_views = cfg.priors.num_views if cfg.priors.prior_3d else 1
        self.num_dense = dense_point_count(cfg.data.image_size)
        self.cache_bytes = cache_bytes
        self.epoch = 0
        self._cache: ByteLRU = ByteLRU(cache_bytes)
        d = cfg.data
        from_folder = d.input_source == "folder" or (d.condition_views and d.condition_source == "folder")
        self.condition_images = (
            ConditionImages(d.condition_folder, d.condition_grey, by_position=self.captured)
            if from_folder else None
        )

    @classmethod
    @abstractmethod
    def categories(cls, cfg: Config) -> tuple[str, ...]:
        """Categories of this data set selected by ``cfg.data.categories`` (ValueError if unknown)."""

    @abstractmethod
    def _object_ids(self) -> list[tuple[str, str]]:
        """``(category, object_id)`` of each object of ``self.split``, in index order (see :func:`interleave`)."""

    @abstractmethod
    def _shape(self, index: int, rng: np.random.Generator) -> Shape:
        """Build or load object ``index`` (``rng`` is its own shape stream)."""

    @abstractmethod
    def frame(self, category: str) -> Frame:
        """The frame clouds and cameras of ``category`` are handed out in (:mod:`cdm.normalise`): fixed by
        the data set and the category, never by one object's ground truth."""

    def fingerprint(self) -> str:
        """Short hash naming the exact objects this split yields, for reproducibility records.

        Covers the kind, the ``data`` config, the object ids, :meth:`_content_version` (what else
        decides the objects' content: the generator's version, the files' sizes) and the frames' version.
        """
        identity = [self.kind, self.split, self.cfg.data.model_dump(mode="json"), [list(o) for o in self.objects],
                    self._content_version(), f"frame {FRAME_VERSION}"]
        # Unsorted, as recorded on every run so far: `cdm-lab rerun` compares against those records.
        return json_digest(identity, sort_keys=False)

    def _content_version(self) -> str:
        """Subclasses whose content is not fixed by their object ids and config say what fixes it."""
        return ""

    def __len__(self) -> int:
        return len(self.objects)

    def __getitem__(self, index: int) -> Sample:
        return self.sample(index, self.epoch if self.split == "train" else 0)

    def set_epoch(self, epoch: int) -> None:
        """Select the view round of training samples (held-out views never change)."""
        self.epoch = int(epoch)

    def _rng(self, index: int, *stream: int) -> np.random.Generator:
        entropy = _object_entropy(self.cfg.data.seed, self.objects[index].object_id)
        return np.random.default_rng(np.random.SeedSequence(entropy, spawn_key=stream))

    def surface(self, index: int) -> ObjectSurface:
        """The normalised, sampled object ``index`` (cached, least recently used out beyond ``cache_bytes``;
        captured data sets return their :class:`~cdm.data.cache.ObjectRecord` instead)."""
        return self._cache.get(index, lambda: self._load_surface(index))

    def _load_surface(self, index: int) -> ObjectSurface:
        shape = self._shape(index, self._rng(index, _STREAM_SHAPE))
        palette = draw_palette(self._rng(index, _STREAM_PALETTE), max(2, int(shape.material.max(initial=0)) + 1))
        rng = self._rng(index, _STREAM_SURFACE)
        frame = self.frame(self.objects[index].category)
        return sample_surface(shape, frame, self.cfg.data.num_points, self.num_dense, rng, palette)

    def _check_sample_args(self, index: int, view_round: int) -> None:
        if not 0 <= index < len(self.objects):
            raise IndexError(f"index {index} out of range for {len(self.objects)} objects")
        if view_round < 0:
            raise ValueError(f"view_round (epoch) must be >= 0, got {view_round}")

    def sample(self, index: int, view_round: int = 0) -> Sample:
        """Object ``index`` seen from its view of ``view_round`` (a pure function of both)."""
        self._check_sample_args(index, view_round)
        surface = self.surface(index)
        view = self.drawn_view(index, view_round)
        r = render_view(surface, view, self.cfg.data.image_size, self.num_views)
        ref = self.objects[index]
        image, d = r.image, self.cfg.data
        if d.input_source == "folder":  # a generated input image (Table 8 rows 4, 6, 7)
            image = self.condition_images.read(ref.object_id, view_round, 0, d.image_size)
        return Sample(
            image=image,
            mask=r.mask,
            depth=r.depth,
            prior_2d=prior_2d_channels(self.cfg.priors.prior_2d, image, r.mask, r.depth),
            camera=r.camera,
            view_cameras=r.view_cameras,
            points=surface.cloud,
            category=ref.category,
            object_id=ref.object_id,
            conditions=self._conditions(index, surface, view, view_round)
            if self.split == "train" and d.condition_views
            else None,
        )

    def drawn_view(self, index: int, view_round: int) -> View:
        """The random view of object ``index`` in ``view_round`` (what :meth:`sample` renders)."""
        return draw_view(self._rng(index, _STREAM_VIEW, view_round))

    def _conditions(self, index: int, surface: ObjectSurface, view: View, view_round: int) -> ConditionViews:
        """Views 1…k of k + 1 evenly spaced in azimuth around the input view (``data.condition_views``)."""
        d = self.cfg.data
        k = d.condition_views
        turned = [view._replace(azim=view.azim + 360.0 * j / (k + 1)) for j in range(1, k + 1)]
        renders = [render_view(surface, v, d.image_size, 1) for v in turned]
        generated = None
        if d.condition_source == "folder":
            generated = [
                self.condition_images.read(self.objects[index].object_id, view_round, j, d.image_size)
                for j in range(1, k + 1)
            ]
        return condition_views(renders, generated, self.shown_conditions(index, view_round), self.cfg.priors.prior_2d)

    def shown_conditions(self, index: int, view_round: int) -> int:
        """How many of the ``data.condition_views`` extra views a training sample uses (1…k drawn
        per sample and round with ``data.condition_views_random``)."""
        d = self.cfg.data
        if not d.condition_views_random:
            return d.condition_views
        return int(self._rng(index, _STREAM_CONDITIONS, view_round).integers(1, d.condition_views + 1))
