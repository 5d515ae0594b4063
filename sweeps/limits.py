"""Caps on what one sweep may ask of the machine, checked before anything is allocated or started.

- :func:`load_yaml`: spec and profile files are read with a size cap, must be UTF-8, and YAML
  aliases may not expand the document past :data:`MAX_YAML_NODES` nodes (a 330-byte "billion
  laughs" anchor chain would otherwise grow to gigabytes inside ``yaml.safe_load``).
- :func:`check_trials`: at most ``--max-cells`` trials (default :data:`MAX_TRIALS`), counted from
  the spec's grid, cells and seeds before a single config is built.
- :func:`check_memory`: a lower-bound estimate of what one trial's training holds in memory (the
  data set's object index, its surface cache, one batch's tensors and activations), refused when
  the trials that run at once would need more than :data:`MEMORY_FRACTION` of this machine's RAM.

Every refusal is a :class:`LimitError` naming the field or file and how to raise the cap.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

if TYPE_CHECKING:
    from cdm.config import Config

__all__ = [
    "MAX_TRIALS",
    "MAX_YAML_BYTES",
    "MAX_YAML_NODES",
    "MEMORY_FRACTION",
    "LimitError",
    "check_memory",
    "check_trials",
    "estimate_trial_bytes",
    "load_yaml",
    "machine_memory",
]

MAX_YAML_BYTES = 1 << 20
"""Largest spec or profiles file read (1 MiB; the repository's specs are a few kB)."""
MAX_YAML_NODES = 100_000
"""Most YAML nodes a document may hold once its aliases are expanded."""
MAX_TRIALS = 1000
"""Default cap on trials per sweep (cells × seeds, or Optuna samples); ``--max-cells N`` raises it."""
MEMORY_FRACTION = 0.8
"""Share of this machine's RAM the concurrent trials' estimated memory may take."""

_SURFACE_CACHE_BYTES = 512 * 2**20  # cdm.data.views.ObjectDataset's default cache budget, per split
_BYTES_PER_OBJECT_ID = 256  # one (category, id string) entry of a data set's object index


class LimitError(ValueError):
    """An input exceeds a cap; the message names the file or field and how to raise the cap."""


def _expanded_size(node: yaml.Node, memo: dict[int, int], active: set[int]) -> int:
    """Nodes under ``node`` with every alias expanded (shared nodes counted once per use)."""
    key = id(node)
    if key in memo:
        return memo[key]
    if key in active:
        raise LimitError("refers to itself through an alias (a recursive anchor)")
    active.add(key)
    if isinstance(node, yaml.SequenceNode):
        children = list(node.value)
    elif isinstance(node, yaml.MappingNode):
        children = [part for pair in node.value for part in pair]
    else:
        children = []
    size = 1
    for child in children:
        size += _expanded_size(child, memo, active)
        if size > MAX_YAML_NODES:
            break
    active.discard(key)
    memo[key] = size
    return size


def load_yaml(path: Path) -> Any:
    """Read a YAML file safely: size-capped, UTF-8, aliases bounded; ``yaml.safe_load``'s result.

    Raises:
        LimitError: the file cannot be read, is too large, is not UTF-8 text, is not YAML, or
            expands past :data:`MAX_YAML_NODES` nodes.
    """
    try:
        size = path.stat().st_size
        if size > MAX_YAML_BYTES:
            raise LimitError(f"{path}: {size} bytes; a spec may be at most {MAX_YAML_BYTES} bytes")
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise LimitError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise LimitError(f"{path}: not UTF-8 text (byte {exc.start}); give a YAML spec file") from None
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        expanded = _expanded_size(node, {}, set())
        if expanded > MAX_YAML_NODES:
            raise LimitError(f"{path}: its aliases (*name) expand to more than {MAX_YAML_NODES} YAML nodes; "
                             "write the values out or use fewer nested aliases")
        return loader.construct_document(node)
    except yaml.YAMLError as exc:
        raise LimitError(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from None
    except RecursionError:
        raise LimitError(f"{path}: nested too deeply to be a spec") from None
    except LimitError as exc:
        if str(exc).startswith(str(path)):
            raise
        raise LimitError(f"{path}: {exc}") from None
    finally:
        loader.dispose()


def check_trials(spec: Any, max_trials: int = MAX_TRIALS) -> None:
    """Refuse a :class:`sweeps.spec.Spec` with more than ``max_trials`` trials, counted without building them
    (typed ``Any``: the spec module reads its files through this one).

    A grid counts (explicit cells or 1) × the product of its value lists × seeds, an upper bound
    when ``exclude`` drops combinations; Optuna counts its largest ``num_samples``.
    """
    if spec.search.kind == "optuna":
        samples = [spec.search.num_samples, *(p.num_samples for p in spec.profiles.values() if p.num_samples)]
        count, what = max(samples), "search.num_samples"
    else:
        count = max(1, len(spec.cells)) * math.prod(len(v) for v in spec.grid.values()) * len(spec.seeds)
        what = "grid × cells × seeds"
    if count > max_trials:
        raise LimitError(f"{what}: {count} trials; a sweep may have at most {max_trials} "
                         f"(pass --max-cells {count} to run it anyway)")


def machine_memory() -> int:
    """This machine's physical memory in bytes."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def estimate_trial_bytes(config: Config, categories: int) -> int:
    """A lower bound of the memory one trial's training holds, in bytes (float32 tensors).

    Counts the object index of both splits, the two splits' surface caches, one batch of input
    images, masks and feature maps, its point features through the widest block, the voxel grids
    of every block and the 3D-prior renderings, activations counted twice for their gradients.
    """
    d, m, p, t = config.data, config.model, config.priors, config.train
    index = (d.train_objects + d.val_objects) * categories * _BYTES_PER_OBJECT_ID
    pixels = d.image_size**2 * (4 + m.feature_dim)
    points = d.num_points * (3 + max(m.widths))
    voxels = sum(w * r**3 for w, r in zip(m.widths, m.voxel_resolutions, strict=True))
    renders = p.num_views * p.render_size**2 if p.prior_3d else 0
    per_object = 4 * 2 * (pixels + points + voxels + renders)
    return index + 2 * _SURFACE_CACHE_BYTES + t.batch_size * per_object


def check_memory(configs: list[Config], concurrent: int, total: int | None = None) -> None:
    """Refuse configs whose ``concurrent`` trials would need more than :data:`MEMORY_FRACTION` of
    ``total`` bytes (default: this machine's RAM)."""
    from cdm.data import list_categories

    total = machine_memory() if total is None else total
    budget = MEMORY_FRACTION * total
    for config in configs:
        need = concurrent * estimate_trial_bytes(config, len(list_categories(config)))
        if need > budget:
            d, t = config.data, config.train
            raise LimitError(
                f"data.train_objects={d.train_objects}, data.num_points={d.num_points}, data.image_size={d.image_size}, "
                f"train.batch_size={t.batch_size}: {concurrent} concurrent trial(s) need at least {need / 2**30:.1f} GiB "
                f"but this machine has {total / 2**30:.1f} GiB ({MEMORY_FRACTION:.0%} usable); lower these sizes "
                "or resources.max_concurrent_trials"
            )
