"""Seeds until settled, the rule: which trials a sequential sweep starts next, and where each cell stopped.

A sweep whose spec says ``seeds: {min, max, until: settled}`` (or ``--until-settled``) runs in rounds:

- round 1 trains every cell at its first ``min`` seeds;
- once a cell's seeds and the reference's same seeds (``compare_to``, default the first cell) have
  finished, :func:`sweeps.compare.sequential.decide` looks at their per-object scores (look ``k − min + 1`` of
  ``max − min + 1`` at ``k`` seeds); a settled cell (better, worse, or level within ``settle.margin``)
  stops, an open one gets its next seed, and the reference that seed too, until ``max`` seeds or the
  budget ends (``--budget``: no seed starts once the trials would pass the trial count, or once the time
  spent plus a typical trial's would pass the wall time);
- a cell whose trial (or the reference's) failed, or that was scored on other objects, stops without a
  record: the results table shows why.

:func:`next_round` is that rule as a pure function of what has started and finished. The Tune searcher
(:mod:`sweeps.execute.seed_search`) calls it to propose trials, and the runner calls it on the sweep's outcomes
(:func:`final_round`) for the results table's records, so the table shows the searcher's decisions.
The one fact the outcomes cannot show, that the wall-time budget ended, is a tag on the parent run
(:data:`BUDGET_TAG`). Knows nothing of Ray.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from cdm.metric_names import object_column
from sweeps.compare.bootstrap import UnpairedError
from sweeps.compare.outcomes import TrialOutcome
from sweeps.compare.sequential import FOOTNOTE, SettleRecord, decide
from sweeps.plan.budget import SeedBudget
from sweeps.plan.trials import Cell, SweepPlan
from sweeps.store.files import write_file

__all__ = [
    "BUDGET_TAG",
    "Round",
    "describe_rule",
    "final_round",
    "next_round",
    "object_scores",
    "outcome_results",
    "write_settle_json",
    "settle_json",
]

BUDGET_TAG = "settle.budget_ended"
"""Parent-run tag set when the wall-time budget ends (its value: seconds spent): no seed starts after it."""

Results = Mapping[str, Mapping[str, float] | None]
"""Trial label → its ``object_id → score`` in the spec's metric (None: the trial failed or scored nothing)."""


@dataclass(frozen=True)
class Round:
    """What the rule says now: trials to start, trials still running, and the cells that have stopped."""

    start: tuple[str, ...]
    """Labels of the trials to start now, in plan order."""
    waiting: tuple[str, ...]
    """Labels started and not finished yet."""
    records: dict[str, SettleRecord]
    """Cell name → where it stopped (settled, at ``max`` or by the budget); open cells have none."""

    @property
    def finished(self) -> bool:
        return not self.start and not self.waiting


def object_scores(rows: Iterable[Mapping[str, object]], metric: str) -> dict[str, float]:
    """``object_id → score`` of ``metric`` (``eval/f1``, ``eval/cd/chair``) in a trial's per-object rows
    (``objects.csv``), where the results table reads it; empty when the rows do not hold it."""
    where = object_column(metric)
    if where is None:
        return {}
    column, category = where
    return {str(r["object_id"]): float(r[column]) for r in rows
            if column in r and (category is None or r.get("category") == category)}


def outcome_results(
    plan: SweepPlan, outcomes: Iterable[TrialOutcome]
) -> tuple[set[str], dict[str, dict[str, float] | None]]:
    """(started labels, results) of a finished ``run_sweep``: what :func:`next_round` reads, from the trials'
    outcomes instead of the searcher's memory."""
    started, results = set(), {}
    for o in outcomes:
        started.add(o.label)
        # A trial not run, or stopped before its last step (no scheduler stops one here: the sweep was
        # interrupted), is still to come; a failed one is a result, of no scores.
        if o.status in ("ok", "failed"):
            results[o.label] = object_scores(o.objects, plan.spec.metric.name) or None
    return started, results


def _by_cell(plan: SweepPlan) -> dict[str, list[Cell]]:
    cells: dict[str, list[Cell]] = {}
    for cell in plan.cells:
        cells.setdefault(cell.name, []).append(cell)
    return cells


def next_round(plan: SweepPlan, started: set[str], results: Results, *, trials_left: int | None = None,
               out_of_time: bool = False) -> Round:
    """The sequential rule (module docstring) applied to the trials ``started`` and their ``results``.

    Args:
        trials_left: trials the budget still allows (None: no trial budget); a cell whose next seed (and
            the reference's) would not fit stops with reason ``budget``.
        out_of_time: the wall-time budget has ended: every open cell stops with reason ``budget``.
    """
    rule = plan.sequential
    cells = _by_cell(plan)
    reference = cells[plan.spec.compare_to or next(iter(cells))]
    # Round 1 runs whatever the results; the budget was checked against it before the sweep started.
    start = {c.label: c for trials in cells.values() for c in trials[:rule.min] if c.label not in started}
    records: dict[str, SettleRecord] = {}
    for name, trials in cells.items():
        if trials is reference:
            continue
        k = max(rule.min, sum(c.label in started for c in trials))
        mine, theirs = trials[:k], reference[:k]
        if any(c.label not in results for c in (*mine, *theirs)):
            start.update({c.label: c for c in theirs if c.label not in started})
            continue
        scores = {c.seed: results[c.label] for c in mine}
        against = {c.seed: results[c.label] for c in theirs}
        if any(v is None for v in (*scores.values(), *against.values())):
            continue  # a failed seed ends the comparison; the table shows the failure
        try:
            decision = decide(scores, against, mode=plan.spec.metric.mode, margin=plan.spec.settle.margin,
                              look=k - rule.min + 1, looks=rule.looks)
        except UnpairedError:
            continue  # scored on other objects than the reference: the table says "not paired"
        if decision.settled or k == rule.max:
            records[name] = SettleRecord(k, decision, "settled" if decision.settled else "max", rule.looks)
            continue
        wanted = [c for c in (trials[k], reference[k]) if c.label not in started and c.label not in start]
        if out_of_time or (trials_left is not None and trials_left - len(start) < len(wanted)):
            records[name] = SettleRecord(k, decision, "budget", rule.looks)
            continue
        start.update({c.label: c for c in wanted})
    order = {c.label: i for i, c in enumerate(plan.cells)}
    waiting = tuple(sorted((label for label in started if label not in results), key=order.__getitem__))
    return Round(tuple(sorted(start, key=order.__getitem__)), waiting, records)


def final_round(plan: SweepPlan, outcomes: Iterable[TrialOutcome], budget: SeedBudget | None,
                parent_tags: Mapping[str, str]) -> Round:
    """The rule on a sweep's outcomes, as the searcher last applied it: its records (the results table's),
    and the trials it would still start when the sweep was interrupted. ``parent_tags``: the parent run's
    tags, where the searcher noted the wall-time budget's end (:data:`BUDGET_TAG`)."""
    started, results = outcome_results(plan, outcomes)
    out_of_time = BUDGET_TAG in parent_tags
    left = None if budget is None or budget.trials is None else budget.trials - len(started)
    return next_round(plan, started, results, trials_left=left, out_of_time=out_of_time)


def settle_json(records: Mapping[str, SettleRecord], budget: SeedBudget | None) -> str:
    """The parent run's ``settle.json``: per cell the seeds run, verdict, interval and why it stopped."""
    cells = {name: {"seeds": r.seeds, "verdict": r.decision.verdict, "reason": r.reason, "text": r.text(),
                    "interval": {"mean": r.decision.interval.mean, "low": r.decision.interval.low,
                                 "high": r.decision.interval.high, "objects": r.decision.interval.objects,
                                 "covers": r.decision.interval.covers}}
             for name, r in records.items()}
    return json.dumps({"budget": budget.text() if budget else None, "cells": cells}, indent=2)


def write_settle_json(path: Path, records: Mapping[str, SettleRecord], budget: SeedBudget | None) -> Path:
    """:func:`settle_json` written to ``path``, never through a link planted there, trusted storage or not."""
    write_file(path, settle_json(records, budget))
    return path


def describe_rule(plan: SweepPlan, budget: SeedBudget | None) -> list[str]:
    """The dry-run lines of a sequential sweep: round 1, the worst case, the rule and the budget; none for
    a sweep of fixed seeds."""
    rule, spec = plan.sequential, plan.spec
    if rule is None:
        return []
    cells = len(_by_cell(plan))
    reference = spec.compare_to or plan.cells[0].name
    level = (f" or lies inside ±{spec.settle.margin:g} (level)" if spec.settle.margin
             else " (no settle.margin: no level verdict)")
    return [
        f"search: grid, seeds until settled: round 1 = {cells} cells × {rule.min} seeds = {len(plan.first_round)} "
        f"trials; worst case {plan.num_trials} trials ({cells} cells × {rule.max} seeds, {rule.looks} looks)",
        f"rule: each cell against {reference} on {spec.metric.name}; settled when the interval excludes 0 "
        f"(better/worse){level}; else one more seed, up to {rule.max}",
        f"interval: {FOOTNOTE}",
        f"budget: {budget.text() if budget else f'none (until {rule.max} seeds)'}",
        "trials:",
    ]
