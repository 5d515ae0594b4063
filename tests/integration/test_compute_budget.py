"""``sweeps/local_recipe.yaml`` end to end at a tiny compute budget (its smoke profile: 3 CPU seconds a trial,
evaluated every 1.5): real Ray, Optuna and MLflow. Trials stop by compute, at different steps; ASHA counts its
rungs in those seconds; the trials score the tuning split, none of the held-out objects a table reports; each
cell's cost reaches the results table, the parent run's results.csv and the report's alike."""

from __future__ import annotations

import csv
import io
import statistics
from pathlib import Path

import pytest
from mlflow import MlflowClient

from cdm.config import load_config
from cdm.data import build_dataset
from cdm.metric_names import COMPUTE_METRIC
from sweeps import run
from sweeps.execute.tuner import _scheduler
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand
from sweeps.results import publish
from sweeps.store.read import last_objects

pytestmark = [pytest.mark.ray, pytest.mark.slow]

SPEC = Path(__file__).resolve().parents[2] / "sweeps" / "local_recipe.yaml"


def test_local_recipe_trials_stop_by_compute_on_the_tuning_split_with_their_cost_in_the_table(tmp_path, capsys):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    assert run.main([str(SPEC), "--smoke", "--out", str(tmp_path / "results"), "--tracking-uri", uri]) == 0
    out = capsys.readouterr().out
    plan = expand(load_spec(SPEC), "smoke")
    budget, every = plan.profile.compute_s, plan.profile.eval_every_s
    assert (budget, every) == (3.0, 1.5)
    assert "budget: 3 s of compute per trial" in out and "scored on: the tuning split" in out
    asha = _scheduler(plan)  # what the runner handed Tune: rungs in seconds of compute, not steps
    rungs = [milestone for milestone, _ in asha._brackets[0]._rungs]
    assert (asha._time_attr, asha._max_t, rungs) == (COMPUTE_METRIC, 3.0, [3.0, 1.5])

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("local_recipe")
    runs = client.search_runs([exp.experiment_id])
    parent = next(r for r in runs if r.data.tags.get("kind") == "sweep")
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(children) == 4 and all(r.info.status == "FINISHED" for r in children)
    steps, costs = {}, {}
    for child in children:
        history = client.get_metric_history(child.info.run_id, COMPUTE_METRIC)
        spent = [m.value for m in sorted(history, key=lambda m: m.step)]
        # One report per evaluation, each past its multiple of 1.5 s; the last past the budget, before 10,000 steps.
        assert all(s >= every * (k + 1) for k, s in enumerate(spent)) and spent[-1] >= budget, spent
        steps[child.info.run_id] = max(m.step for m in history)
        costs[child.data.tags["cell"]] = spent[-1]
        assert steps[child.info.run_id] < plan.profile.steps
    assert len(set(steps.values())) > 1  # equal compute, unequal steps: the configurations' steps cost differently

    # The tuning split: every scored object is a tune object, none a val object of the main job's table.
    config = load_config(None, {**plan.fixed, **plan.sets})  # object ids depend on none of the searched fields
    tune_ids = {o.object_id for o in build_dataset(config, "val").objects}
    val_ids = {o.object_id for o in build_dataset(config.replace(**{"data.eval_split": "val"}), "val").objects}
    scored = {row["object_id"] for c in children for row in last_objects(client, c.info.run_id)}
    assert scored and scored <= tune_ids and not tune_ids & val_ids
    assert all("/tune/" in o for o in scored) and all("/val/" in o for o in val_ids)

    # The cost column: each cell's own measured compute (one seed: its trial's), not the budget; the report agrees.
    folder = tmp_path / "results" / "local_recipe" / "smoke"
    logged = Path(client.download_artifacts(parent.info.run_id, "results.csv", str(tmp_path / "parent")))
    assert logged.read_bytes() == (folder / "results.csv").read_bytes()
    assert publish.main(["local_recipe", "--tracking-uri", uri, "--out", str(tmp_path / "report")]) == 0
    for table in (folder, tmp_path / "report"):
        rows = {r["cell"]: r for r in csv.DictReader(io.StringIO((table / "results.csv").read_text()))}
        assert {cell: float(rows[cell][f"{COMPUTE_METRIC} mean"]) for cell in costs} == costs
    assert statistics.fmean(costs.values()) != budget

