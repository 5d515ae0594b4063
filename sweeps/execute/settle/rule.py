"""The rule of seeds until settled (:mod:`sweeps.execute.settle`) as a pure function of what has started and
finished: the searcher applies it to what it proposed, the runner and the report to a sweep's outcomes."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from cdm.metric_names import object_column
from sweeps.compare.bootstrap import UnpairedError
from sweeps.compare.outcomes import TrialOutcome
from sweeps.compare.sequential import SettleRecord, decide
from sweeps.plan.budget import SeedBudget
from sweeps.plan.trials import Cell, SweepPlan

__all__ = ["BUDGET_TAG", "Results", "Round", "by_cell", "next_round", "object_scores", "outcome_results"]

BUDGET_TAG = "settle.budget_ended"
"""Parent-run tag set when the wall-time budget ends (its value: seconds spent), the one fact a sweep's
outcomes cannot show: no seed starts after it."""

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


def outcome_results(plan: SweepPlan, outcomes: Iterable[TrialOutcome]) -> tuple[set[str], dict[str, dict | None]]:
    """(started labels, results) of a sweep's outcomes, as :func:`next_round` reads them."""
    started, results = set(), {}
    for o in outcomes:
        started.add(o.label)
        # A trial not run, or stopped before its last step (no scheduler stops one here: the sweep was
        # interrupted), is still to come; a failed one is a result, of no scores.
        if o.status in ("ok", "failed"):
            results[o.label] = object_scores(o.objects, plan.spec.metric.name) or None
    return started, results


def by_cell(plan: SweepPlan) -> dict[str, list[Cell]]:
    """Cell name → its trials in seed order."""
    cells: dict[str, list[Cell]] = {}
    for cell in plan.cells:
        cells.setdefault(cell.name, []).append(cell)
    return cells


def next_round(plan: SweepPlan, started: set[str], results: Results, budget: SeedBudget | None = None,
               out_of_time: bool = False) -> Round:
    """The rule (:mod:`sweeps.execute.settle`) applied to the trials ``started`` and their ``results``.

    ``budget``: a cell whose next seed (and the reference's) would pass its trial count stops with reason
    ``budget``; ``out_of_time``: its wall time has ended, and every open cell stops with reason ``budget``.
    """
    rule = plan.sequential
    trials_left = None if budget is None or budget.trials is None else budget.trials - len(started)
    cells = by_cell(plan)
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
