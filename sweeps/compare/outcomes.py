"""How each trial of a sweep ended, and the order a sweep's trials are listed in.

Knows nothing of Ray or MLflow: the runner and the report turn finished trials into
:class:`TrialOutcome` s, :mod:`sweeps.compare.table` aggregates them, and :mod:`sweeps.execute.settle`
decides on them which seeds run next.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Literal

from cdm.config import F1_THRESHOLD

__all__ = ["FINISHED", "Status", "TrialOutcome", "finished", "sweep_order", "unstarted"]

Status = Literal["ok", "stopped", "failed", "pending"]
FINISHED: tuple[Status, ...] = ("ok", "stopped")
"""Statuses whose trial has metrics to aggregate: ran to the end, or stopped early by the scheduler."""


@dataclass(frozen=True)
class TrialOutcome:
    """How one trial ended and its last evaluation's metrics."""

    label: str
    """Unique trial label (the MLflow run name)."""
    cell: str
    """Cell name; trials of one cell at different seeds are aggregated."""
    status: Status
    """``ok`` ran to the end, ``stopped`` early by the scheduler, ``failed`` raised, ``pending`` never ran."""
    metrics: dict[str, float] = field(default_factory=dict)
    paper_label: str | None = None
    paper: dict[str, float] = field(default_factory=dict)
    error: str | None = None
    objects: tuple[dict[str, object], ...] = ()
    """Per-object rows of the last evaluation (``object_id``, ``category``, ``cd``, ``f1``, ``baseline/…``)."""
    f1_threshold: float = F1_THRESHOLD
    """The trial's ``eval.f1_threshold``: what its F1 is labelled with (:func:`cdm.metric_names.label`)."""

    @property
    def finished(self) -> bool:
        """Ran to the end or was stopped early: its last evaluation counts."""
        return self.status in FINISHED


def finished(group: Sequence[TrialOutcome]) -> list[TrialOutcome]:
    """The outcomes of ``group`` whose last evaluation counts, in order."""
    return [o for o in group if o.finished]


def sweep_order(
    labels: Sequence[str] | None, metric: str, mode: Literal["min", "max"]
) -> Callable[[TrialOutcome], float]:
    """Sort key of a sweep's outcomes, as the runner and the report list them: a grid's trials in its
    plan's order ``labels`` (unplanned last); an Optuna sweep's (``labels`` None) best ``metric`` first."""
    if labels is not None:
        order = {label: i for i, label in enumerate(labels)}
        return lambda o: order.get(o.label, len(order))
    sign = 1 if mode == "min" else -1
    return lambda o: sign * o.metrics.get(metric, sign * math.inf)


def unstarted(
    planned: Sequence[str], outcomes: Iterable[TrialOutcome], next_round: Collection[str] | None = None
) -> list[str]:
    """Labels of a grid's ``planned`` trials with no outcome, in plan order: the rows an interrupted sweep
    lists as pending, the runner's table and the report's alike. ``next_round``: a sequential sweep's
    trials its rule would start next (:meth:`sweeps.execute.settle.UntilSettled.final`); the seeds it never
    needed are no trials of it."""
    seen = {o.label for o in outcomes}
    return [label for label in planned if label not in seen and (next_round is None or label in next_round)]
