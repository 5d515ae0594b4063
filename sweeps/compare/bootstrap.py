"""Paired comparison of sweep cells scored on the same objects: mean difference, bootstrap interval, verdict.

Every cell is evaluated on the same held-out objects with the same sampling seed (``cdm.evaluate.EvalSet``'s
fingerprint records that), so the difference of two cells on one object cancels how hard that object is, most of
the spread between objects; a 95% percentile bootstrap over objects says whether an effect is larger than its
noise. Seeds of one cell are averaged per object first: they add precision, not pairs. Plain rows
(``objects.csv`` of a trial's last evaluation), no Ray, no MLflow.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

__all__ = ["PairedDifference", "UnpairedError", "compare", "interval_text", "paired_bootstrap", "per_object_means"]

Verdict = Literal["better", "worse", "no clear difference"]


class UnpairedError(ValueError):
    """Two cells were evaluated on different objects; a paired difference would mean nothing."""


@dataclass(frozen=True)
class PairedDifference:
    """``mean`` of per-object differences (cell − reference) with its bootstrap interval ``[low, high]``."""

    mean: float
    low: float
    high: float
    n: int
    """Objects paired."""
    clipped: bool = False
    """The interval reached past the values the Δ can take and was cut to them (:meth:`within`)."""

    def within(self, bounds: tuple[float, float] | None) -> PairedDifference:
        """This difference with its interval cut to ``bounds`` (the values the Δ can take; None: no bound),
        marked ``clipped`` where it reached past them."""
        if bounds is None or (bounds[0] <= self.low and self.high <= bounds[1]):
            return self
        low, high = max(self.low, bounds[0]), min(self.high, bounds[1])
        return PairedDifference(self.mean, low, high, self.n, clipped=True)

    def verdict(self, mode: Literal["min", "max"]) -> Verdict:
        """``better`` when the whole interval lies on the good side of 0 for ``mode``, ``worse`` on the bad."""
        if self.high < 0.0 or self.low > 0.0:
            improved = (self.high < 0.0) == (mode == "min")
            return "better" if improved else "worse"
        return "no clear difference"

    def text(self) -> str:
        return interval_text(self.mean, self.low, self.high)


def interval_text(mean: float, low: float, high: float) -> str:
    """``+1.10 [+0.39, +1.87]``: 3 decimals when both ends are within ±1 (F1-like), else 2 (CD-like)."""
    digits = 3 if max(abs(low), abs(high)) <= 1 else 2
    return f"{mean:+.{digits}f} [{low:+.{digits}f}, {high:+.{digits}f}]"


def paired_bootstrap(
    cell: Sequence[float], reference: Sequence[float], resamples: int = 2000, level: float = 0.95, seed: int = 0
) -> PairedDifference:
    """Mean of ``cell − reference`` over paired objects and its percentile bootstrap interval.

    Each of ``resamples`` draws takes ``n`` objects with replacement (one ``rng.integers`` call of
    shape ``(resamples, n)`` from ``numpy.random.default_rng(seed)``), so the interval is reproducible.
    """
    d = np.asarray(cell, dtype=float) - np.asarray(reference, dtype=float)
    if d.ndim != 1 or d.size == 0:
        raise ValueError(f"paired_bootstrap: need two equal-length, non-empty 1-D samples (got {d.shape})")
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, d.size, size=(resamples, d.size))].mean(axis=1)
    tail = (1.0 - level) / 2.0
    low, high = np.quantile(means, [tail, 1.0 - tail])
    return PairedDifference(float(d.mean()), float(low), float(high), int(d.size))


def per_object_means(trials: Iterable[Sequence[Mapping[str, object]]], key: str) -> dict[str, float]:
    """``object_id → mean of row[key]`` over the trials (seeds) of one cell; objects every trial scored.

    Rows carrying an ``eval_set`` fingerprint are keyed ``<object_id>@<eval_set>``, so the same id
    scored under different evaluation settings never pairs.
    """
    values: dict[str, list[float]] = {}
    count = 0
    for rows in trials:
        count += 1
        for row in rows:
            oid = str(row["object_id"]) + (f"@{row['eval_set']}" if row.get("eval_set") else "")
            values.setdefault(oid, []).append(float(row[key]))
    return {oid: float(np.mean(v)) for oid, v in values.items() if len(v) == count}


def compare(
    cell: Mapping[str, float], reference: Mapping[str, float], names: tuple[str, str], seed: int = 0
) -> PairedDifference:
    """Paired difference of two ``object_id → score`` maps (from :func:`per_object_means`).

    Raises:
        UnpairedError: the two were not scored on the same objects (``names`` label the message).
    """
    if set(cell) != set(reference):
        only = sorted(set(cell) ^ set(reference))
        raise UnpairedError(
            f"{names[0]} and {names[1]} were evaluated on different objects ({len(only)} not shared, e.g. "
            f"{only[0]}); a paired comparison needs the same evaluation set"
        )
    ids = sorted(cell)
    return paired_bootstrap([cell[i] for i in ids], [reference[i] for i in ids], seed=seed)
