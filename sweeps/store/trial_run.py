"""A trial's record: its child run under the sweep's parent run, written from exactly one place.

The trial's rank-0 training process feeds it as a :class:`cdm.train.Callback`, because SQLite locks under
many writers. A child is found again by its ``trial_id`` tag, so a resumed trial continues its own run and
skips steps it had already logged: no duplicates. The driver closes it with Tune's verdict
(:meth:`sweeps.store.sweep_run.SweepRun.close_trial`).
"""

from __future__ import annotations

import importlib.util
import json
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import yaml
from mlflow.entities import Dataset, DatasetInput, InputTag, Metric, RunTag

from cdm.checkpoint import load_checkpoint, save_checkpoint
from cdm.config import Config
from cdm.io.csv import read_csv
from cdm.metric_names import CD, COMPUTE_METRIC, F1, f1_at
from cdm.provenance import code_version, installed_packages
from cdm.train import Callback
from sweeps.mlflow_model import MODEL_NAME, log_model
from sweeps.store.read import find_trial_run, is_per_category, metric_histories
from sweeps.store.tracking import client, log_params, source_tags

__all__ = [
    "CURVE_KEYS", "EVAL_FOLDERS", "F1_TAG", "MODEL_TAG", "PACKAGES_FILE", "PER_TRIAL_PARAMS",
    "SYSTEM_METRICS_INTERVAL_S", "Curve", "TrialRun", "eval_dataset", "system_metrics_monitor",
]

MODEL_TAG = "model"
"""The tag holding the run's ``runs:/<run id>/model`` URI, to paste into ``cdm-lab evaluate --checkpoint``."""

F1_TAG = F1.name
"""The tag naming what a trial's ``eval/f1`` and ``final/f1`` mean (:func:`cdm.metric_names.f1_at` of its
``eval.f1_threshold``): the keys stay the same at every threshold, so runs compare by name."""

PER_TRIAL_PARAMS = ("train.out_dir",)
"""Config fields that differ in every trial by construction (its own folder): not params, so the
compare view shows only what the cells set."""


PACKAGES_FILE = "environment/packages.txt"
"""The child run's artifact listing every installed package (``name==version``), the list whose digest the
``repro.packages_digest`` tag holds (:func:`cdm.provenance.installed_packages`)."""

SYSTEM_METRICS_INTERVAL_S = 10.0
"""Seconds between two samples of MLflow's system-metrics monitor (CPU, memory, disk, network; ``system/…``):
MLflow's own default. A sample is a few psutil calls and one read of the run in a background thread, logged at
once: nothing the training loop waits on. ``MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL`` overrides it, as MLflow
documents."""


def system_metrics_monitor(uri: str, run_id: str, resumed: bool):
    """MLflow's own system-metrics monitor on ``run_id`` (:class:`mlflow.system_metrics.system_metrics_monitor.
    SystemMetricsMonitor`, what ``mlflow.start_run(log_system_metrics=True)`` starts), sampling every
    :data:`SYSTEM_METRICS_INTERVAL_S`; it stops itself once the run is no longer ``RUNNING``. None, and nothing
    started, where psutil (its source of numbers) is not installed or ``MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING``
    is set to false. ``resumed``: a resumed trial's series continues after its earlier samples."""
    from mlflow.environment_variables import MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING

    off = MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING.is_set() and not MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING.get()
    if off or importlib.util.find_spec("psutil") is None:
        return None
    from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

    monitor = SystemMetricsMonitor(run_id, sampling_interval=SYSTEM_METRICS_INTERVAL_S, resume_logging=resumed,
                                   tracking_uri=uri)
    monitor.start()
    return monitor


def eval_dataset(config: Config, fingerprint: str, objects: list[dict[str, str]]) -> DatasetInput:
    """The evaluation set as an MLflow dataset input (``log_inputs``; the run page's "Datasets used"): named by
    the data kind and ``eval.protocol``, its digest the evaluation-set fingerprint
    (:func:`cdm.evaluate.build_eval_set`: equal digests, comparable scores), its source the data root (a
    ``local`` source) or, for data generated in code, the generator (a ``code`` source); the profile counts
    ``objects`` (the scored rows of ``objects.csv``) per category. Tagged ``mlflow.data.context=eval``."""
    data = config.data
    if data.root:
        source_type, source = "local", {"uri": str(data.root)}
    else:
        source_type, source = "code", {"tags": {"data.kind": data.kind, "data.seed": str(data.seed)}}
    categories: dict[str, int] = {}
    for row in objects:
        categories[row["category"]] = categories.get(row["category"], 0) + 1
    profile = {"num_objects": len(objects), "categories": categories}
    dataset = Dataset(f"{data.kind} {config.eval.protocol} eval", fingerprint, source_type, json.dumps(source),
                      profile=json.dumps(profile))
    return DatasetInput(dataset, [InputTag("mlflow.data.context", "eval")])


EVAL_FOLDERS = {".png": "panels", ".ply": "clouds"}
"""Sub-folder of ``eval/step_<N>/`` per file suffix (``objects.csv`` stays at the top): a reader finds the
panels apart from the dozens of clouds."""


CURVE_KEYS = ("train/loss", "train/loss_diffusion")
"""The training series a trial's learning curve draws, besides its sweep's metric."""

Curve = Callable[[Mapping[str, Sequence[tuple[int, float]]], Path, str, str, float], "Path | None"]
"""Draws a trial's learning curve: ``(history, folder, metric, title, f1_threshold)`` → the PNG written in
``folder``, or None while ``history`` (metric → ``(step, value)`` series of :data:`CURVE_KEYS` and ``metric``)
holds no curve; :func:`sweeps.execute.trial.learning_curve`."""


class TrialRun(Callback):
    """The child run of one trial, fed by :func:`cdm.train.fit`'s callbacks (rank 0 only); ``curve`` draws its
    learning curve at the last evaluation.

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
        metric: str = CD.key,
        curve: Curve | None = None,
    ):
        self.client = client(uri)
        self.run_name, self.metric, self.curve = run_name, metric, curve
        self.last_step = 0 if config.eval.only else config.train.steps
        self.budget_s = config.train.compute_budget_s
        self.f1_threshold = config.eval.f1_threshold
        found = find_trial_run(self.client, experiment_id, parent_run_id, trial_id)
        # Last step already in the run, per kind: a crash between a step's log and its evaluation
        # must not make the re-run evaluation look logged.
        self.logged_until = {"train": -1, "eval": -1}
        self.eval_set_tagged = False
        # Where the trial wrote (node-local scratch) is no part of its config: the record's places are its tags.
        tree = config.to_dict()
        tree["train"].pop("out_dir")
        self.config_yaml = yaml.safe_dump(tree, sort_keys=False)
        self.record: dict[str, str] = {}
        self.config, self.monitor, self.resumed = config, None, found is not None
        if found is None:
            # A sweep's trial carries the driver's commit; a re-run's is the checkout it runs from.
            commit = tags.get("repro.git_commit") or code_version()["git_commit"]
            run = self.client.create_run(
                experiment_id, run_name=run_name,
                tags={"mlflow.parentRunId": parent_run_id, "trial_id": trial_id, F1_TAG: f1_at(self.f1_threshold),
                      **source_tags(commit), **tags})
            self.run_id = run.info.run_id
            kept = {k: v for k, v in config.flat().items() if k not in PER_TRIAL_PARAMS}
            log_params(self.client, self.run_id, kept)
            self.client.log_text(self.run_id, self.config_yaml, "config.yaml")
        else:
            self.run_id = found
            self.client.update_run(found, status="RUNNING")
            for kind, key in (("train", "train/loss"), ("eval", CD.key)):
                self.logged_until[kind] = max((m.step for m in self.client.get_metric_history(found, key)), default=-1)

    def _log(self, step: int, metrics: dict[str, float]) -> None:
        """``metrics`` at ``step`` as the trainer reported them: full float precision, under their own names."""
        now = int(time.time() * 1000)
        self.client.log_batch(self.run_id, metrics=[Metric(k, float(v), now, step) for k, v in metrics.items()])

    def on_start(self, record: dict[str, str]) -> None:
        self.record = record
        self.client.log_batch(self.run_id, tags=[RunTag(f"repro.{k}", v) for k, v in record.items()])
        self.client.log_text(self.run_id, "\n".join(installed_packages()) + "\n", PACKAGES_FILE)
        self.monitor = system_metrics_monitor(self.client.tracking_uri, self.run_id, self.resumed)

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        if step > self.logged_until["train"]:
            self._log(step, metrics)

    def on_eval(self, step: int, metrics: dict[str, float], files: list[Path]) -> None:
        if step <= self.logged_until["eval"]:
            return
        # Baselines depend on the evaluation set only: the driver logs them once on the parent run; the
        # per-category scores become final/… when the driver closes the run (SweepRun._log_final).
        self._log(step, {k: v for k, v in metrics.items() if not k.startswith("baseline/") and not is_per_category(k)})
        if not self.eval_set_tagged:  # every evaluation of a run scores the same evaluation set
            self._log_eval_set(files)
        for path in files:
            sub = EVAL_FOLDERS.get(path.suffix)
            self.client.log_artifact(self.run_id, str(path), f"eval/step_{step:07d}" + (f"/{sub}" if sub else ""))
        # The curve at the last evaluation only: MLflow charts the metrics live, and drawing it took ~0.7 s
        # per evaluation (benchmarks/RESULTS.md).
        last = step >= self.last_step or (self.budget_s is not None and metrics[COMPUTE_METRIC] >= self.budget_s)
        if files and last and self.curve is not None:
            # Read from the run's history (not in-memory lists): the curve stays whole across a resumed trial.
            history = metric_histories(self.client, self.run_id, (*CURVE_KEYS, self.metric))
            curve = self.curve(history, files[0].parent, self.metric, self.run_name, self.f1_threshold)
            if curve is not None:
                self.client.log_artifact(self.run_id, str(curve), "curves")
        if last and self.monitor is not None:  # the last evaluation: the samples so far logged
            self.monitor.finish()
            self.monitor = None

    def _log_eval_set(self, files: list[Path]) -> None:
        """The evaluation set the run is scored on: its fingerprint as the tag ``eval_set`` (what the results
        stage looks the parent's baselines up by) and as the digest of the run's dataset input
        (:func:`eval_dataset`), both from the evaluation's ``objects.csv``."""
        for path in (p for p in files if p.name == "objects.csv"):
            rows = list(read_csv(path, "evaluation"))
            if rows:
                fingerprint = rows[0]["eval_set"]
                self.client.set_tag(self.run_id, "eval_set", fingerprint)
                self.client.log_inputs(self.run_id, datasets=[eval_dataset(self.config, fingerprint, rows)])
                self.eval_set_tagged = True

    def on_checkpoint(self, step: int, path: Path) -> None:
        """The checkpoint's weights for inference become the run's MLflow model ``model``
        (:func:`sweeps.mlflow_model.log_model`), replacing the previous evaluation's: the run keeps the weights of
        its last checkpoint, also where ASHA stopped it early. Continuing training needs the full checkpoint, which
        Ray keeps in the sweep's storage (tag ``checkpoint``, set by the driver)."""
        with tempfile.TemporaryDirectory(prefix="cdm-model-") as tmp:
            folder = Path(tmp) / "checkpoint"
            save_checkpoint(load_checkpoint(path).for_inference(), folder)
            log_model(self.client, self.run_id, folder, {"step": step, **self.record})
        self.client.set_tag(self.run_id, MODEL_TAG, f"runs:/{self.run_id}/{MODEL_NAME}")
