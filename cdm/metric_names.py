"""The metric record: each metric's name, function, direction, unit, partner and range, declared once
(:func:`declare`), with the names a training reports and the labels and precision a reader sees them at.

Apart from :mod:`cdm.metrics` and :mod:`cdm.train` (torch), so that the plan stage and the readers of finished
numbers (table, verdicts, report, MLflow) name metrics without importing them. A metric is read everywhere as
``eval/<name>[/<category>]``, ``final/<name>`` in MLflow and ``<name>`` in ``objects.csv``.

The keys are stable (``eval/f1`` whatever ``eval.f1_threshold`` is): runs at different thresholds stay
comparable by name in MLflow, whose keys allow no ``@``. The threshold lives in a run's config, so a label
is made from it (:func:`label`, :func:`f1_at`), never from the default :data:`cdm.config.F1_THRESHOLD`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from cdm.baseline_names import BASELINES

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["CD", "COMPUTE_METRIC", "COMPUTE_UNIT", "F1", "METRICS", "TRAIN_METRICS", "Metric", "declare",
           "delta_range", "f1_at", "f1_unit", "label", "metric_names", "mode", "number_text", "object_column",
           "partner", "rounded"]

TRAIN_METRICS = ("train/loss", "train/loss_diffusion", "train/loss_prior_3d", "train/lr", "train/skipped_steps",
                 "train/steps_per_s", "train/cpu_s_per_step", "train/elapsed_s")
"""What :func:`cdm.train.fit` logs every ``train.log_every`` steps, in this order."""

Thresholds = float | Iterable[float]


@dataclass(frozen=True)
class Metric:
    """``score``: a batch's ``(B, N, 3)`` predicted and ``(B, M, 3)`` true clouds and their
    :class:`cdm.metrics.ChamferF1` → ``(B,)`` scores; ``mode``: which is better; ``unit``: its heading's words,
    from the runs' ``eval.f1_threshold`` values; ``partner``: the metric shown beside it; ``span``: the values
    one score can take (bounding every Δ of means), or None."""

    name: str
    score: Callable[[Tensor, Tensor, Any], Tensor]
    mode: Literal["min", "max"]
    unit: Callable[[Thresholds], str]
    partner: str | None = None
    span: tuple[float, float] | None = None

    @property
    def key(self) -> str:
        """What a training logs it as: ``eval/<name>``."""
        return f"eval/{self.name}"


METRICS: dict[str, Metric] = {}
"""Every metric an evaluation scores, by short name, in the order rows and logs list them."""


def declare(metric: Metric) -> Metric:
    """Add ``metric`` to :data:`METRICS`: evaluation scores it, every reader shows it (``METRICS.pop`` drops it)."""
    METRICS[metric.name] = metric
    return metric

COMPUTE_METRIC = "train/compute_s"
"""Seconds of compute training has spent (``train.compute_budget_s``'s unit: CPU seconds of the training process,
GPU wall seconds on CUDA; evaluation not counted), reported by :func:`cdm.train.fit` with every evaluation."""

COMPUTE_UNIT = "CPU seconds of the trial's process; GPU wall seconds on CUDA; evaluation not counted"
"""What a second of :data:`COMPUTE_METRIC` (and of a budget in compute) is, in words."""


def metric_names(categories: Sequence[str] = ()) -> list[str]:
    """Every metric name :func:`cdm.train.fit` can report (per-category names for the given categories)."""
    names = [*TRAIN_METRICS, COMPUTE_METRIC]
    for prefix in ["eval"] + [f"baseline/{b}" for b in BASELINES]:
        names += [f"{prefix}/{s}" for s in METRICS]
        names += [f"{prefix}/{s}/{c}" for c in categories for s in METRICS]
    return names


def object_column(metric: str) -> tuple[str, str | None] | None:
    """``eval/cd`` → (``cd``, None), ``eval/f1/chair`` → (``f1``, ``chair``): where ``objects.csv`` holds it."""
    parts = metric.split("/")
    if parts[0] != "eval" or len(parts) not in (2, 3) or parts[1] not in METRICS:
        return None
    return parts[1], parts[2] if len(parts) == 3 else None


def partner(metric: str) -> str | None:
    """``eval/f1`` ↔ ``eval/cd``: the other headline metric, shown beside the optimised one."""
    record = METRICS.get(metric.removeprefix("eval/")) if metric.startswith("eval/") else None
    return None if record is None or record.partner is None else METRICS[record.partner].key


def mode(metric: str) -> Literal["min", "max"]:
    """Which way ``eval/<name>[/<category>]`` of a declared metric is better: Chamfer distance lower, F1 higher."""
    return METRICS[metric.split("/")[1]].mode


def delta_range(metric: str) -> tuple[float, float] | None:
    """The values the true Δ (cell − reference) of ``metric`` can take whatever the objects, or None.

    F1 lies in [0, 1], so every Δ of it, and its mean, lies in [−1, 1]: an interval reaching past that has too
    few objects (or seeds) to tell anything and is clipped to it. CD ≥ 0 bounds the true Δ only by minus the
    reference's unknown true mean CD, so a CD interval is never clipped."""
    where = object_column(metric)
    span = None if where is None else METRICS[where[0]].span
    return None if span is None else (span[0] - span[1], span[1] - span[0])


def number_text(value: float, scale: float | None = None) -> str:
    """Every metric's display precision: 3 decimals for F1-like numbers, 2 for CD ×1000-like ones (decided by
    ``scale``, default ``value``)."""
    return f"{value:.3f}" if abs(value if scale is None else scale) < 10 else f"{value:.2f}"


def rounded(value: float) -> float:
    """``value`` at the precision the tables print it (3 decimals below 10, else 2), for text a person reads (a
    run's description); what is logged to MLflow and written to ``results.csv`` stays at full precision."""
    return float(number_text(value)) if math.isfinite(value) else value


def _distinct(thresholds: Thresholds) -> list[float]:
    return sorted({float(thresholds)} if isinstance(thresholds, (int, float)) else {float(t) for t in thresholds})


def _at(values: list[float]) -> str:
    return "F1@" + " / ".join(f"{v:g}" for v in values)


def f1_at(thresholds: Thresholds) -> str:
    """F1's threshold τ (``eval.f1_threshold``) in a few words, on the squared distance and in world units:
    ``F1@0.02 sq. dist = 0.141421 world``; runs at several thresholds name each (``F1@0.01 / 0.25 sq. dist``)."""
    values = _distinct(thresholds)
    if len(values) == 1:
        return f"{_at(values)} sq. dist = {math.sqrt(values[0]):g} world"
    return f"{_at(values)} sq. dist (per cell)"


def f1_unit(thresholds: Thresholds) -> str:
    """The unit every F1 of a table or description is read in: a loose threshold (a blob of the right size
    scores high), so the baselines beside it matter."""
    values = _distinct(thresholds)
    world = " / ".join(f"{math.sqrt(v):g}" for v in values)
    return (f"F1 is {_at(values)} on the squared distance: a point counts when it lies within {world} in world "
            "units of the other cloud (BDM's definition, cdm/metrics.py); CD is ×1000, in world units²")


def label(metric: str, thresholds: Thresholds) -> str:
    """``metric`` with its unit, for axes and headings, F1's from the run's ``eval.f1_threshold``:
    ``eval/f1`` → ``eval/f1 (F1@0.02 sq. dist = 0.141421 world)``, ``eval/cd/chair`` → ``eval/cd/chair
    (CD ×1000)``; any other name as is."""
    parts = metric.split("/")
    record = METRICS.get(parts[1]) if len(parts) >= 2 else None
    return metric if record is None else f"{metric} ({record.unit(thresholds)})"


CD = declare(Metric("cd", lambda pred, gt, chamfer: chamfer.cd, "min", lambda _: "CD ×1000", partner="f1"))
"""Chamfer distance ×1000, world units² (cdm/metrics.py)."""
F1 = declare(Metric("f1", lambda pred, gt, chamfer: chamfer.f1, "max", f1_at, partner="cd", span=(0.0, 1.0)))
"""F-score at ``eval.f1_threshold`` on the squared distance (cdm/metrics.py)."""
