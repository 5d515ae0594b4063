"""MLflow tracking of a sweep: one parent run per sweep, one child run per trial.

The driver opens the parent run (spec, expanded grid and results table as artifacts) and closes
each child with Tune's verdict (finished, stopped early, failed + reason). The child run itself is
written from exactly one place — the trial's rank-0 training process, as a :class:`cdm.train.Callback`
— because SQLite locks under many writers. A child is found again by its ``trial_id`` tag,
so a resumed trial continues its own run and skips steps it had already logged: no duplicates.

All calls go through an explicit :class:`mlflow.MlflowClient` (no global active run), so a Ray actor
reused for the next trial carries nothing over.
"""

from __future__ import annotations

import csv
import math
import os
import tempfile
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml
from mlflow import MlflowClient
from mlflow.entities import Metric, Param, RunTag

from cdm.config import Config
from cdm.train import Callback
from sweeps.compare.outcomes import TrialOutcome
from sweeps.compare.rules import rounded
from sweeps.store_retry import PatientClient, wait_when_busy

__all__ = [
    "EVAL_FOLDERS",
    "EXPERIMENT_KIND",
    "SYSTEM_METRICS",
    "WORKFLOW",
    "SweepRun",
    "baselines_by_eval_set",
    "TrialRun",
    "find_trial_run",
    "finished_trial_metrics",
    "metric_histories",
    "parent_baselines",
    "resolve_tracking_uri",
    "trial_metrics",
    "ui_command",
    "ui_link",
]

_BATCH = 100  # MLflow's limit of params per log_batch call
wait_when_busy()  # every process that logs waits for a busy SQLite store instead of failing
PER_TRIAL_PARAMS = ("train.out_dir",)
"""Config fields that differ in every trial by construction (its own folder): not params, so the
compare view shows only what the cells set."""


def resolve_tracking_uri(cli: str | None, cwd: Path | None = None) -> str:
    """``--tracking-uri``, else ``MLFLOW_TRACKING_URI``, else ``sqlite:///<cwd>/mlflow.db``; always absolute.

    A relative SQLite path would resolve inside each Ray trial's own working directory, so it is
    made absolute against ``cwd`` here, on the driver.
    """
    cwd = (cwd or Path.cwd()).resolve()
    uri = cli or os.environ.get("MLFLOW_TRACKING_URI") or "sqlite:///mlflow.db"
    if uri.startswith("sqlite:///") and not uri.startswith("sqlite:////"):
        uri = f"sqlite:///{cwd / uri.removeprefix('sqlite:///')}"
    return uri


def ui_command(uri: str) -> str:
    """The command that shows this tracking store in a browser, bound to loopback only."""
    if uri.startswith("sqlite:"):
        return f"mlflow ui --backend-store-uri {uri} --host 127.0.0.1 --port 5000"
    return f"open {uri} in a browser"


EXPERIMENT_KIND = ("mlflow.experimentKind", "custom_model_development")
"""The experiment tag MLflow 3 keeps an experiment's kind in (its UI's kind selector writes it: "Machine
learning", not "GenAI apps & agents"). MLflow 3.17's own UI chooses its workflow per browser instead
(``localStorage`` ``mlflow.workflowType``, default GenAI; the URL's ``workflowType`` wins), so every link
the runner prints also carries :data:`WORKFLOW`."""

WORKFLOW = "workflowType=machine_learning"
"""The URL parameter that opens MLflow 3's model-training workflow (Runs, Models) whatever the browser
chose before: no Sessions, Judges, Prompts or AI Gateway, the runs under "Runs", not "Evaluation runs"."""


def ui_link(path: str) -> str:
    """``path`` of the MLflow UI (``#/experiments/…``) opening in the model-training workflow (:data:`WORKFLOW`)."""
    return path + ("&" if "?" in path else "?") + WORKFLOW


def _experiment(client: MlflowClient, name: str, uri: str) -> str:
    """The experiment ``name``'s id, created if needed, tagged a model-training one (:data:`EXPERIMENT_KIND`),
    also when an older sweep created it."""
    found = client.get_experiment_by_name(name)
    if found is not None:
        experiment_id = found.experiment_id
    else:
        location = None
        if uri.startswith("sqlite:///"):
            # Keep artifacts beside the database rather than in whatever directory the driver ran from.
            location = (Path(uri.removeprefix("sqlite:///")).parent / "mlruns" / name).as_uri()
        experiment_id = client.create_experiment(name, artifact_location=location)
    client.set_experiment_tag(experiment_id, *EXPERIMENT_KIND)
    return experiment_id


def _log_params(client: MlflowClient, run_id: str, params: list[Param]) -> None:
    """``params`` in batches of MLflow's limit."""
    for i in range(0, len(params), _BATCH):
        client.log_batch(run_id, params=params[i:i + _BATCH])


def _params(values: dict[str, Any]) -> list[Param]:
    return [Param(k, str(v)) for k, v in values.items()]


SYSTEM_METRICS = ("train/steps_per_s", "train/cpu_s_per_step", "train/elapsed_s")
"""Training-loop timings a child logs as ``system/<name>``: MLflow's UI shows that prefix apart, under
"System metrics", so the model charts hold what a reader compares (metric, partner, loss terms)."""


def _per_category(key: str) -> bool:
    """``eval/f1/chair``: a per-category score, logged once on a child as ``final/f1/chair``, not as a series."""
    return key.startswith("eval/") and key.count("/") >= 2


def _shown(key: str, value: float) -> float:
    """``value`` as a reader sees it in the UI's tables: scores at the results table's precision, losses
    and timings at 4 significant digits (a learning rate of 1e-4 keeps its digits)."""
    if key.startswith("eval/"):
        return rounded(value)
    return float(f"{value:.4g}") if math.isfinite(value) else value


def parent_baselines(parent_metrics: Mapping[str, float], eval_set: str | None,
                     parent_params: Mapping[str, str] | None = None) -> dict[str, float]:
    """The ``baseline/…`` scores the parent run holds for ``eval_set`` (see :meth:`SweepRun.log_results`):
    the overall ones as metrics, the per-category ones as params."""
    held = {**{k: float(v) for k, v in (parent_params or {}).items() if "baseline/" in k}, **parent_metrics}
    prefix = f"eval_set {eval_set}/"
    own = {k.removeprefix(prefix): v for k, v in held.items() if k.startswith(prefix + "baseline/")}
    return own or {k: v for k, v in held.items() if k.startswith("baseline/")}


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
    step = max((m.step for m in client.get_metric_history(run_id, "eval/cd")), default=0)
    return {**trial_metrics(run.data.metrics, run.data.params), "step": step}


def trial_metrics(logged: Mapping[str, float], params: Mapping[str, str] | None = None) -> dict[str, float]:
    """A child run's metrics as its trial reported them: its series' last values, and the per-category
    scores (``eval/f1/chair``) back from the ``final/…`` params the driver logged them as (metrics in
    sweeps before the params)."""
    finals = {**logged, **{k: float(v) for k, v in (params or {}).items() if k.startswith("final/")}}
    per_category = {"eval/" + k.removeprefix("final/"): v for k, v in finals.items()
                    if k.startswith("final/") and _per_category("eval/" + k.removeprefix("final/"))}
    return {**per_category, **{k: v for k, v in logged.items() if not k.startswith("final/")}}


def baselines_by_eval_set(outcomes: Sequence[TrialOutcome]) -> dict[str, dict[str, float]]:
    """Evaluation-set fingerprint → the ``baseline/…`` metrics scored on it (the same in every trial on it).

    A trial without per-object rows files its baselines under ``""``.
    """
    out: dict[str, dict[str, float]] = {}
    for o in (o for o in outcomes if o.finished):
        eval_set = str(o.objects[0].get("eval_set", "")) if o.objects else ""
        found = {k: v for k, v in o.metrics.items() if k.startswith("baseline/")}
        if found and eval_set not in out:
            out[eval_set] = found
    return out


class SweepRun:
    """The parent run of one sweep, driven from the Ray driver."""

    def __init__(self, uri: str, experiment_id: str, run_id: str):
        self.uri, self.experiment_id, self.run_id = uri, experiment_id, run_id
        self.client = PatientClient(uri)

    @classmethod
    def start(cls, uri: str, experiment: str, run_name: str, tags: dict[str, str], params: dict[str, Any]) -> SweepRun:
        """Create the experiment if needed and open a new parent run."""
        client = PatientClient(uri)
        experiment_id = _experiment(client, experiment, uri)
        run = client.create_run(experiment_id, run_name=run_name, tags={"kind": "sweep", **tags})
        client.log_batch(run.info.run_id, params=_params(params))
        return cls(uri, experiment_id, run.info.run_id)

    @classmethod
    def reopen(cls, uri: str, run_id: str) -> SweepRun:
        """The parent run of an interrupted sweep, marked running again."""
        client = PatientClient(uri)
        run = client.get_run(run_id)
        client.set_experiment_tag(run.info.experiment_id, *EXPERIMENT_KIND)  # a sweep begun before the tag
        client.update_run(run_id, status="RUNNING")
        return cls(uri, run.info.experiment_id, run_id)

    def __getstate__(self) -> dict[str, str]:
        # Tune pickles its callbacks into the experiment state; the client reconnects after a restore.
        return {"uri": self.uri, "experiment_id": self.experiment_id, "run_id": self.run_id}

    def __setstate__(self, state: dict[str, str]) -> None:
        self.__init__(state["uri"], state["experiment_id"], state["run_id"])

    def log_artifacts(self, paths: Iterable[Path]) -> None:
        for path in paths:
            self.client.log_artifact(self.run_id, str(path))

    def close_trial(
        self,
        trial_id: str,
        run_name: str,
        status: str,
        error: str | None = None,
        stopped_early: bool = False,
        last: Mapping[str, object] | None = None,
    ) -> None:
        """Set a child run's final status from Tune's verdict; creates the run if the trial died before opening it.

        Args:
            status: ``FINISHED`` or ``FAILED``.
            last: the trial's last reported result (Tune's ``trial.last_result``): the source of the
                per-category scores, which the child logs only here, as ``final/…``.
        """
        run_id = find_trial_run(self.client, self.experiment_id, self.run_id, trial_id)
        if run_id is None:
            run_id = self.client.create_run(
                self.experiment_id, run_name=run_name,
                tags={"mlflow.parentRunId": self.run_id, "trial_id": trial_id}).info.run_id
        if error:
            self.client.set_tag(run_id, "error", error[-5000:])
        if stopped_early:
            self.client.set_tag(run_id, "stopped_early", "true")
        if status == "FINISHED":
            self._log_final(run_id, last or {})
        self.client.set_terminated(run_id, status=status)

    def _log_final(self, run_id: str, last: Mapping[str, object]) -> None:
        """Log the last evaluation's ``eval/cd``, ``eval/f1`` as ``final/…`` metrics, their per-category
        scores as ``final/…`` params.

        Stable names to sort, search and compare by in the UI (``metrics.`final/f1` > 0.4``), whatever
        step a trial ended at (ASHA stops some early), at the results table's precision (the runs view
        shows them as logged). Logged here, on the driver, once Tune's verdict is in: the trial itself
        cannot tell its last evaluation from an intermediate one. The overall scores come from the
        child's own history; the per-category ones from ``last`` (the child logs no series of them).
        """
        history = self.client.get_metric_history(run_id, "eval/cd")
        latest = self.client.get_run(run_id).data.metrics
        if not history or any(k.startswith("final/") for k in latest):  # logged once: a resumed trial may close twice
            return
        step = max(m.step for m in history)
        now = int(time.time() * 1000)
        scores = {**{k: v for k, v in last.items() if _per_category(k) and isinstance(v, (int, float))}, **latest}
        final = {"final/" + k.removeprefix("eval/"): rounded(float(v)) for k, v in scores.items()
                 if k.split("/")[:2] in (["eval", "cd"], ["eval", "f1"])}
        # Per category one number each, not a chart of one point: a param, where MLflow lists values.
        self.client.log_batch(run_id, metrics=[Metric(k, v, now, step) for k, v in final.items() if k.count("/") == 1],
                              params=[Param(k, str(v)) for k, v in final.items() if k.count("/") > 1])

    def trial_objects(self, trial_id: str) -> list[dict[str, object]]:
        """Per-object rows (``objects.csv``) of the trial's last logged evaluation; empty if none."""
        run_id = find_trial_run(self.client, self.experiment_id, self.run_id, trial_id)
        return [] if run_id is None else last_objects(self.client, run_id)

    def log_results(self, baselines: dict[str, dict[str, float]], description: str) -> None:
        """The sweep's results on the parent run: the baselines once per evaluation set (``baseline/sphere/f1``;
        ``eval_set <id>/baseline/…`` when the cells were scored on several) — the overall scores as
        metrics, the per-category ones as params (a chart of one bar says nothing) — and ``description``
        as the run's description. The cells' results are the run's ``results.md`` and its children.
        Values at the results table's precision: the run page lists them as logged.

        Args:
            baselines: evaluation-set fingerprint → ``baseline/<name>/<metric>`` → value.
        """
        now = int(time.time() * 1000)
        metrics, params = [], []
        for eval_set, values in baselines.items():
            prefix = "" if len(baselines) == 1 else f"eval_set {eval_set}/"
            metrics += [Metric(prefix + k, rounded(v), now, 0) for k, v in values.items() if k.count("/") == 2]
            params += [Param(prefix + k, str(rounded(v))) for k, v in values.items() if k.count("/") > 2]
        self.client.log_batch(self.run_id, metrics=metrics)
        _log_params(self.client, self.run_id, params)
        self.client.set_tag(self.run_id, "mlflow.note.content", description)

    def end(self, status: str = "FINISHED") -> None:
        self.client.set_terminated(self.run_id, status=status)


EVAL_FOLDERS = {".png": "panels", ".ply": "clouds"}
"""Sub-folder of ``eval/step_<N>/`` per file suffix (``objects.csv`` stays at the top): a reader finds the
panels apart from the dozens of clouds."""


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
        with open(local, newline="") as fh:
            rows = list(csv.DictReader(fh))
    text = ("object_id", "category", "eval_set")
    return [{k: (v if k in text else float(v)) for k, v in row.items()} for row in rows]


def metric_histories(client: MlflowClient, run_id: str, keys: Iterable[str]) -> dict[str, list[tuple[int, float]]]:
    """Metric → its ``(step, value)`` history in the run (empty where the run logged none)."""
    return {k: [(m.step, m.value) for m in client.get_metric_history(run_id, k)] for k in keys}


def learning_curve_png(
    client: MlflowClient, run_id: str, folder: Path, metric: str = "eval/cd", title: str = ""
) -> Path | None:
    """The run's training curves (:func:`sweeps.compare.plots.training_curves` for this one trial: the loss terms
    apart, ``metric`` once the run holds two evaluations) from its MLflow history, titled ``title``;
    None while the run holds no curve (no loss logged, fewer than two evaluations).

    Reading the history (not in-memory lists) keeps the curve whole across a resumed trial.
    """
    from sweeps.compare.plots import has_curve, training_curves

    keys = ("train/loss", "train/loss_diffusion", metric)
    history = metric_histories(client, run_id, keys)
    if not has_curve(history, metric):
        return None
    return training_curves({title: history}, {title: title}, metric, title, folder / "learning_curve.png")


class TrialRun(Callback):
    """The child run of one trial, fed by :func:`cdm.train.fit`'s callbacks (rank 0 only).

    Opens the run on construction — or reopens the trial's earlier run after a resume, logging only
    steps past what that run already holds.
    """

    def __init__(
        self,
        uri: str,
        experiment_id: str,
        parent_run_id: str,
        trial_id: str,
        run_name: str,
        tags: dict[str, str],
        config: Config,
        metric: str = "eval/cd",
    ):
        self.client = PatientClient(uri)
        self.run_name, self.metric = run_name, metric
        self.last_step = 0 if config.eval.only else config.train.steps
        found = find_trial_run(self.client, experiment_id, parent_run_id, trial_id)
        # Last step already in the run, per kind: a crash between a step's log and its evaluation
        # must not make the re-run evaluation look logged.
        self.logged_until = {"train": -1, "eval": -1}
        self.eval_set_tagged = False
        if found is None:
            run = self.client.create_run(
                experiment_id, run_name=run_name,
                tags={"mlflow.parentRunId": parent_run_id, "trial_id": trial_id, **tags})
            self.run_id = run.info.run_id
            _log_params(
                self.client, self.run_id, _params({k: v for k, v in config.flat().items() if k not in PER_TRIAL_PARAMS})
            )
            self.client.log_text(self.run_id, yaml.safe_dump(config.to_dict(), sort_keys=False), "config.yaml")
        else:
            self.run_id = found
            self.client.update_run(found, status="RUNNING")
            for kind, key in (("train", "train/loss"), ("eval", "eval/cd")):
                self.logged_until[kind] = max((m.step for m in self.client.get_metric_history(found, key)), default=-1)

    def _log(self, step: int, metrics: dict[str, float]) -> None:
        now = int(time.time() * 1000)
        named = {("system/" + k.removeprefix("train/") if k in SYSTEM_METRICS else k): v for k, v in metrics.items()}
        self.client.log_batch(
            self.run_id, metrics=[Metric(k, _shown(k, float(v)), now, step) for k, v in named.items()]
        )

    def on_start(self, record: dict[str, str]) -> None:
        self.client.log_batch(self.run_id, tags=[RunTag(f"repro.{k}", v) for k, v in record.items()])

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        if step > self.logged_until["train"]:
            self._log(step, metrics)

    def on_eval(self, step: int, metrics: dict[str, float], files: list[Path]) -> None:
        if step <= self.logged_until["eval"]:
            return
        # Baselines depend on the evaluation set only: the driver logs them once on the parent run; the
        # per-category scores become final/… when the driver closes the run (SweepRun._log_final).
        self._log(step, {k: v for k, v in metrics.items() if not k.startswith("baseline/") and not _per_category(k)})
        if not self.eval_set_tagged:  # every evaluation of a run scores the same evaluation set
            for path in (p for p in files if p.name == "objects.csv"):
                with path.open(newline="") as fh:
                    first = next(csv.DictReader(fh), None)
                if first is not None:
                    self.client.set_tag(self.run_id, "eval_set", first["eval_set"])
                    self.eval_set_tagged = True
        for path in files:
            sub = EVAL_FOLDERS.get(path.suffix)
            self.client.log_artifact(self.run_id, str(path), f"eval/step_{step:07d}" + (f"/{sub}" if sub else ""))
        # The curve at the last evaluation only: MLflow charts the metrics live, and drawing it took ~0.7 s
        # per evaluation (benchmarks/RESULTS.md).
        if files and step >= self.last_step:
            curve = learning_curve_png(self.client, self.run_id, files[0].parent, self.metric, self.run_name)
            if curve is not None:
                self.client.log_artifact(self.run_id, str(curve), "curves")

    def on_checkpoint(self, step: int, path: Path) -> None:
        self.client.set_tag(self.run_id, "checkpoint", str(path))
