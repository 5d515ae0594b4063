"""Caps on what one sweep may ask of the machine, checked before anything is allocated or started: the trial
count, a long dry run's progress (10⁶ cells held 2.9 GB and printed nothing for 120 s) and a ``--set``'s size
(50,000 nested brackets took YAML 93 s to end in a ``RecursionError``). The memory of the trials that run at
once is :func:`cdm.memory.check_memory`'s. Every refusal is a :class:`LimitError` naming the field or file and
how to raise the cap.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from typing import Any, TextIO

from sweeps.plan.spec import Spec

__all__ = [
    "MAX_SET_CHARS",
    "MAX_SET_DEPTH",
    "MAX_TRIALS",
    "LISTED_TRIALS",
    "PROGRESS_EVERY",
    "LimitError",
    "check_progress",
    "check_set_text",
    "check_trials",
    "count_trials",
]

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


def count_trials(spec: Spec) -> tuple[int, str]:
    """Trials of a spec, counted without building them, and what was counted.

    A grid counts (explicit cells or 1) × the product of its value lists × seeds, an upper bound
    when ``exclude`` drops combinations; Optuna counts its largest ``num_samples``.
    """
    if spec.search.sampled:
        samples = [spec.search.num_samples, *(p.num_samples for p in spec.profiles.values() if p.num_samples)]
        return max(samples), "search.num_samples"
    return max(1, len(spec.cells)) * math.prod(len(v) for v in spec.grid.values()) * len(
        spec.seed_values
    ), "grid × cells × seeds"


def check_trials(spec: Spec, max_trials: int = MAX_TRIALS) -> None:
    """Refuse a spec with more than ``max_trials`` trials (:func:`count_trials`)."""
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
