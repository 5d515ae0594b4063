"""A sweep's record read back from MLflow: its parent run with the spec and plan it was started with, its child
runs (one per trial, found by the ``trial_id`` tag), their last metrics, evaluation files and metric histories,
and the baselines the parent holds.

The baselines live on the parent run once per evaluation set (``baseline/sphere/f1``; ``eval_set <id>/baseline/…``
where the cells were scored on several), written by :meth:`sweeps.store.sweep_run.SweepRun.log_results`; a
child's per-category scores are its ``final/…`` metrics (:meth:`sweeps.store.sweep_run.SweepRun.close_trial`).
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mlflow.entities import Run

from cdm.io.csv import read_csv
from cdm.io.json import read_json
from cdm.io.yaml import read_mapping
from cdm.metric_names import CD
from sweeps.store.tracking import PatientClient, client

__all__ = [
    "LoggedSweep", "ReportError", "UnknownExperimentError", "find_trial_run", "finished_trial_metrics",
    "is_per_category", "last_eval_files", "last_objects", "metric_histories", "parent_baselines", "read_sweep",
    "trial_metrics", "trial_runs",
]


class ReportError(ValueError):
    """The experiment exists but holds no sweep that can be read; the message says what is missing."""


class UnknownExperimentError(ReportError):
    def __init__(self, name: str, known: list[str]):
        super().__init__(f"no MLflow experiment named {name!r}; known: {', '.join(known) or 'none'}")
        self.known = known


@dataclass(frozen=True)
class LoggedSweep:
    """One sweep as MLflow holds it: the parent run, its spec file and plan, its child runs."""

    client: PatientClient
    experiment: str
    experiment_id: str
    parent: Run
    spec_file: dict[str, Any]
    """The spec file the sweep started with, as YAML read it (validated by :func:`sweeps.plan.spec.load_spec`'s
    rules in the results stage)."""
    plan: dict[str, Any]
    """``plan.json``: ``fixed`` overrides, ``sets`` and the grid's ``cells`` (label, values, seed, paper)."""
    children: list[Run]


def _parent(store: PatientClient, experiment: str | None, parent_run_id: str | None) -> Run:
    if parent_run_id is not None:
        return store.get_run(parent_run_id)
    exp = store.get_experiment_by_name(experiment)
    if exp is None:
        raise UnknownExperimentError(experiment, sorted(e.name for e in store.search_experiments()))
    parents = store.search_runs([exp.experiment_id], filter_string="tags.kind = 'sweep'",
                                order_by=["attributes.start_time DESC"], max_results=1)
    if not parents:
        raise ReportError(f"experiment {experiment!r} holds no sweep (no run tagged kind=sweep)")
    return parents[0]


def read_sweep(uri: str, experiment: str | None = None, parent_run_id: str | None = None) -> LoggedSweep:
    """The latest sweep of ``experiment`` (or the sweep whose parent run is ``parent_run_id``).

    Raises:
        UnknownExperimentError: no experiment of that name (the error lists the known ones).
        ReportError: the experiment holds no sweep parent run, or the parent lacks a readable spec/plan.
    """
    store = client(uri)
    parent = _parent(store, experiment, parent_run_id)
    run_id = parent.info.run_id
    exp = store.get_experiment(parent.info.experiment_id)
    names = [a.path for a in store.list_artifacts(run_id)]
    specs = [n for n in names if n.endswith((".yaml", ".yml"))]
    if not specs or "plan.json" not in names:
        raise ReportError(
            f"sweep run {run_id} has no spec file or plan.json artifact (artifacts: {', '.join(names) or 'none'})"
        )
    with tempfile.TemporaryDirectory() as tmp:
        try:
            spec = read_mapping(Path(store.download_artifacts(run_id, specs[0], tmp)), "spec")
            plan = read_json(Path(store.download_artifacts(run_id, "plan.json", tmp)), f"sweep run {run_id}")
        except ValueError as exc:
            raise ReportError(str(exc)) from None
    return LoggedSweep(store, exp.name, exp.experiment_id, parent, spec, plan,
                       trial_runs(store, exp.experiment_id, run_id))


def is_per_category(key: str) -> bool:
    """``eval/f1/chair``: a per-category score, logged once on a child as ``final/f1/chair``, not as a series."""
    return key.startswith("eval/") and key.count("/") >= 2


def parent_baselines(parent_metrics: Mapping[str, float], eval_set: str | None,
                     parent_params: Mapping[str, str] | None = None) -> dict[str, float]:
    """The ``baseline/…`` scores the parent run holds for ``eval_set``: metrics, overall and per category
    (sweeps before full-precision logging kept the per-category ones as rounded params, read here too)."""
    held = {**{k: float(v) for k, v in (parent_params or {}).items() if "baseline/" in k}, **parent_metrics}
    prefix = f"eval_set {eval_set}/"
    own = {k.removeprefix(prefix): v for k, v in held.items() if k.startswith(prefix + "baseline/")}
    return own or {k: v for k, v in held.items() if k.startswith("baseline/")}


def trial_runs(store: PatientClient, experiment_id: str, parent_run_id: str) -> list[Run]:
    """The sweep's child runs, one per trial, oldest first: re-runs filed under the same parent (tagged
    ``rerun_of``) are checks of a trial, not trials, and are left out."""
    children = store.search_runs([experiment_id], filter_string=f"tags.mlflow.parentRunId = '{parent_run_id}'",
                                 order_by=["attributes.start_time ASC"], max_results=10000)
    return [r for r in children if "rerun_of" not in r.data.tags]


def find_trial_run(store: PatientClient, experiment_id: str, parent_run_id: str, trial_id: str) -> str | None:
    """Run id of the child run of ``trial_id`` under ``parent_run_id``, or None."""
    runs = store.search_runs(
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
    store = client(uri)
    run_id = find_trial_run(store, experiment_id, parent_run_id, trial_id)
    if run_id is None:
        return None
    run = store.get_run(run_id)
    if run.info.status != "FINISHED" or not any(k.startswith("final/") for k in run.data.metrics):
        return None
    step = max((m.step for m in store.get_metric_history(run_id, CD.key)), default=0)
    return {**trial_metrics(run.data.metrics, run.data.params), "step": step}


def trial_metrics(logged: Mapping[str, float], params: Mapping[str, str] | None = None) -> dict[str, float]:
    """A child run's metrics as its trial reported them: its series' last values, and the per-category
    scores (``eval/f1/chair``) back from the ``final/…`` metrics the driver logged them as (rounded params in
    sweeps from before full-precision logging)."""
    finals = {**{k: float(v) for k, v in (params or {}).items() if k.startswith("final/")}, **logged}
    per_category = {"eval/" + k.removeprefix("final/"): v for k, v in finals.items()
                    if k.startswith("final/") and is_per_category("eval/" + k.removeprefix("final/"))}
    return {**per_category, **{k: v for k, v in logged.items() if not k.startswith("final/")}}


def last_eval_files(store: PatientClient, run_id: str) -> list[str]:
    """Artifact paths under the child run's last ``eval/step_<N>/`` folder and its sub-folders (panels,
    clouds); empty before any evaluation."""
    steps = sorted(a.path for a in store.list_artifacts(run_id, "eval") if a.is_dir)
    out = []
    for step in steps[-1:]:
        for a in store.list_artifacts(run_id, step):
            out += [b.path for b in store.list_artifacts(run_id, a.path)] if a.is_dir else [a.path]
    return out


def last_objects(store: PatientClient, run_id: str) -> list[dict[str, object]]:
    """Rows of ``eval/step_<last>/objects.csv`` in a child run (numbers as floats); empty if absent."""
    tables = [f for f in last_eval_files(store, run_id) if f.endswith("/objects.csv")]
    if not tables:  # no evaluation logged yet, or one interrupted before its table
        return []
    with tempfile.TemporaryDirectory() as tmp:
        local = store.download_artifacts(run_id, tables[0], tmp)
        rows = read_csv(Path(local), f"run {run_id}")
    text = ("object_id", "category", "eval_set")
    return [{k: (v if k in text else float(v)) for k, v in row.items()} for row in rows]


def metric_histories(store: PatientClient, run_id: str, keys: Iterable[str]) -> dict[str, list[tuple[int, float]]]:
    """Metric → its ``(step, value)`` history in the run (empty where the run logged none)."""
    return {k: [(m.step, m.value) for m in store.get_metric_history(run_id, k)] for k in keys}
