"""Caps on what one sweep may ask of the machine, checked before anything is allocated or started.

- :func:`load_yaml`: spec and profile files are read with a size cap, must be UTF-8, and YAML
  aliases may not expand the document past :data:`MAX_YAML_NODES` nodes (a 330-byte "billion
  laughs" anchor chain would otherwise grow to gigabytes inside ``yaml.safe_load``).
- :func:`check_trials`: at most ``--max-cells`` trials (default :data:`MAX_TRIALS`), counted from
  the spec's grid, cells and seeds before a single config is built (:func:`count_trials`).
- a ``--dry-run`` of more than :data:`LISTED_TRIALS` grid trials checks them one at a time, holding
  and listing only the first, with a :func:`check_progress` line every :data:`PROGRESS_EVERY` (10⁶
  cells held 2.9 GB and printed nothing for 120 s).
- :func:`check_set_text`: a ``--set key=value`` is at most :data:`MAX_SET_CHARS` characters and
  :data:`MAX_SET_DEPTH` brackets deep, checked before YAML parses it (50,000 nested brackets took
  YAML 93 s to end in a ``RecursionError``).
- the memory of the trials that run at once is checked by :func:`cdm.memory.check_memory`.

Every refusal is a :class:`LimitError` naming the field or file and how to raise the cap.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import yaml

from cdm.io.files import BoundedYamlLoader, read_bounded

__all__ = [
    "MAX_SET_CHARS",
    "MAX_SET_DEPTH",
    "MAX_TRIALS",
    "MAX_YAML_BYTES",
    "MAX_YAML_NODES",
    "LISTED_TRIALS",
    "PROGRESS_EVERY",
    "LimitError",
    "check_progress",
    "check_set_text",
    "check_trials",
    "count_trials",
    "load_yaml",
]

MAX_YAML_BYTES = 1 << 20
"""Largest spec or profiles file read (1 MiB; the repository's specs are a few kB)."""
MAX_YAML_NODES = 100_000
"""Most YAML nodes a document may hold once its aliases are expanded."""
MAX_SET_CHARS = 4096
"""Longest ``--set key=value`` (a list of a few hundred categories fits)."""
MAX_SET_DEPTH = 16
"""Deepest bracket (``[``, ``{``) nesting of a ``--set`` value; a config field needs two at most."""
MAX_TRIALS = 1000
"""Default cap on trials per sweep (cells × seeds, or Optuna samples); ``--max-cells N`` raises it."""
LISTED_TRIALS = MAX_TRIALS
"""Most grid trials a ``--dry-run`` holds, lists and estimates (all of a sweep within the default cap); past
it, as ``--max-cells`` allows, the rest are checked one at a time and counted."""
PROGRESS_EVERY = 10_000
"""Trials checked between two progress lines of a long ``--dry-run`` (a few seconds of work)."""


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
        raw = read_bounded(path, str(path), MAX_YAML_BYTES, show_path=False)  # a FIFO or device is refused, not read
    except ValueError as exc:
        raise LimitError(f"{exc}; a spec may be at most {MAX_YAML_BYTES} bytes of YAML") from None
    except OSError as exc:
        raise LimitError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise LimitError(f"{path}: not UTF-8 text (byte {exc.start}); give a YAML spec file") from None
    loader = BoundedYamlLoader(text)
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


def count_trials(spec: Any) -> tuple[int, str]:
    """Trials of a :class:`sweeps.plan.spec.Spec`, counted without building them, and what was counted (typed
    ``Any``: the spec module reads its files through this one).

    A grid counts (explicit cells or 1) × the product of its value lists × seeds, an upper bound
    when ``exclude`` drops combinations; Optuna counts its largest ``num_samples``.
    """
    if spec.search.sampled:
        samples = [spec.search.num_samples, *(p.num_samples for p in spec.profiles.values() if p.num_samples)]
        return max(samples), "search.num_samples"
    return max(1, len(spec.cells)) * math.prod(len(v) for v in spec.grid.values()) * len(
        spec.seed_values
    ), "grid × cells × seeds"


def check_trials(spec: Any, max_trials: int = MAX_TRIALS) -> None:
    """Refuse a :class:`sweeps.plan.spec.Spec` with more than ``max_trials`` trials (:func:`count_trials`)."""
    count, what = count_trials(spec)
    if count > max_trials:
        raise LimitError(f"{what}: {count} trials; a sweep may have at most {max_trials} "
                         f"(pass --max-cells {count} to run it anyway)")


def check_set_text(text: str) -> None:
    """Refuse a ``--set`` text longer than :data:`MAX_SET_CHARS` or nested deeper than :data:`MAX_SET_DEPTH`
    (brackets counted as written, inside quotes too: an upper bound), before any parser reads it."""
    key = text.split("=", 1)[0][:60]
    if len(text) > MAX_SET_CHARS:
        raise LimitError(f"--set {key}=…: {len(text)} characters; a --set may have at most {MAX_SET_CHARS} "
                         "(put long values in a spec's fixed: section)")
    depth = deepest = 0
    for char in text:
        if char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth -= 1
    if deepest > MAX_SET_DEPTH:
        raise LimitError(f"--set {key}=…: brackets nested {deepest} deep; a value may nest at most {MAX_SET_DEPTH}")


def check_progress(total: int, out: TextIO | None = None) -> Callable[[int, Any], None]:
    """An ``each`` for :func:`sweeps.plan.trials.expand`: prints ``checked i/total trials`` every :data:`PROGRESS_EVERY`
    cells to ``out`` (default: ``sys.stdout`` at the time of printing)."""
    def each(i: int, cell: Any) -> None:
        if i % PROGRESS_EVERY == 0:
            print(f"  checked {i}/{total} trials …", file=out or sys.stdout, flush=True)
    return each
