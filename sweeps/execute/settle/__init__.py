"""Seeds until settled (``seeds: {min, max, until: settled}`` or ``--until-settled``); :class:`UntilSettled` is
its one entry point. The sweep runs in rounds: round 1 trains every cell at its first ``min`` seeds; once a
cell's seeds and the reference's same seeds (``compare_to``, default the first cell) have finished,
:func:`sweeps.compare.sequential.decide` looks at their per-object scores (look ``k − min + 1`` of
``max − min + 1`` at ``k`` seeds). A settled cell (better, worse, or level within ``settle.margin``) stops;
an open one gets its next seed, the reference that seed too, until ``max`` seeds or the ``--budget`` ends
(no seed starts once the trials would pass its count, or the time spent plus a typical trial's its wall
time). A cell whose trial (or the reference's) failed, or was scored on other objects, stops without a
record: the results table shows why.

Its parts: :mod:`.rule`, that rule as a pure function of what has started and finished, and :mod:`.searcher`,
the Tune ``Searcher`` applying it (Ray is imported only when a sweep runs). Its two inputs sit in the stages
below, which read them on their own: the interval (:mod:`sweeps.compare.sequential`, every comparison over
seeds reads it) and ``--budget`` (:mod:`sweeps.plan.budget`, checked with the request).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from sweeps.compare.outcomes import TrialOutcome
from sweeps.compare.sequential import FOOTNOTE, SettleRecord
from sweeps.execute.settle.rule import BUDGET_TAG, Round, by_cell, next_round, outcome_results
from sweeps.plan.budget import SeedBudget
from sweeps.plan.trials import SweepPlan
from sweeps.store.files import write_file

if TYPE_CHECKING:
    from sweeps.execute.settle.searcher import SeedSearcher
    from sweeps.store.sweep_run import SweepRun

__all__ = ["BUDGET_TAG", "Round", "UntilSettled"]


@dataclass(frozen=True)
class UntilSettled:
    """Seeds until settled for one sweep: ``plan`` (every seed up to ``max`` has its trial label) under
    ``budget`` (``--budget``; None: until ``max``), at each moment the sweep meets it."""

    plan: SweepPlan
    budget: SeedBudget | None = None

    def lines(self) -> list[str]:
        """The dry-run lines: round 1, the worst case, the rule and the budget; none for fixed seeds."""
        rule, spec, plan = self.plan.sequential, self.plan.spec, self.plan
        if rule is None:
            return []
        cells = len(by_cell(plan))
        level = (f" or lies inside ±{spec.settle.margin:g} (level)" if spec.settle.margin
                 else " (no settle.margin: no level verdict)")
        return [
            f"search: grid, seeds until settled: round 1 = {cells} cells × {rule.min} seeds = "
            f"{len(plan.first_round)} trials; worst case {plan.num_trials} trials ({cells} cells × {rule.max} seeds, "
            f"{rule.looks} looks)",
            f"rule: each cell against {spec.compare_to or plan.cells[0].name} on {spec.metric.name}; settled when "
            f"the interval excludes 0 (better/worse){level}; else one more seed, up to {rule.max}",
            f"interval: {FOOTNOTE}",
            f"budget: {self.budget.text() if self.budget else f'none (until {rule.max} seeds)'}",
            "trials:",
        ]

    def check_resume(self, sweep_dir: str) -> None:
        """Refuse a searcher state Tune would restore badly (:func:`.searcher.check_searcher_state`)."""
        from sweeps.execute.settle.searcher import check_searcher_state

        check_searcher_state(sweep_dir, self.plan)

    def searcher(self, sweep_run: SweepRun) -> SeedSearcher:
        """The Tune searcher of a new or resumed sweep, reading scores from ``sweep_run``'s child runs."""
        from sweeps.execute.settle.searcher import SeedSearcher

        return SeedSearcher(self.plan, sweep_run, self.budget)

    def final(self, outcomes: Iterable[TrialOutcome], parent_tags: Mapping[str, str]) -> Round:
        """The rule on a sweep's outcomes, as the searcher last applied it: its records (the results table's),
        and the trials it would still start when the sweep was interrupted. ``parent_tags``: the parent run's
        tags, where the searcher noted the wall-time budget's end."""
        started, results = outcome_results(self.plan, outcomes)
        return next_round(self.plan, started, results, self.budget, BUDGET_TAG in parent_tags)

    def write_json(self, path: Path, records: Mapping[str, SettleRecord]) -> Path:
        """The parent run's ``settle.json`` at ``path`` (never through a link planted there): per cell the
        seeds run, verdict, interval and why it stopped."""
        cells = {name: {"seeds": r.seeds, "verdict": r.decision.verdict, "reason": r.reason, "text": r.text(),
                        "interval": {"mean": r.decision.interval.mean, "low": r.decision.interval.low,
                                     "high": r.decision.interval.high, "objects": r.decision.interval.objects,
                                     "covers": r.decision.interval.covers}}
                 for name, r in records.items()}
        write_file(path, json.dumps({"budget": self.budget.text() if self.budget else None, "cells": cells}, indent=2))
        return path
