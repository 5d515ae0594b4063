"""Data sets: the common sample format and a registry of data-set kinds.

A data-set kind is one class named by its entry in :data:`cdm.registry.DATA_SETS` under its ``data.kind``
name; it is built from the resolved :class:`~cdm.config.Config` and a split and yields
:class:`~cdm.data.sample.Sample`. Adding a data set is one module, its entry there and its name in
:data:`cdm.config.DataKind`, the list of kinds a config accepts (docs/ARCHITECTURE.md, "Where a change goes").
"""

from __future__ import annotations

from cdm.config import Config
from cdm.data.sample import Batch, Sample, collate
from cdm.data.views import ObjectDataset, Split
from cdm.registry import DATA_SETS, load

__all__ = ["DATASETS", "Batch", "Sample", "build_dataset", "collate", "list_categories"]

DATASETS: dict[str, type[ObjectDataset]] = {kind: load(entry.builder) for kind, entry in DATA_SETS.items()}
"""Data-set classes by ``data.kind``: each entry's builder in :data:`cdm.registry.DATA_SETS`."""


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
