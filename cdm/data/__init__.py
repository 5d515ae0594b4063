"""Data sets: the common sample format and a registry of data-set kinds.

A data-set kind is one class registered in :data:`DATASETS` under its ``data.kind`` name; it is built
from the resolved :class:`~cdm.config.Config` and a split and yields :class:`~cdm.data.sample.Sample`.
Adding a data set (ShapeNet, Co3D) is one module, one entry here and its name in
:data:`cdm.config.DataKind`, the list of kinds a config accepts (so no other kind reaches this registry).
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


def build_dataset(cfg: Config, split: Split) -> ObjectDataset:
    """The ``split`` (``"train"`` or ``"val"``) of the data set ``cfg.data`` describes; a ``Dataset[Sample]``.

    Raises:
        ValueError: unknown category, a missing, empty or unreadable ``data.root``, a broken
            mesh file (named); the message names the config field.
    """
    return DATASETS[cfg.data.kind](cfg, split)


def list_categories(cfg: Config) -> tuple[str, ...]:
    """Categories the configured data set will use (``data.categories`` or all it has)."""
    return DATASETS[cfg.data.kind].categories(cfg)
