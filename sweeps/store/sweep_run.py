"""The sweep's parent run, written from the Ray driver: opened with the spec, expanded grid and results table as
artifacts, each child closed with Tune's verdict (finished, stopped early, failed + reason), the baselines logged
once per evaluation set. The child run itself is written by the trial (:class:`sweeps.store.trial_run.TrialRun`).

All calls go through an explicit client (:func:`sweeps.store.tracking.client`; no global active run), so a Ray
actor reused for the next trial carries nothing over.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from mlflow.entities import Metric

from cdm.metric_names import CD, object_column
from cdm.provenance import code_version
from sweeps.store.read import find_trial_run, is_per_category, last_objects
from sweeps.store.tracking import EXPERIMENT_KIND, client, experiment, log_params, source_tags

__all__ = ["SweepRun", "baselines_by_eval_set", "with_logged_baselines"]

_BATCH_METRICS = 1000  # MLflow's limit of metrics per log_batch call


def _eval_set(outcome: Any) -> str:
    """The fingerprint of the evaluation set a :class:`sweeps.compare.outcomes.TrialOutcome` was scored on;
    ``""`` without per-object rows."""
    return str(outcome.objects[0].get("eval_set", "")) if outcome.objects else ""


def baselines_by_eval_set(outcomes: Sequence[Any]) -> dict[str, dict[str, float]]:
    """Evaluation-set fingerprint → the ``baseline/…`` metrics scored on it (the same in every trial on it):
    the first finished trial's (``outcomes``: :class:`sweeps.compare.outcomes.TrialOutcome`), as
    :meth:`SweepRun.log_results` logs them. A trial without per-object rows files its baselines under ``""``."""
    out: dict[str, dict[str, float]] = {}
    for o in (o for o in outcomes if o.finished):
        found = {k: v for k, v in o.metrics.items() if k.startswith("baseline/")}
        if found and _eval_set(o) not in out:
            out[_eval_set(o)] = found
    return out


def with_logged_baselines(outcomes: Sequence[Any], baselines: Mapping[str, Mapping[str, float]]) -> list[Any]:
    """``outcomes``, each finished one holding the baselines of its evaluation set as the parent run logs them
    (``baselines``: :func:`baselines_by_eval_set`) in place of its own: the numbers the report reads back
    (:func:`sweeps.store.read.parent_baselines`), so the runner's ``results.csv`` and the report's are
    written from the same floats even where two trials' baselines differed in the last bit."""
    def held(o: Any) -> Any:
        own = {k: v for k, v in o.metrics.items() if not k.startswith("baseline/")}
        return replace(o, metrics={**own, **baselines.get(_eval_set(o), {})})

    return [held(o) if o.finished and _eval_set(o) in baselines else o for o in outcomes]


class SweepRun:
    """The parent run of one sweep, driven from the Ray driver."""

    def __init__(self, uri: str, experiment_id: str, run_id: str):
        self.uri, self.experiment_id, self.run_id = uri, experiment_id, run_id
        self.client = client(uri)

    @classmethod
    def start(cls, uri: str, name: str, run_name: str, tags: dict[str, str], params: dict[str, Any]) -> SweepRun:
        """Create the experiment ``name`` if needed and open a new parent run."""
        store = client(uri)
        experiment_id = experiment(store, name, uri)
        source = source_tags(code_version()["git_commit"])
        run = store.create_run(experiment_id, run_name=run_name, tags={"kind": "sweep", **source, **tags})
        log_params(store, run.info.run_id, params)
        return cls(uri, experiment_id, run.info.run_id)

    @classmethod
    def reopen(cls, uri: str, run_id: str) -> SweepRun:
        """The parent run of an interrupted sweep, marked running again."""
        store = client(uri)
        run = store.get_run(run_id)
        store.set_experiment_tag(run.info.experiment_id, *EXPERIMENT_KIND)  # a sweep begun before the tag
        store.update_run(run_id, status="RUNNING")
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
        checkpoint: str | None = None,
    ) -> None:
        """Set a child run's final status from Tune's verdict; creates the run if the trial died before opening it.

        Args:
            status: ``FINISHED`` or ``FAILED``.
            last: the trial's last reported result (Tune's ``trial.last_result``): the source of the
                per-category scores, which the child logs only here, as ``final/…``.
            checkpoint: the trial's newest checkpoint in the sweep's storage (the full training state, to
                continue from), tagged ``checkpoint``; the weights for inference are the run's ``model/``.
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
        if checkpoint is not None:
            self.client.set_tag(run_id, "checkpoint", checkpoint)
        if status == "FINISHED":
            self._log_final(run_id, last or {})
        self.client.set_terminated(run_id, status=status)

    def _log_final(self, run_id: str, last: Mapping[str, object]) -> None:
        """Log the last evaluation's ``eval/cd``, ``eval/f1`` and their per-category scores as ``final/…`` metrics.

        Stable names to sort, search and compare by in the UI (``metrics.`final/f1/chair` > 0.6``), whatever
        step a trial ended at (ASHA stops some early), at full precision: the same floats the trial reported
        to Tune, so the report rebuilds the runner's ``results.csv`` from them byte for byte. Logged here, on
        the driver, once Tune's verdict is in: the trial itself cannot tell its last evaluation from an
        intermediate one. The overall scores come from the child's own history; the per-category ones from
        ``last`` (the child logs no series of them).
        """
        history = self.client.get_metric_history(run_id, CD.key)
        latest = self.client.get_run(run_id).data.metrics
        if not history or any(k.startswith("final/") for k in latest):  # logged once: a resumed trial may close twice
            return
        step = max(m.step for m in history)
        now = int(time.time() * 1000)
        scores = {**{k: v for k, v in last.items() if is_per_category(k) and isinstance(v, (int, float))}, **latest}
        self.client.log_batch(run_id, metrics=[
            Metric("final/" + k.removeprefix("eval/"), float(v), now, step) for k, v in scores.items()
            if object_column(k) is not None])

    def trial_objects(self, trial_id: str) -> list[dict[str, object]]:
        """Per-object rows (``objects.csv``) of the trial's last logged evaluation; empty if none."""
        run_id = find_trial_run(self.client, self.experiment_id, self.run_id, trial_id)
        return [] if run_id is None else last_objects(self.client, run_id)

    def log_results(self, baselines: dict[str, dict[str, float]], description: str) -> None:
        """The sweep's results on the parent run: the baselines once per evaluation set (``baseline/sphere/f1``,
        ``baseline/sphere/f1/chair``; ``eval_set <id>/baseline/…`` when the cells were scored on several) as
        metrics at full precision, and ``description`` as the run's description. The cells' results are the
        run's ``results.md`` and its children.

        Args:
            baselines: evaluation-set fingerprint → ``baseline/<name>/<metric>[/<category>]`` → value.
        """
        now = int(time.time() * 1000)
        metrics = [Metric(("" if len(baselines) == 1 else f"eval_set {eval_set}/") + k, float(v), now, 0)
                   for eval_set, values in baselines.items() for k, v in values.items()]
        for i in range(0, len(metrics), _BATCH_METRICS):
            self.client.log_batch(self.run_id, metrics=metrics[i:i + _BATCH_METRICS])
        self.client.set_tag(self.run_id, "mlflow.note.content", description)

    def end(self, status: str = "FINISHED") -> None:
        self.client.set_terminated(self.run_id, status=status)
