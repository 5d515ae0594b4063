"""Seeds until settled on Ray Tune's machinery: a ``Searcher`` proposing ``{"cell": <trial label>}``, the grid's
own Tune config, so each seed is built, named and tracked as a grid trial (one MLflow child run per seed).

It keeps no results of its own: per-object scores are read from each finished trial's MLflow run
(:meth:`sweeps.store.sweep_run.SweepRun.trial_objects`), after ``--resume`` too, so a restored searcher needs
from Tune's snapshot only what it had proposed and the time spent (JSON, no pickle): no seed runs twice, none is
lost. Concurrency is Tune's ``ConcurrencyLimiter``.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from pathlib import Path
from typing import Any

from ray.tune.search import Searcher

from cdm.io.files import read_bounded, read_from
from cdm.io.json import parse_json
from cdm.io.write import write_atomic
from sweeps.execute.settle.rule import BUDGET_TAG, Round, next_round, object_scores
from sweeps.plan.budget import SeedBudget
from sweeps.plan.trials import SweepPlan
from sweeps.store.files import StoreError, location_filesystem
from sweeps.store.read import last_objects
from sweeps.store.sweep_run import SweepRun

__all__ = ["MAX_STATE_BYTES", "SeedSearcher", "check_searcher_state"]

MAX_STATE_BYTES = 4 * 2**20
"""Most bytes of a searcher state file (a proposal is ~60 bytes; a sweep has at most a few thousand)."""
_STATE_GLOB = "seed-searcher-*.json"
_FRESH_START = ("without it a finished seed could run again: start the sweep again in a new folder (finished trials "
                "stay in MLflow)")


def parse_searcher_state(raw: bytes, where: str, plan: SweepPlan) -> tuple[dict[str, str], float]:
    """``(proposed, spent_s)`` of a searcher state file's bytes, every entry checked against ``plan``: a
    trial label of the plan, each proposed once, at most one per label; StoreError naming ``where``."""
    try:
        state = parse_json(raw, "--resume", Path(where))
    except ValueError as exc:
        raise StoreError(f"{exc}; the seed searcher's state is damaged, {_FRESH_START}") from None
    labels = {c.label for c in plan.cells}
    proposed = state.get("proposed") if isinstance(state, dict) else None
    spent = state.get("spent_s") if isinstance(state, dict) else None
    problem = None
    if not isinstance(proposed, dict) or not isinstance(spent, (int, float)) or isinstance(spent, bool):
        problem = "expected {\"proposed\": {trial id: trial label}, \"spent_s\": seconds}"
    elif not (math.isfinite(spent) and 0 <= spent):
        problem = f"spent_s {spent!r} is not a finite number of seconds"
    elif len(proposed) > len(labels):
        problem = f"{len(proposed)} proposals, more than the plan's {len(labels)} trials"
    elif bad := next((v for v in proposed.values() if v not in labels), None):
        problem = f"proposal {str(bad)[:80]!r} is no trial of this sweep"
    elif len(set(proposed.values())) != len(proposed):
        problem = "a trial proposed twice"
    if problem:
        raise StoreError(f"--resume: {where}: the seed searcher's state is damaged ({problem}); {_FRESH_START}")
    return {str(k): str(v) for k, v in proposed.items()}, float(spent)


def check_searcher_state(sweep_dir: str, plan: SweepPlan) -> None:
    """Refuse, before Tune restores it, a sequential sweep's searcher state that is missing, damaged or
    oversized: Tune would log the failure and start a fresh searcher, which runs finished seeds again.

    Reads the file Tune restores (the last by name, ``Searcher.restore_from_dir``) in ``sweep_dir``, a
    local folder or a URI, at most :data:`MAX_STATE_BYTES` of it.

    Raises:
        StoreError: naming the file and what is wrong.
    """
    from pyarrow import fs

    filesystem, folder = location_filesystem(sweep_dir)
    found = sorted(i.path for i in filesystem.get_file_info(fs.FileSelector(folder, allow_not_found=True))
                   if i.type == fs.FileType.File and Path(i.path).match(_STATE_GLOB))
    if not found:
        raise StoreError(f"--resume: {sweep_dir} holds no seed searcher state ({_STATE_GLOB}); {_FRESH_START}")
    where = found[-1]
    info = filesystem.get_file_info(where)
    if info.size > MAX_STATE_BYTES:
        raise StoreError(
            f"--resume: {where} is {info.size} bytes; a seed searcher's state is at most {MAX_STATE_BYTES} "
            f"(damaged or planted); {_FRESH_START}"
        )
    parse_searcher_state(read_from(filesystem, where, "--resume", MAX_STATE_BYTES), where, plan)


class SeedSearcher(Searcher):
    """Proposes a sequential sweep's trials round by round (:meth:`sweeps.execute.settle.UntilSettled.searcher`);
    ``None`` while a round's results are out, ``Searcher.FINISHED`` once every cell has stopped."""

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
        return next_round(self.plan, set(self.proposed.values()), self.results, self.budget, self._check_time())

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
        write_atomic(Path(checkpoint_path), json.dumps({"proposed": self.proposed, "spent_s": self._spent()}),
                     "searcher state")

    def restore(self, checkpoint_path: str) -> None:
        """Proposals from ``checkpoint_path`` (checked as :func:`check_searcher_state` checked it before
        Tune started), results from MLflow: one search over the parent's children, then the scores of
        each finished one (at most one per trial of the plan)."""
        try:
            raw = read_bounded(Path(checkpoint_path), "--resume", MAX_STATE_BYTES)
        except ValueError as exc:
            raise StoreError(f"{exc}; the seed searcher's state is damaged, {_FRESH_START}") from None
        self.proposed, spent = parse_searcher_state(raw, checkpoint_path, self.plan)
        self.spent_before, self.since = spent, time.monotonic()
        self.started_at, self.durations = {}, []
        self.out_of_time = BUDGET_TAG in self.sweep_run.client.get_run(self.sweep_run.run_id).data.tags
        self.results = {}
        children = self._children()
        # A trial whose run the driver closed as FINISHED or FAILED has its result; any other is still to run
        # (Tune re-queues it and reports its end to on_trial_complete).
        for trial_id, label in self.proposed.items():
            child = children.get(trial_id)
            status = None if child is None else child.info.status
            if status == "FAILED":
                self.results[label] = None
            elif status == "FINISHED":
                rows = last_objects(self.sweep_run.client, child.info.run_id)
                self.results[label] = object_scores(rows, self.plan.spec.metric.name) or None

    def _children(self) -> dict[str, Any]:
        """The parent's child runs by trial id, in one query; the child runs of trials Tune's last
        snapshot never saw (started in the second before the driver died) are deleted: the rule starts
        their seeds again, and each seed keeps one child run."""
        client, run = self.sweep_run.client, self.sweep_run
        children = client.search_runs([run.experiment_id], max_results=10_000,
                                      filter_string=f"tags.mlflow.parentRunId = '{run.run_id}'")
        kept = {}
        for child in children:
            if "rerun_of" in child.data.tags:
                continue
            if (trial_id := child.data.tags.get("trial_id")) in self.proposed:
                kept.setdefault(trial_id, child)  # newest first, as MLflow orders a search
            else:
                client.delete_run(child.info.run_id)
        return kept
