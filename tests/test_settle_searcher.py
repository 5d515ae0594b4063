"""The Tune searcher of seeds until settled (sweeps/execute/settle/searcher.py) against a real MLflow SQLite
store, driven the way Tune drives it (suggest, on_trial_complete, save, restore), without a Ray cluster."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest
from ray.tune.search import Searcher

from sweeps.execute.settle import BUDGET_TAG, UntilSettled
from sweeps.execute.settle.searcher import SeedSearcher
from sweeps.plan.budget import SeedBudget
from sweeps.plan.spec import Spec
from sweeps.plan.trials import expand
from sweeps.store.files import StoreError
from sweeps.store.sweep_run import SweepRun

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
        writer.writerows(
            {"object_id": f"o{i}", "category": "chair", "eval_set": "e", "cd": 1.0, "f1": 0.1 * i + 0.05 * seed}
            for i in range(6)
        )
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
    searcher = UntilSettled(_plan()).searcher(sweep_run)
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

    restored = UntilSettled(_plan()).searcher(SweepRun(uri, sweep_run.experiment_id, sweep_run.run_id))
    restored.restore(str(tmp_path / "state.json"))
    assert restored.proposed == {**first, **second}
    assert set(restored.results) == {*first.values(), "ref · seed 2"}  # read back from MLflow, not from the file
    assert restored.suggest("t20") is None  # null · seed 2 is Tune's to re-run: not proposed again
    children = sweep_run.client.search_runs(
        [sweep_run.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{sweep_run.run_id}'"
    )
    assert "unseen" not in {c.data.tags["trial_id"] for c in children}  # its seed keeps one child run
    null_id = next(t for t, label in second.items() if label == "null · seed 2")
    _finish(sweep_run, null_id, "null · seed 2", tmp_path)
    restored.on_trial_complete(null_id, {})
    assert restored.suggest("t21") == Searcher.FINISHED  # null at max: open at 3 seeds
    assert restored.current().records["null"].reason == "max"


def test_the_wall_time_budget_ends_on_the_parent_run_and_a_trial_budget_counts_proposals(tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep_run = SweepRun.start(uri, "t", "t", tags={}, params={})
    searcher = UntilSettled(_plan(), SeedBudget(seconds=1e-6)).searcher(sweep_run)
    first = _suggest_all(searcher, 0)
    assert len(first) == 4  # round 1 runs whatever the budget
    for trial_id, label in first.items():
        _finish(sweep_run, trial_id, label, tmp_path)
        searcher.on_trial_complete(trial_id, {})
    assert searcher.suggest("t10") == Searcher.FINISHED
    assert searcher.current().records["null"].reason == "budget"
    assert BUDGET_TAG in sweep_run.client.get_run(sweep_run.run_id).data.tags

    counted = UntilSettled(_plan(), SeedBudget(trials=5)).searcher(SweepRun.start(uri, "u", "u", tags={}, params={}))
    assert len(_suggest_all(counted, 0)) == 4
    counted.results = {label: {"o0": 0.0, "o1": 1.0} for label in counted.proposed.values()}
    assert counted.suggest("t10") == Searcher.FINISHED  # the null cell's next seed needs the reference's too: 2 > 1


def _state_folder(tmp_path, text: str | bytes, name: str = "seed-searcher-2026-12-04_20-00-00.json") -> Path:
    folder = tmp_path / "sweep"
    folder.mkdir(exist_ok=True)
    (folder / name).write_bytes(text.encode() if isinstance(text, str) else text)
    return folder


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ('{"proposed": {"t0": "ref · seed 0"', "is not JSON"),
        ("[" * 100_000 + "]" * 100_000, "nests 100000 levels deep"),
        (
            json.dumps({"proposed": {f"t{i}": "ref · seed 0" for i in range(10**6)}, "spent_s": 1.0}),
            "bytes; a seed searcher's state is at most",
        ),
        (
            json.dumps({"proposed": {f"t{i}": "ref · seed 0" for i in range(7)}, "spent_s": 1.0}),
            "7 proposals, more than the plan's 6 trials",
        ),
        (
            json.dumps({"proposed": {"t0": "ref · seed 9"}, "spent_s": 1.0}),
            "proposal 'ref · seed 9' is no trial of this sweep",
        ),
        (
            json.dumps({"proposed": {"t0": "ref · seed 0", "t1": "ref · seed 0"}, "spent_s": 1.0}),
            "a trial proposed twice",
        ),
        ('{"proposed": {}, "spent_s": NaN}', "spent_s nan is not a finite number"),
        ('{"proposed": [], "spent_s": 1}', 'expected {"proposed"'),
        ('{"proposed": {}, "spent_s": ' + "9" * 5001 + "}", "field 'spent_s' has more than 1000 digits"),
    ],
)
def test_a_damaged_or_oversized_searcher_state_is_refused_before_tune_restores_it(tmp_path, text, said):
    folder = _state_folder(tmp_path, text)
    with pytest.raises(StoreError, match=re.escape(said)) as refused:
        UntilSettled(_plan()).check_resume(str(folder))
    assert str(refused.value).startswith("--resume: ") and "\n" not in str(refused.value)
    assert "without it a finished seed could run again" in str(refused.value)


def test_the_state_tune_restores_is_the_one_checked_and_a_missing_one_is_refused(tmp_path):
    with pytest.raises(StoreError, match="holds no seed searcher state"):
        UntilSettled(_plan()).check_resume(str(tmp_path))
    folder = _state_folder(tmp_path, "not json", "seed-searcher-2026-01-01_00-00-00.json")
    _state_folder(
        tmp_path, json.dumps({"proposed": {"t0": "ref · seed 0"}, "spent_s": 3.0})
    )  # the later name: Tune's pick
    UntilSettled(_plan()).check_resume(str(folder))


def test_restore_asks_mlflow_a_bounded_number_of_times_whatever_the_file_says(tmp_path):
    """Every trial of the plan proposed and finished: one search of the parent's children and one parent
    lookup, plus one evaluation table per finished trial (bounded by the plan, not by the file)."""
    from mlflow import MlflowClient

    class Counting(MlflowClient):
        calls: dict[str, int] = {}

        def search_runs(self, *args, **kwargs):
            Counting.calls["search_runs"] = Counting.calls.get("search_runs", 0) + 1
            return super().search_runs(*args, **kwargs)

        def get_run(self, *args, **kwargs):
            Counting.calls["get_run"] = Counting.calls.get("get_run", 0) + 1
            return super().get_run(*args, **kwargs)

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep_run = SweepRun.start(uri, "t", "t", tags={}, params={})
    plan = _plan()
    proposed = {f"t{i}": c.label for i, c in enumerate(plan.cells)}
    for trial_id, label in proposed.items():
        _finish(sweep_run, trial_id, label, tmp_path, status="FAILED" if label == "null · seed 2" else "FINISHED")
    (tmp_path / "state.json").write_text(json.dumps({"proposed": proposed, "spent_s": 5.0}))
    restored = UntilSettled(plan).searcher(SweepRun(uri, sweep_run.experiment_id, sweep_run.run_id))
    restored.sweep_run.client = Counting(uri)
    restored.restore(str(tmp_path / "state.json"))
    assert set(restored.results) == set(proposed.values()) and restored.spent_before == 5.0
    assert restored.results["null · seed 2"] is None and restored.results["ref · seed 2"]["o1"] == 0.2
    assert Counting.calls == {"search_runs": 1, "get_run": 1}


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncated", "a million entries", "a 5,001-digit number"])
def test_resume_with_a_damaged_searcher_state_exits_2_and_runs_no_seed_again(tmp_path, damage):
    """Through the command a user types: `python sweeps/run.py SPEC --resume`, a sweep folder whose searcher
    state was damaged after seed 0 finished. Tune would have restored a fresh searcher and run seed 0
    again; the runner refuses before Ray starts and MLflow keeps the one child run."""
    from sweeps.plan.spec import load_spec
    from tests.hostile_files import ROOT, assert_refused, run_command

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    sweep_run = SweepRun.start(uri, "point_size", "point_size", tags={}, params={})
    _finish(sweep_run, "t0", "ref · seed 0", tmp_path)
    folder = tmp_path / "results" / "point_size" / "smoke"
    folder.mkdir(parents=True)
    spec = load_spec(ROOT / "sweeps" / "point_size.yaml").until_settled()
    (folder / "sweep.json").write_text(
        json.dumps(
            {
                "spec": spec.model_dump(mode="json"),
                "sets": {},
                "profile": "smoke",
                "budget": None,
                "tracking_uri": uri,
                "parent_run_id": sweep_run.run_id,
            }
        )
    )
    text = {"truncated": '{"proposed": {"t0": "',
            "a million entries": json.dumps({"proposed": {f"t{i}": str(i) for i in range(10**6)}, "spent_s": 1.0}),
            "a 5,001-digit number": '{"proposed": {}, "spent_s": ' + "9" * 5001 + "}"}[damage]
    (folder / "seed-searcher-2026-12-04_20-00-00.json").write_text(text)
    outcome = run_command(
        [
            str(ROOT / "sweeps" / "run.py"),
            str(ROOT / "sweeps" / "point_size.yaml"),
            "--resume",
            "--trust-storage",
            "--profile",
            "smoke",
            "--out",
            str(tmp_path / "results"),
        ],
        tmp_path,
        timeout=300,
    )
    assert_refused(
        outcome, "--resume: ", "seed-searcher-2026-12-04_20-00-00.json", "without it a finished seed could run again",
        *(["field 'spent_s' has more than 1000 digits"] if damage == "a 5,001-digit number" else []),
    )
    children = sweep_run.client.search_runs(
        [sweep_run.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{sweep_run.run_id}'"
    )
    assert [c.data.tags["trial_id"] for c in children] == ["t0"]
