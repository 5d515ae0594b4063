"""How much memory a training run will hold, checked against this machine's before anything is allocated.

:func:`estimate_train_bytes` is a lower bound (float32): the data set's object index of both
splits, their surface caches, and one batch's input images, masks and feature maps, its point
features through the widest block, the voxel grids of every block and the 3D-prior renderings,
activations counted twice for their gradients. :func:`check_memory` refuses configs whose runs at
once would need more than :data:`MEMORY_FRACTION` of the machine's RAM, so
``data.train_objects=100000000000`` stops with one line instead of growing to gigabytes.
"""

from __future__ import annotations

import os

from cdm.config import Config, ConfigError

__all__ = ["MEMORY_FRACTION", "check_memory", "estimate_train_bytes", "machine_memory"]

MEMORY_FRACTION = 0.8
"""Share of this machine's RAM the estimated memory of the runs at once may take."""

_SURFACE_CACHE_BYTES = 512 * 2**20  # cdm.data.views.ObjectDataset's default cache budget, per split
_BYTES_PER_OBJECT_ID = 256  # one (category, id string) entry of a data set's object index


def machine_memory() -> int:
    """This machine's physical memory in bytes."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def estimate_train_bytes(config: Config, categories: int) -> int:
    """A lower bound of the memory one training run of ``config`` over ``categories`` holds, in bytes."""
    d, m, p, t = config.data, config.model, config.priors, config.train
    index = (d.train_objects + d.val_objects) * categories * _BYTES_PER_OBJECT_ID
    pixels = d.image_size**2 * (4 + m.feature_dim)
    points = d.num_points * (3 + max(m.widths))
    voxels = sum(w * r**3 for w, r in zip(m.widths, m.voxel_resolutions, strict=True))
    renders = p.num_views * p.render_size**2 if p.prior_3d else 0
    per_object = 4 * 2 * (pixels + points + voxels + renders)
    return index + 2 * _SURFACE_CACHE_BYTES + t.batch_size * per_object


def check_memory(configs: list[Config], concurrent: int, total: int | None = None) -> None:
    """Refuse configs whose ``concurrent`` runs would need more than :data:`MEMORY_FRACTION` of
    ``total`` bytes (default: this machine's RAM)."""
    from cdm.data import list_categories

    total = machine_memory() if total is None else total
    budget = MEMORY_FRACTION * total
    for config in configs:
        need = concurrent * estimate_train_bytes(config, len(list_categories(config)))
        if need > budget:
            d, t = config.data, config.train
            raise ConfigError(
                f"data.train_objects={d.train_objects}, data.num_points={d.num_points}, "
                f"data.image_size={d.image_size}, "
                f"train.batch_size={t.batch_size}: {concurrent} run(s) at once need at least {need / 2**30:.1f} GiB "
                f"but this machine has {total / 2**30:.1f} GiB ({MEMORY_FRACTION:.0%} usable); lower these sizes "
                "(in a sweep, or resources.max_concurrent_trials)"
            )
