"""A folder of meshes as a data set: one sub-folder per category, any of .obj .ply .off .stl .glb.

Layout: ``<data.root>/<category>/**/<name>.<ext>`` (files may sit in nested folders, e.g. ShapeNet's
``<model>/models/model_normalized.obj``). Multi-part files (a glTF scene) are merged into one mesh
with their node transforms applied. Each mesh is sampled and rendered exactly as the procedural shapes
are (:mod:`cdm.data.views`), in its category's frame: the union bounding box of the category's
*training* meshes onto ``[-1, 1]`` (:func:`cdm.normalise.box_frame`), so every file keeps its own size
and place and no held-out file shapes the frame; it gets the main colour of its palette.

Split: per category, files are ranked by a hash of their path inside the category folder and the
first 10 % (at least one) are held out. The split depends on file names only — not on
``data.seed`` or on the other files — so a file stays in its split when the folder grows.
Every mesh of the split is loaded once when the data set is built, so a broken file fails at once.
"""

from __future__ import annotations

import hashlib
import math
from functools import lru_cache
from pathlib import Path

import numpy as np

from cdm.config import Config
from cdm.data.views import ObjectDataset, Shape, Split, interleave, select_categories
from cdm.io.meshes import read_mesh
from cdm.normalise import Frame, box_frame

__all__ = ["MESH_SUFFIXES", "VAL_FRACTION", "MeshFolderDataset"]

MESH_SUFFIXES = (".glb", ".obj", ".off", ".ply", ".stl")
"""File types read (case-insensitive), all through trimesh."""

VAL_FRACTION = 0.1
"""Share of each category's meshes held out (at least one)."""

def _root(cfg: Config) -> Path:
    if cfg.data.root is None:
        raise ValueError("data.root must name a folder of meshes (one sub-folder per category) when data.kind='meshes'")
    root = Path(cfg.data.root).expanduser()
    if not root.is_dir():
        raise ValueError(
            f"data.root: {root} is not a readable folder; point it at a folder with one sub-folder per category"
        )
    return root


def _mesh_files(folder: Path) -> list[Path]:
    try:
        return sorted(p for p in folder.rglob("*") if p.suffix.lower() in MESH_SUFFIXES and p.is_file())
    except OSError as exc:
        raise ValueError(f"data.root: cannot list {folder}: {exc.strerror}") from None


@lru_cache(maxsize=4096)
def _bounds(path: Path, stamp: tuple[int, int]) -> np.ndarray:
    """``(2, 3)`` bounding box of the mesh at ``path`` (once per process and file version: ``stamp`` = size, mtime)."""
    return np.asarray(read_mesh(path, "data.root").bounds, dtype=np.float64)


def _held_out(files: list[Path], folder: Path) -> set[Path]:
    ranked = sorted(files, key=lambda p: hashlib.sha256(p.relative_to(folder).as_posix().encode()).hexdigest())
    return set(ranked[: max(1, math.floor(VAL_FRACTION * len(files) + 0.5))])


class MeshFolderDataset(ObjectDataset):
    """Meshes under ``data.root``; object ids ``meshes/<category>/<path inside the category folder>``."""

    kind = "meshes"

    def __init__(self, cfg: Config, split: Split, cache_bytes: int = 512 * 2**20):
        root = _root(cfg)
        self._files: dict[str, Path] = {}
        self._frames: dict[str, Frame] = {}
        per_category = []
        for category in self.categories(cfg):
            folder = root / category
            files = _mesh_files(folder)
            if len(files) < 2:
                raise ValueError(
                    f"data.root: category folder {folder} has {len(files)} mesh file(s); each category needs at "
                    "least 2 (one per split)"
                )
            held_out = _held_out(files, folder)
            self._frames[category] = box_frame(
                _bounds(p, (p.stat().st_size, p.stat().st_mtime_ns)) for p in files if p not in held_out
            )
            chosen = [p for p in files if (p in held_out) == (split == "val")]
            refs = [(category, f"meshes/{category}/{p.relative_to(folder).as_posix()}") for p in chosen]
            self._files.update({object_id: path for (_, object_id), path in zip(refs, chosen, strict=True)})
            per_category.append(refs)
        self._per_category = per_category
        super().__init__(cfg, split, cache_bytes)
        for index in range(len(self)):
            self.surface(index)

    @classmethod
    def categories(cls, cfg: Config) -> tuple[str, ...]:
        """Sub-folders of ``data.root`` that hold mesh files, filtered by ``data.categories``."""
        root = _root(cfg)
        try:
            folders = sorted(p for p in root.iterdir() if p.is_dir())
        except OSError as exc:
            raise ValueError(f"data.root: cannot list {root}: {exc.strerror}") from None
        found = tuple(p.name for p in folders if _mesh_files(p))
        if not found:
            raise ValueError(
                f"data.root: {root} has no category sub-folder with mesh files ({', '.join(MESH_SUFFIXES)}); "
                "expected <root>/<category>/<mesh files>"
            )
        return select_categories(cfg.data.categories, found, f"data.root {root}")

    def _object_ids(self) -> list[tuple[str, str]]:
        return interleave(self._per_category)

    def _content_version(self) -> str:
        # Sizes and modification times: cheap, and they change when a mesh file is replaced.
        stats = [(oid, p.stat().st_size, p.stat().st_mtime_ns) for oid, p in sorted(self._files.items())]
        return hashlib.sha256(repr(stats).encode()).hexdigest()

    def frame(self, category: str) -> Frame:
        return self._frames[category]

    def _shape(self, index: int, rng: np.random.Generator) -> Shape:
        mesh = read_mesh(self._files[self.objects[index].object_id], "data.root")
        return Shape(mesh, np.zeros(len(mesh.faces), dtype=np.int64))
