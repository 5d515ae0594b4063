"""ShapeNet as the paper uses it: 3D-R2N2 renderings paired with PointFlow's point clouds.

Layout under ``data.root`` (both as published, side by side)::

    ShapeNetRendering/<synset>/<model>/rendering/00.png … 23.png     137×137 RGBA, transparent background
    ShapeNetRendering/<synset>/<model>/rendering/rendering_metadata.txt   one line per image
    ShapeNetCore.v2.PC15k/<synset>/{train,val,test}/<model>.npy       (15000, 3) float surface samples

An object is a PC15k model that also has renderings. Its split is PC15k's folder (``train`` for
training, ``data.eval_split`` held out), unless ``<root>/pc_dict_v2.json`` is there: BDM's split file
(``experiments/data/ShapeNet/pc_dict_v2.json`` in mlpc-ucsd/BDM), R2N2's ``train``/``test`` split →
synset → model → the PC15k folder holding its cloud; with it the splits are R2N2's, as BDM trains and
scores (``data.eval_split: test``). Categories are the 13 R2N2 classes by name
(:data:`SYNSETS`; ``data.categories`` also takes synset ids). The held-out input is view 00; training
draws any of the 24 views per view round, or shows view ``data.train_view`` only (BDM: 00, its
``which_view_from24``; the paper profile's ShapeNet protocol, with ``model.mask_channels: false`` as
BDM's ShapeNet config sets no mask and no distance-transform channel). Clouds and cameras are in BDM's
global normalisation of the category, ``x' = (x_v1 − μ)/σ`` with μ and σ of the training split's clouds
(:mod:`cdm.normalise` gives the formulas and BDM's source), and ``data.num_points`` are drawn from the
cloud (the paper: 4,096).
R2N2 renderings have no depth: use ``priors.prior_2d: contour`` (the default) and, as the paper does
on ShapeNet, ``priors.render_kind: planar``; the depth prior (Table 6) reads estimated maps
(``priors.depth_source: maps``, :mod:`cdm.data.depth_maps`), their ``position`` the view's place in
the azimuth-sorted sequence.

Frames. R2N2 rendered ShapeNetCore **v1** meshes; PC15k samples ShapeNetCore **v2**, whose model frame
is v1's turned and mirrored. As BDM's ShapeNet data set code (``transform_v2_to_v1`` in mlpc-ucsd/BDM
``experiments/dataset/shapenet_r2n2.py``) does before projecting, every PC15k cloud is first mapped
into v1 by :func:`v2_to_v1`, ``(x, y, z)_v1 = (−z, y, −x)_v2``. The map is a reflection (det −1):
without it the cloud is mirrored and turned against its own renderings (ground truth projected with
the input camera then lands inside the mask for about half of its points instead of ~all).

Cameras. Each metadata line is ``azimuth elevation in-plane distance-ratio fov`` (degrees, except the
ratio). They are the cameras PyTorch3D's R2N2 reader computes (``compute_extrinsic_matrix`` and
``R2N2._compute_camera_calibration`` in ``pytorch3d/datasets/r2n2``): distance ``ratio × 1.75``,
looking at the origin with +Y (v1's up) up; in the v1 frame the centre is
``d·(cos e·cos a, sin e, cos e·sin a)``, i.e. :func:`cdm.cameras.look_at_cameras` with
``elev = e`` and ``azim = 90° − a`` (ours puts azimuth 0 on +Z, R2N2 on +X, and turns the other way).
NDC focal 2.1875 (PyTorch3D's ``BLENDER_INTRINSIC``: a 35 mm lens on a 32 mm sensor) whatever the
metadata's fov column says (25 in the published files); the image centre is the principal point.
The prior views are the 24 renderings sorted by azimuth (a turntable sequence).
"""

from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import torch

from cdm.cameras import Cameras, look_at_cameras
from cdm.config import Config
from cdm.data.cache import ObjectRecord, ViewImages
from cdm.data.captured import CapturedDataset, cap_cloud
from cdm.data.views import Split, interleave
from cdm.io.arrays import load_npy
from cdm.io.files import read_bounded
from cdm.io.images import read_image
from cdm.io.json import read_json
from cdm.io.names import PLAIN_NAME, plain_name
from cdm.normalise import Frame, bdm_frame
from cdm.registry import PRIORS_2D

__all__ = [
    "BDM_SPLIT_FILE",
    "DISTANCE_SCALE",
    "R2N2_FOCAL",
    "SYNSETS",
    "ShapeNetR2N2Dataset",
    "r2n2_cameras",
    "v2_to_v1",
]

SYNSETS = {
    "02691156": "airplane", "02828884": "bench", "02933112": "cabinet", "02958343": "car", "03001627": "chair",
    "03211117": "display", "03636649": "lamp", "03691459": "loudspeaker", "04090263": "rifle", "04256520": "sofa",
    "04379243": "table", "04401088": "telephone", "04530566": "watercraft",
}
"""The 13 R2N2 classes: synset id → category name."""
_NAMES = {name: synset for synset, name in SYNSETS.items()}

R2N2_FOCAL = 35.0 / 16.0
"""NDC focal of the R2N2 renderings: 2 × 35 mm lens / 32 mm sensor."""
DISTANCE_SCALE = 1.75
"""Camera distance per unit of the metadata's distance ratio (world units of the model frame)."""

_RENDERINGS, _CLOUDS = "ShapeNetRendering", "ShapeNetCore.v2.PC15k"
_PC15K_SPLITS = ("train", "val", "test")
BDM_SPLIT_FILE = "pc_dict_v2.json"
"""BDM's R2N2 split file, read from ``data.root`` when present (module docstring)."""


def v2_to_v1(points: np.ndarray) -> np.ndarray:
    """``(P, 3)`` points of the ShapeNetCore v2 model frame (PC15k) in v1's (R2N2's): ``(−z, y, −x)``.

    BDM's ``transform_v2_to_v1``. Its own inverse (applying it twice gives the input back).
    """
    return np.stack([-points[:, 2], points[:, 1], -points[:, 0]], axis=1)


def r2n2_cameras(metadata: np.ndarray) -> torch.Tensor:
    """``(V, 3)`` (elevation °, azimuth ° in our convention, distance) of metadata rows ``(V, 5)``."""
    return torch.tensor(
        np.stack([metadata[:, 1], 90.0 - metadata[:, 0], metadata[:, 3] * DISTANCE_SCALE], 1), dtype=torch.float32
    )


def _read_metadata(path: Path) -> np.ndarray:
    """``(V, 5)`` rows of ``rendering_metadata.txt``; ValueError naming the file if malformed."""
    if not path.exists():
        raise ValueError(f"data.root: {path} does not exist; expected 24 lines of 5 numbers")
    try:
        text = read_bounded(path, "data.root").decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"data.root: {path} is not UTF-8 text; expected 24 lines of 5 numbers") from None
    try:
        rows = np.array([[float(x) for x in line.split()] for line in text.splitlines() if line.strip()])
    except ValueError:
        rows = np.empty((0, 0))
    if rows.ndim != 2 or rows.shape[0] == 0 or rows.shape[1] != 5 or not np.isfinite(rows).all():
        raise ValueError(f"data.root: {path} is malformed; expected one line of 5 numbers per rendering "
                         "(azimuth elevation in-plane distance-ratio fov)")
    if np.any(rows[:, 2] != 0):
        raise ValueError(f"data.root: {path} has a non-zero in-plane rotation, which R2N2 renderings never have")
    return rows


def _read_cloud(npy: Path) -> np.ndarray:
    """``(P, 3)`` float64 PC15k cloud at ``npy`` in the v1 frame; ValueError naming the file if unusable."""
    cloud = load_npy(npy, "data.root")
    if cloud.ndim != 2 or cloud.shape[1] != 3 or len(cloud) == 0 or not np.isfinite(cloud).all():
        raise ValueError(f"data.root: {npy} holds {cloud.shape} values; expected finite (P, 3) points")
    return v2_to_v1(cloud.astype(np.float64))


@lru_cache(maxsize=32)
def _training_frame(npys: tuple[tuple[Path, int], ...]) -> Frame:
    """BDM's frame over the clouds at ``npys`` (one category's training split; each path with its mtime),
    once per process and file version."""
    return bdm_frame(_read_cloud(npy) for npy, _ in npys)


class ShapeNetR2N2Dataset(CapturedDataset):
    """R2N2 renderings + PC15k clouds; object ids ``shapenet/<category>/<model>``."""

    kind = "shapenet_r2n2"
    layout = f"<root>/{_RENDERINGS}/<synset>/<model>/rendering/ and <root>/{_CLOUDS}/<synset>/<split>/<model>.npy"

    def __init__(self, cfg: Config, split: Split, cache_bytes: int = 512 * 2**20):
        if PRIORS_2D[cfg.priors.prior_2d].reads_depth and cfg.priors.depth_source != "maps":
            raise ValueError(
                f"priors.prior_2d: {cfg.priors.prior_2d!r} on ShapeNet needs estimated maps (R2N2 renderings have no "
                "depth): set priors.depth_source=maps and priors.depth_maps, or use 'contour' or 'none'"
            )
        self._models: dict[str, tuple[str, str, str]] = {}
        """object id → (synset, model, PC15k folder)."""
        super().__init__(cfg, split, cache_bytes)

    @classmethod
    def _canonical(cls, names: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(SYNSETS.get(n, n) for n in names)

    @classmethod
    def _raw_categories(cls, root: Path) -> tuple[str, ...]:
        for folder in (root / _RENDERINGS, root / _CLOUDS):
            if not folder.is_dir():
                raise ValueError(f"data.root: {folder} is missing; expected {cls.layout}")
        found = tuple(
            name
            for synset, name in SYNSETS.items()
            if (root / _RENDERINGS / synset).is_dir() and (root / _CLOUDS / synset).is_dir()
        )
        if not found:
            raise ValueError(f"data.root: no R2N2 synset folder (e.g. {root / _CLOUDS / '03001627'}) is in both "
                             f"{_RENDERINGS} and {_CLOUDS} under {root}")
        return found

    def _split_members(self, published: str) -> dict[str, dict[str, str]] | None:
        """BDM's split file's ``synset → model → PC15k folder`` for ``published``, or None without one."""
        path = self.root / BDM_SPLIT_FILE
        if not path.is_file():
            return None
        table = read_json(path, "data.root")
        if not isinstance(table, dict) or not all(isinstance(v, dict) for v in table.values()):
            raise ValueError(f"data.root: {path} is not BDM's split file (split → synset → model → PC15k folder)")
        if published not in table:
            raise ValueError(f"data.eval_split: {path} (BDM's R2N2 split) has splits {sorted(table)}, not "
                             f"{published!r}; BDM scores the R2N2 test split: data.eval_split=test")
        return table[published]

    def _members(self, published: str, synset: str) -> list[tuple[str, str]]:
        """``(model, PC15k folder)`` of each model of split ``published`` in ``synset`` with renderings and a
        cloud; ValueError naming the source if none."""
        members = self._split_members(published)
        if members is None:
            source = self.root / _CLOUDS / synset / published
            if not source.is_dir():
                raise ValueError(f"data.root: {source} is missing; PC15k has {{train,val,test}} folders per synset")
            # Only plain names can be PC15k model ids (hex): "._x.npy" of a macOS archive is no model.
            entries = [(npy.stem, published) for npy in sorted(source.glob("*.npy")) if PLAIN_NAME.fullmatch(npy.stem)]
        else:
            source = self.root / BDM_SPLIT_FILE
            models = members.get(synset, {})
            if not isinstance(models, dict):
                raise ValueError(
                    f"data.root: {source}, split {published!r}, synset {synset}: expected model → PC15k folder"
                )
            entries = sorted(models.items())
            for model, pc_folder in entries:
                where = f"data.root: {source}, split {published!r}, synset {synset}"
                plain_name(model, f"{where}, model")
                if pc_folder not in _PC15K_SPLITS:
                    raise ValueError(
                        f"{where}, model {model}: PC15k folder {str(pc_folder)[:40]!r}; "
                        f"expected one of {', '.join(_PC15K_SPLITS)}"
                    )
        # PC15k has models R2N2 never rendered (and BDM's file names clouds PC15k may lack): skipped.
        found = [(model, pc_folder) for model, pc_folder in entries
                 if (self.root / _RENDERINGS / synset / model / "rendering" / "rendering_metadata.txt").is_file()
                 and (self.root / _CLOUDS / synset / pc_folder / f"{model}.npy").is_file()]
        if not found:
            raise ValueError(f"data.root: no model of {source} has renderings in {self.root / _RENDERINGS / synset}")
        return found

    def _raw_index(self, categories: tuple[str, ...]) -> list[tuple[str, str]]:
        per_category = []
        for name in categories:
            synset = _NAMES[name]
            refs = []
            for model, pc_folder in self._members(self.published, synset):
                object_id = f"shapenet/{name}/{model}"
                self._models[object_id] = (synset, model, pc_folder)
                refs.append((name, object_id))
            per_category.append(refs)
        return interleave(per_category)

    def _paths(self, index: int) -> tuple[Path, Path]:
        synset, model, pc_folder = self._models[self.objects[index].object_id]
        return (
            self.root / _RENDERINGS / synset / model / "rendering",
            self.root / _CLOUDS / synset / pc_folder / f"{model}.npy",
        )

    def frame(self, category: str) -> Frame:
        """BDM's global normalisation of ``category`` (:func:`cdm.normalise.bdm_frame`) over every full
        cloud of its **training** split, v1 frame, for both splits; read once per process."""
        if self.prepared is not None:
            raise ValueError(f"data.root: {self.root} is prepared, its clouds already in the frame; the frame is "
                             "computed from the published tree")
        synset = _NAMES[category]
        npys = [
            self.root / _CLOUDS / synset / folder / f"{model}.npy" for model, folder in self._members("train", synset)
        ]
        return _training_frame(tuple((npy, npy.stat().st_mtime_ns) for npy in npys))

    def _raw_record(self, index: int) -> ObjectRecord:
        rendering, npy = self._paths(index)
        metadata = _read_metadata(rendering / "rendering_metadata.txt")
        frame = self.frame(self.objects[index].category)
        points = frame.points(cap_cloud(_read_cloud(npy), self.objects[index].object_id))
        elev, azim, dist = r2n2_cameras(metadata).unbind(-1)
        cams = look_at_cameras(elev, azim, dist, R2N2_FOCAL)
        T = frame.translation(cams.R, cams.T)
        # The sequence: renderings sorted by azimuth, starting at view 00 (a turntable from the input view).
        order = np.argsort((metadata[:, 0] - metadata[0, 0]) % 360.0, kind="stable")
        position = np.empty_like(order)
        position[order] = np.arange(len(order))
        idx = torch.from_numpy(order)
        sequence = Cameras(cams.R[idx], T[idx], cams.focal[idx], cams.principal[idx])
        return ObjectRecord(points, sequence, torch.from_numpy(position).long(), frame.scale)

    def _raw_view(self, index: int, record: ObjectRecord, view: int, size: int) -> ViewImages:
        path = self._paths(index)[0] / f"{view:02d}.png"
        raw = read_image(path, cv2.IMREAD_UNCHANGED, "data.root")
        if raw is None:
            raise ValueError(f"data.root: cannot read image {path} (missing or corrupt); expected a 137×137 RGBA PNG")
        if raw.ndim != 3 or raw.shape[2] != 4 or raw.dtype != np.uint8:
            raise ValueError(
                f"data.root: {path} is not an 8-bit RGBA PNG (shape {raw.shape}, {raw.dtype}); R2N2 renderings are"
            )
        alpha = raw[..., 3:].astype(np.float32) / 255.0
        # Composite on white, as R2N2 renderings are usually shown; the mask keeps the silhouette.
        rgb = (raw[..., 2::-1].astype(np.float32) * alpha + 255.0 * (1.0 - alpha)).round().astype(np.uint8)
        area = size < raw.shape[0]
        interp = cv2.INTER_AREA if area else cv2.INTER_LINEAR
        image = cv2.resize(rgb, (size, size), interpolation=interp)
        mask = np.where(cv2.resize(raw[..., 3], (size, size), interpolation=interp) > 127, 255, 0).astype(np.uint8)
        return ViewImages(image, mask, None, math.nan, record.sequence[int(record.views[view])])
