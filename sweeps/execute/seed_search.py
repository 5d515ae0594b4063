"""Seeds until settled on Ray Tune's own machinery: a ``Searcher`` that proposes each cell's next seed.

The rule is :mod:`sweeps.compare.settle`'s :func:`~sweeps.compare.settle.next_round`; this searcher applies it to the
trials it proposed and the results they logged. It proposes ``{"cell": <trial label>}``, the grid's own
Tune config, so every trial is built, named and tracked as a grid trial is (one MLflow child run per
seed). It keeps no results of its own: per-object scores are read from each finished trial's MLflow run
(:meth:`sweeps.execute.tracking.SweepRun.trial_objects`), and after ``--resume`` from the runs again, so a restored
searcher needs from Tune's snapshot only which trials it had proposed and the time spent (a JSON file, no
pickle of its own): no seed runs twice, none is lost. Concurrency is Tune's: ``max_concurrent_trials``
wraps the searcher in a ``ConcurrencyLimiter``, on 2 CPUs and on a cluster alike.
"""

from __future__ import annotations

import json
import statistics
import time
from typing import Any

from ray.tune.search import Searcher

from sweeps.compare.settle import BUDGET_TAG, Round, next_round, object_scores
from sweeps.execute.tracking import SweepRun, find_trial_run
from sweeps.plan.spec import SeedBudget
from sweeps.plan.trials import SweepPlan

__all__ = ["SeedSearcher"]


class SeedSearcher(Searcher):
    """Proposes the trials of a sequential sweep round by round (module docstring); ``None`` while a round's
    results are out, ``Searcher.FINISHED`` once every cell has stopped.

    Args:
        plan: the expanded sequential sweep (every seed up to ``max`` has its trial label).
        sweep_run: the parent MLflow run, where finished trials' per-object scores are read.
        budget: ``--budget`` (None: until ``max``).
    """

    CKPT_FILE_TMPL = "seed-searcher-{}.json"

    def __init__(self, plan: SweepPlan, sweep_run: SweepRun, budget: SeedBudget | None = None):
        super().__init__(metric=plan.spec.metric.name, mode=plan.spec.metric.mode)
        self.plan, self.sweep_run, self.budget = plan, sweep_run, budget
        self.proposed: dict[str, str] = {}
        """Tune trial id → trial label, in the order proposed."""
        self.results: dict[str, dict[str, float] | None] = {}
        """Trial label → ``object_id → score`` of a finished trial (None: failed or scored nothing), from MLflow."""
        self.spent_before = 0.0
        """Wall seconds the sweep ran before this driver (restored with the proposals)."""
        self.since = time.monotonic()
        self.started_at: dict[str, float] = {}
        self.durations: list[float] = []
        self.out_of_time = False

    def _spent(self) -> float:
        return self.spent_before + time.monotonic() - self.since

    def _check_time(self) -> bool:
        """Whether the wall-time budget has ended: the time spent plus a typical trial's passes it. Noted
        once on the parent run (:data:`BUDGET_TAG`), where a resumed searcher finds it."""
        if self.out_of_time or self.budget is None or self.budget.seconds is None:
            return self.out_of_time
        typical = statistics.median(self.durations) if self.durations else 0.0
        if self._spent() + typical > self.budget.seconds:
            self.out_of_time = True
            self.sweep_run.client.set_tag(self.sweep_run.run_id, BUDGET_TAG, f"{self._spent():.0f}")
        return self.out_of_time

    def current(self) -> Round:
        """The rule applied to what this searcher has proposed and seen finish."""
        left = None if self.budget is None or self.budget.trials is None else self.budget.trials - len(self.proposed)
        return next_round(self.plan, set(self.proposed.values()), self.results, trials_left=left,
                          out_of_time=self._check_time())

    def suggest(self, trial_id: str) -> dict[str, Any] | str | None:
        now = self.current()
        if now.finished:
            return Searcher.FINISHED
        if not now.start:
            return None
        label = now.start[0]
        self.proposed[trial_id] = label
        self.started_at[trial_id] = time.monotonic()
        return {"cell": label}

    def on_trial_complete(self, trial_id: str, result: dict[str, Any] | None = None, error: bool = False) -> None:
        label = self.proposed.get(trial_id)
        if label is None:
            return
        if trial_id in self.started_at:
            self.durations.append(time.monotonic() - self.started_at.pop(trial_id))
        scores = {} if error else object_scores(self.sweep_run.trial_objects(trial_id), self.plan.spec.metric.name)
        self.results[label] = scores or None

    def save(self, checkpoint_path: str) -> None:
        # JSON, not a pickle: a restored searcher reads its proposals here and the results from MLflow.
        with open(checkpoint_path, "w") as out:
            json.dump({"proposed": self.proposed, "spent_s": self._spent()}, out)

    def restore(self, checkpoint_path: str) -> None:
        with open(checkpoint_path) as fh:
            state = json.load(fh)
        labels = {c.label for c in self.plan.cells}
        self.proposed = {str(k): str(v) for k, v in state["proposed"].items() if v in labels}
        self.spent_before, self.since = float(state["spent_s"]), time.monotonic()
        self.started_at, self.durations = {}, []
        self.out_of_time = BUDGET_TAG in self.sweep_run.client.get_run(self.sweep_run.run_id).data.tags
        self.results = {}
        self._drop_unseen_runs()
        for trial_id, label in self.proposed.items():
            if (found := self._finished_record(trial_id)) is not None:
                self.results[label] = found or None

    def _drop_unseen_runs(self) -> None:
        """Delete the child runs of trials Tune's last snapshot never saw (started in the second before the
        driver died): the rule starts their seeds again, and each seed keeps one child run."""
        client, run = self.sweep_run.client, self.sweep_run
        children = client.search_runs([run.experiment_id], max_results=10_000,
                                      filter_string=f"tags.mlflow.parentRunId = '{run.run_id}'")
        for child in children:
            if "rerun_of" not in child.data.tags and child.data.tags.get("trial_id") not in self.proposed:
                client.delete_run(child.info.run_id)

    def _finished_record(self, trial_id: str) -> dict[str, float] | None:
        """Scores of a trial whose MLflow run the driver closed as FINISHED ({} for FAILED); None while it
        is still to run (Tune re-queues it and reports its end to :meth:`on_trial_complete`)."""
        run_id = find_trial_run(self.sweep_run.client, self.sweep_run.experiment_id, self.sweep_run.run_id, trial_id)
        if run_id is None:
            return None
        status = self.sweep_run.client.get_run(run_id).info.status
        if status == "FAILED":
            return {}
        if status != "FINISHED":
            return None
        return object_scores(self.sweep_run.trial_objects(trial_id), self.plan.spec.metric.name)
