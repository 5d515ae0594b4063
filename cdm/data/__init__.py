"""Data sets: the common sample format and a registry of data-set kinds.

A data-set kind is one class registered in :data:`DATASETS` under its ``data.kind`` name; it is built
from the resolved :class:`~cdm.config.Config` and a split and yields :class:`~cdm.data.sample.Sample`.
Adding a data set (ShapeNet, Co3D) is one module and one entry here (and the name in ``data.kind``).
"""

from __future__ import annotations

from cdm.config import Config
from cdm.data.co3d import Co3DDataset
from cdm.data.meshes import MeshFolderDataset
from cdm.data.procedural import ProceduralDataset
from cdm.data.sample import Batch, Sample, collate
from cdm.data.shapenet import ShapeNetR2N2Dataset
from cdm.data.views import ObjectDataset, Split

__all__ = ["DATASETS", "Batch", "Sample", "build_dataset", "collate", "list_categories"]

DATASETS: dict[str, type[ObjectDataset]] = {
    ProceduralDataset.kind: ProceduralDataset,
    MeshFolderDataset.kind: MeshFolderDataset,
    ShapeNetR2N2Dataset.kind: ShapeNetR2N2Dataset,
    Co3DDataset.kind: Co3DDataset,
}
"""Data-set classes by ``data.kind``."""


def _kind(cfg: Config) -> type[ObjectDataset]:
    if cfg.data.kind not in DATASETS:
        raise ValueError(f"data.kind: unknown data set {cfg.data.kind!r}; allowed: {', '.join(DATASETS)}")
    return DATASETS[cfg.data.kind]


def build_dataset(cfg: Config, split: Split) -> ObjectDataset:
    """The ``split`` (``"train"`` or ``"val"``) of the data set ``cfg.data`` describes; a ``Dataset[Sample]``.

    Raises:
        ValueError: unknown kind or category, a missing, empty or unreadable ``data.root``, a broken
            mesh file (named); the message names the config field.
    """
    return _kind(cfg)(cfg, split)


def list_categories(cfg: Config) -> tuple[str, ...]:
    """Categories the configured data set will use (``data.categories`` or all it has)."""
    return _kind(cfg).categories(cfg)
