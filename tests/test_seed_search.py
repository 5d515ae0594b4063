"""The Tune searcher of seeds until settled (sweeps/execute/seed_search.py) against a real MLflow SQLite store, driven
the way Tune drives it (suggest, on_trial_complete, save, restore), without a Ray cluster."""

from __future__ import annotations

import csv
from pathlib import Path

from ray.tune.search import Searcher

from sweeps.compare.settle import BUDGET_TAG
from sweeps.execute.seed_search import SeedSearcher
from sweeps.execute.tracking import SweepRun
from sweeps.plan.spec import SeedBudget, Spec
from sweeps.plan.trials import expand

CELLS = [{"label": "ref"}, {"label": "null", "set": {"eval.save_clouds": 1}}]


def _plan():
    spec = Spec.model_validate({"name": "t", "cells": CELLS, "seeds": {"min": 2, "max": 3, "until": "settled"}})
    return expand(spec, "smoke")


def _finish(sweep_run: SweepRun, trial_id: str, label: str, folder: Path, status: str = "FINISHED") -> None:
    """What a trial and the driver leave in MLflow: a child run with its last evaluation's ``objects.csv``
    (the null cell scores exactly what the reference scores), closed with Tune's verdict."""
    client = sweep_run.client
    run = client.create_run(sweep_run.experiment_id, run_name=label,
                            tags={"mlflow.parentRunId": sweep_run.run_id, "trial_id": trial_id})
    table = folder / trial_id / "objects.csv"
    table.parent.mkdir(parents=True)
    seed = int(label[-1])
    with table.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, ["object_id", "category", "eval_set", "cd", "f1"])
        writer.writeheader()
        writer.writerows({"object_id": f"o{i}", "category": "chair", "eval_set": "e", "cd": 1.0, "f1": 0.1 * i + 0.05 * seed}
                         for i in range(6))
    client.log_artifact(run.info.run_id, str(table), "eval/step_0000010")
    client.set_terminated(run.info.run_id, status)


def _suggest_all(searcher: SeedSearcher, first_id: int) -> dict[str, str]:
    """Ask until the searcher waits, as Tune's loop does; trial id → label proposed."""
    out, i = {}, first_id
    while isinstance(suggestion := searcher.suggest(f"t{i}"), dict):
        out[f"t{i}"] = suggestion["cell"]
        i += 1
    return out


def test_a_restored_searcher_keeps_its_proposals_reads_results_from_mlflow_and_runs_no_seed_twice(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep_run = SweepRun.start(uri, "t", "t", tags={}, params={})
    searcher = SeedSearcher(_plan(), sweep_run)
    first = _suggest_all(searcher, 0)
    assert sorted(first.values()) == ["null · seed 0", "null · seed 1", "ref · seed 0", "ref · seed 1"]
    for trial_id, label in first.items():
        _finish(sweep_run, trial_id, label, tmp_path)
        searcher.on_trial_complete(trial_id, {})
    second = _suggest_all(searcher, 10)
    assert sorted(second.values()) == ["null · seed 2", "ref · seed 2"]  # null is open after round 1
    searcher.save(str(tmp_path / "state.json"))
    # The driver dies: ref · seed 2 had finished, null · seed 2 had not; a trial Tune never saw had opened a run.
    ref_id = next(t for t, label in second.items() if label == "ref · seed 2")
    _finish(sweep_run, ref_id, "ref · seed 2", tmp_path)
    _finish(sweep_run, "unseen", "null · seed 2", tmp_path, status="RUNNING")

    restored = SeedSearcher(_plan(), SweepRun(uri, sweep_run.experiment_id, sweep_run.run_id))
    restored.restore(str(tmp_path / "state.json"))
    assert restored.proposed == {**first, **second}
    assert set(restored.results) == {*first.values(), "ref · seed 2"}  # read back from MLflow, not from the file
    assert restored.suggest("t20") is None  # null · seed 2 is Tune's to re-run: not proposed again
    children = sweep_run.client.search_runs([sweep_run.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{sweep_run.run_id}'")
    assert "unseen" not in {c.data.tags["trial_id"] for c in children}  # its seed keeps one child run
    null_id = next(t for t, label in second.items() if label == "null · seed 2")
    _finish(sweep_run, null_id, "null · seed 2", tmp_path)
    restored.on_trial_complete(null_id, {})
    assert restored.suggest("t21") == Searcher.FINISHED  # null at max: open at 3 seeds
    assert restored.current().records["null"].reason == "max"


def test_the_wall_time_budget_ends_on_the_parent_run_and_a_trial_budget_counts_proposals(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep_run = SweepRun.start(uri, "t", "t", tags={}, params={})
    searcher = SeedSearcher(_plan(), sweep_run, SeedBudget(seconds=1e-6))
    first = _suggest_all(searcher, 0)
    assert len(first) == 4  # round 1 runs whatever the budget
    for trial_id, label in first.items():
        _finish(sweep_run, trial_id, label, tmp_path)
        searcher.on_trial_complete(trial_id, {})
    assert searcher.suggest("t10") == Searcher.FINISHED
    assert searcher.current().records["null"].reason == "budget"
    assert BUDGET_TAG in sweep_run.client.get_run(sweep_run.run_id).data.tags

    counted = SeedSearcher(_plan(), SweepRun.start(uri, "u", "u", tags={}, params={}), SeedBudget(trials=5))
    assert len(_suggest_all(counted, 0)) == 4
    counted.results = {label: {"o0": 0.0, "o1": 1.0} for label in counted.proposed.values()}
    assert counted.suggest("t10") == Searcher.FINISHED  # the null cell's next seed needs the reference's too: 2 > 1
