"""Runs a sweep logged to MLflow, read back: a trial's child run found by its ``trial_id`` tag, its last
metrics and evaluation files, its metric histories, the baselines its parent run holds.

The driver's parent run (:class:`sweeps.execute.tracking.SweepRun`), the trial's child run
(:class:`sweeps.execute.trial_tracking.TrialRun`), a resumed trial and the results stage read runs through here.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path

from mlflow import MlflowClient
from mlflow.entities import Run

from cdm.io.csv import read_csv
from cdm.metric_names import CD
from sweeps.store_retry import PatientClient, wait_when_busy

__all__ = [
    "find_trial_run",
    "finished_trial_metrics",
    "last_eval_files",
    "last_objects",
    "metric_histories",
    "parent_baselines",
    "is_per_category",
    "trial_metrics",
    "trial_runs",
]

wait_when_busy()  # every process that opens a run waits for a busy SQLite store instead of failing


def is_per_category(key: str) -> bool:
    """``eval/f1/chair``: a per-category score, logged once on a child as ``final/f1/chair``, not as a series."""
    return key.startswith("eval/") and key.count("/") >= 2


def parent_baselines(parent_metrics: Mapping[str, float], eval_set: str | None,
                     parent_params: Mapping[str, str] | None = None) -> dict[str, float]:
    """The ``baseline/…`` scores the parent run holds for ``eval_set`` (see
    :meth:`sweeps.execute.tracking.SweepRun.log_results`): metrics, overall and per category (sweeps before
    full-precision logging kept the per-category ones as rounded params, read here too)."""
    held = {**{k: float(v) for k, v in (parent_params or {}).items() if "baseline/" in k}, **parent_metrics}
    prefix = f"eval_set {eval_set}/"
    own = {k.removeprefix(prefix): v for k, v in held.items() if k.startswith(prefix + "baseline/")}
    return own or {k: v for k, v in held.items() if k.startswith("baseline/")}


def trial_runs(client: MlflowClient, experiment_id: str, parent_run_id: str) -> list[Run]:
    """The sweep's child runs, one per trial, oldest first: the re-runs ``cdm-lab rerun`` files under the same
    parent (tagged ``rerun_of``) are checks of a trial, not trials, and are left out."""
    children = client.search_runs([experiment_id], filter_string=f"tags.mlflow.parentRunId = '{parent_run_id}'",
                                  order_by=["attributes.start_time ASC"], max_results=10000)
    return [r for r in children if "rerun_of" not in r.data.tags]


def find_trial_run(client: MlflowClient, experiment_id: str, parent_run_id: str, trial_id: str) -> str | None:
    """Run id of the child run of ``trial_id`` under ``parent_run_id``, or None."""
    runs = client.search_runs(
        [experiment_id],
        filter_string=f"tags.trial_id = '{trial_id}' and tags.mlflow.parentRunId = '{parent_run_id}'",
        max_results=2,
    )
    return runs[0].info.run_id if runs else None


def finished_trial_metrics(uri: str, experiment_id: str, parent_run_id: str, trial_id: str) -> dict[str, float] | None:
    """The last metrics of a trial the driver already closed as FINISHED, with ``step``; None otherwise.

    A trial that ended just before its driver was killed is FINISHED in MLflow (the driver logged its
    ``final/…``) while Tune's last experiment snapshot still lists it as running: on ``--resume`` its
    own record says it is done, so it reports these again instead of training (and logging) anew.
    """
    client = PatientClient(uri)
    run_id = find_trial_run(client, experiment_id, parent_run_id, trial_id)
    if run_id is None:
        return None
    run = client.get_run(run_id)
    if run.info.status != "FINISHED" or not any(k.startswith("final/") for k in run.data.metrics):
        return None
    step = max((m.step for m in client.get_metric_history(run_id, CD.key)), default=0)
    return {**trial_metrics(run.data.metrics, run.data.params), "step": step}


def trial_metrics(logged: Mapping[str, float], params: Mapping[str, str] | None = None) -> dict[str, float]:
    """A child run's metrics as its trial reported them: its series' last values, and the per-category
    scores (``eval/f1/chair``) back from the ``final/…`` metrics the driver logged them as (rounded params in
    sweeps from before full-precision logging)."""
    finals = {**{k: float(v) for k, v in (params or {}).items() if k.startswith("final/")}, **logged}
    per_category = {"eval/" + k.removeprefix("final/"): v for k, v in finals.items()
                    if k.startswith("final/") and is_per_category("eval/" + k.removeprefix("final/"))}
    return {**per_category, **{k: v for k, v in logged.items() if not k.startswith("final/")}}


def last_eval_files(client: MlflowClient, run_id: str) -> list[str]:
    """Artifact paths under the child run's last ``eval/step_<N>/`` folder and its sub-folders (panels,
    clouds); empty before any evaluation."""
    steps = sorted(a.path for a in client.list_artifacts(run_id, "eval") if a.is_dir)
    out = []
    for step in steps[-1:]:
        for a in client.list_artifacts(run_id, step):
            out += [b.path for b in client.list_artifacts(run_id, a.path)] if a.is_dir else [a.path]
    return out


def last_objects(client: MlflowClient, run_id: str) -> list[dict[str, object]]:
    """Rows of ``eval/step_<last>/objects.csv`` in a child run (numbers as floats); empty if absent."""
    tables = [f for f in last_eval_files(client, run_id) if f.endswith("/objects.csv")]
    if not tables:  # no evaluation logged yet, or one interrupted before its table
        return []
    with tempfile.TemporaryDirectory() as tmp:
        local = client.download_artifacts(run_id, tables[0], tmp)
        rows = read_csv(Path(local), f"run {run_id}")
    text = ("object_id", "category", "eval_set")
    return [{k: (v if k in text else float(v)) for k, v in row.items()} for row in rows]


def metric_histories(client: MlflowClient, run_id: str, keys: Iterable[str]) -> dict[str, list[tuple[int, float]]]:
    """Metric → its ``(step, value)`` history in the run (empty where the run logged none)."""
    return {k: [(m.step, m.value) for m in client.get_metric_history(run_id, k)] for k in keys}
