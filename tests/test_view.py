"""The runs view the runner links (sweeps/results/view.py), on a real SQLite store: the rows, their columns
and order, the baselines as rows, the verdict and interval per cell."""

from __future__ import annotations

import json

from mlflow import MlflowClient

from sweeps.results import view
from sweeps.results.sweep import open_sweep, results_table, trial_records
from tests import test_publish

grid_store = test_publish.grid_store  # three cells (0.02, 0.04, 0.08 failed), one seed each, the sphere baseline


def test_shared_view_lands_on_scores_verdicts_and_baselines(grid_store):
    uri, sweep = grid_store
    record = open_sweep(uri, "synth")
    table = results_table(record, trial_records(record))
    path = view.share_view(record, table)
    assert path == f"#/experiments/{sweep.experiment_id}/runs?viewStateShareKey=sweep-{sweep.run_id}"
    client = MlflowClient(uri)
    state = json.loads(client.get_experiment(sweep.experiment_id).tags[f"mlflow.sharedViewState.sweep-{sweep.run_id}"])
    assert state["searchFilter"] == f"tags.sweep = '{sweep.run_id}'"
    assert "groupBy" not in state  # one seed per cell: one row per run, no group of one
    # Scores, verdict with interval and baselines first, in the ~285 px MLflow leaves beside name and date.
    assert state["selectedColumns"] == state["columnOrder"] == [
        "metrics.`final/f1`", "metrics.`final/cd`", "tags.`vs reference`", "tags.`vs baselines`",
        "metrics.`swept/priors.point_size`", "tags.`seed`"]
    assert sum(state["columnWidths"][c] for c in state["columnOrder"][:2]) + 160 <= 285
    assert (state["orderByKey"], state["orderByAsc"]) == ("metrics.`final/f1`", False)  # best F1 on top
    rows = {r.info.run_name: r for r in client.search_runs([sweep.experiment_id], f"tags.sweep = '{sweep.run_id}'")}
    assert len(rows) == 4  # the three trials and the baseline
    baseline = rows["baseline: sphere"]
    assert baseline.data.tags["kind"] == "baseline" and baseline.data.metrics == {"final/f1": 0.2, "final/cd": 150.0}
    assert "mlflow.parentRunId" not in baseline.data.tags  # no child of the sweep: its readers see trials only
    assert sorted(rows[n].data.metrics.get("swept/priors.point_size", -1) for n in rows if "seed" in n) == [
        -1,
        0.02,
        0.04,
    ]
    assert view.row_tags(table, "point_size=0.02", "eval/f1") == {
        "vs reference": "reference",
        "vs baselines": "beats sphere",
    }
    assert view.row_tags(table, "point_size=0.04", "eval/f1") == {"vs reference": "better [+0.020, +0.020] Δf1 +0.020",
                                                                 "vs baselines": "beats sphere"}
    assert (
        view.row_tags(table, "point_size=0.08", "eval/f1")["vs reference"] == "no result"
    )  # failed: not the reference
    view.share_view(record, table)  # published again (report --log): the baseline rows are not doubled
    assert len(client.search_runs([sweep.experiment_id], "tags.kind = 'baseline'")) == 1
    assert [t.outcome.label for t in trial_records(open_sweep(uri, "synth"), objects=False)] == [
        "point_size=0.02 · seed 0", "point_size=0.04 · seed 0", "point_size=0.08 · seed 0"]  # baselines are no trials


def test_sort_key_orders_swept_values_as_numbers():
    values = ["10", "2", "1e-3", "1", "0.5"]
    assert sorted(values) == ["0.5", "1", "10", "1e-3", "2"]  # MLflow's order for params: text
    assert sorted(values, key=view.sort_key) == ["1e-3", "0.5", "1", "2", "10"]
    assert [view.sort_key(v) for v in ("depth", "True", "nan", "3")] == [None, None, None, 3.0]
