"""The names of the metrics a training reports and the labels a reader sees them under: their one home.

Apart from :mod:`cdm.train` (torch and the model), so that the plan stage checks a sweep's metric and the
readers of finished numbers (results table, plots, MLflow descriptions) label them without importing it.

The keys are stable (``eval/f1`` whatever ``eval.f1_threshold`` is): runs at different thresholds stay
comparable by name in MLflow, whose keys allow no ``@``. The threshold lives in a run's config, so a label
is made from it (:func:`label`, :func:`f1_at`), never from the default :data:`cdm.config.F1_THRESHOLD`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

from cdm.baseline_names import BASELINES

__all__ = ["COMPUTE_METRIC", "COMPUTE_UNIT", "SCORES", "TRAIN_METRICS", "f1_at", "f1_unit", "label", "metric_names"]

TRAIN_METRICS = ("train/loss", "train/loss_diffusion", "train/loss_prior_3d", "train/lr", "train/skipped_steps",
                 "train/steps_per_s", "train/cpu_s_per_step", "train/elapsed_s")
"""What :func:`cdm.train.fit` logs every ``train.log_every`` steps, in this order."""

COMPUTE_METRIC = "train/compute_s"
"""Seconds of compute training has spent (``train.compute_budget_s``'s unit: CPU seconds of the training process,
GPU wall seconds on CUDA; evaluation not counted), reported by :func:`cdm.train.fit` with every evaluation."""

COMPUTE_UNIT = "CPU seconds of the trial's process; GPU wall seconds on CUDA; evaluation not counted"
"""What a second of :data:`COMPUTE_METRIC` (and of a budget in compute) is, in words."""

SCORES = ("cd", "f1")
"""What an evaluation scores per shape (:mod:`cdm.metrics`): ``eval/<score>``, ``baseline/<name>/<score>``,
each also per category (``eval/<score>/<category>``)."""


def metric_names(categories: Sequence[str] = ()) -> list[str]:
    """Every metric name :func:`cdm.train.fit` can report (per-category names for the given categories)."""
    names = [*TRAIN_METRICS, COMPUTE_METRIC]
    for prefix in ["eval"] + [f"baseline/{b}" for b in BASELINES]:
        names += [f"{prefix}/{s}" for s in SCORES]
        names += [f"{prefix}/{s}/{c}" for c in categories for s in SCORES]
    return names


def _distinct(thresholds: float | Iterable[float]) -> list[float]:
    return sorted({float(thresholds)} if isinstance(thresholds, (int, float)) else {float(t) for t in thresholds})


def _at(values: list[float]) -> str:
    return "F1@" + " / ".join(f"{v:g}" for v in values)


def f1_at(thresholds: float | Iterable[float]) -> str:
    """F1's threshold τ (``eval.f1_threshold``) in a few words, on the squared distance and in world units:
    ``F1@0.02 sq. dist = 0.141421 world``; runs at several thresholds name each (``F1@0.01 / 0.25 sq. dist``)."""
    values = _distinct(thresholds)
    if len(values) == 1:
        return f"{_at(values)} sq. dist = {math.sqrt(values[0]):g} world"
    return f"{_at(values)} sq. dist (per cell)"


def f1_unit(thresholds: float | Iterable[float]) -> str:
    """The unit every F1 of a table or description is read in: a loose threshold (a blob of the right size
    scores high), so the baselines beside it matter."""
    values = _distinct(thresholds)
    world = " / ".join(f"{math.sqrt(v):g}" for v in values)
    return (f"F1 is {_at(values)} on the squared distance: a point counts when it lies within {world} in world "
            "units of the other cloud (BDM's definition, cdm/metrics.py); CD is ×1000, in world units²")


def label(metric: str, thresholds: float | Iterable[float]) -> str:
    """``metric`` with its unit, for axes and headings, F1's from the run's ``eval.f1_threshold``:
    ``eval/f1`` → ``eval/f1 (F1@0.02 sq. dist = 0.141421 world)``, ``eval/cd/chair`` → ``eval/cd/chair
    (CD ×1000)``; any other name as is."""
    parts = metric.split("/")
    if len(parts) >= 2 and parts[1] == "f1":
        return f"{metric} ({f1_at(thresholds)})"
    if len(parts) >= 2 and parts[1] == "cd":
        return f"{metric} (CD ×1000)"
    return metric
