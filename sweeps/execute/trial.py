"""One trial on Ray: the Tune trainable and the Ray Train loop around ``cdm.train.fit``.

Each Tune trial builds and fits a Ray Train ``TorchTrainer`` (Ray Train V2's pattern;
``Tuner(trainer)`` is deprecated) whose loop is :func:`train_loop`, given the trial's
:class:`TrialJob`. ``resources.workers_per_trial`` picks how:

- ``0`` — Train's local mode: the loop runs inside the trial's own actor, seconds of start-up per
  trial where a worker group costs tens (``benchmarks/RESULTS.md``, "Code choices"). So small
  machines run local mode, the default of the smoke and local profiles.
- ``>= 1`` — real Train workers (DDP over gloo on CPU, NCCL on GPU), what scales on a cluster.

Local mode only accepts ``ray.tune.report``/``ray.tune.get_checkpoint`` and real workers only
``ray.train.report``/``ray.train.get_checkpoint``; :class:`_RayReporter` picks the pair once.
"""

from __future__ import annotations

import functools
import hashlib
import os
import shutil
import tempfile
from collections.abc import Callable, Mapping, Sequence
from contextlib import nullcontext, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ray
import ray.train
import ray.tune
from ray.train.torch import TorchTrainer

from cdm.config import Config
from cdm.io.files import is_uri
from cdm.metric_names import METRICS
from cdm.prior_model import ensure_priors
from cdm.shared import SharedStore
from cdm.train import Callback, fit
from sweeps.execute.cores import CoreLease
from sweeps.execute.progress import StepReporter, quiet_actor_exit, quiet_loggers
from sweeps.execute.pruning import KEEP
from sweeps.plan.trials import Cell, SweepPlan
from sweeps.store.files import private_folder, storage_location
from sweeps.store.read import finished_trial_metrics
from sweeps.store.trial_run import TrialRun

__all__ = [
    "TrialJob", "TrialProgress", "TrialSetup", "fit_trial", "learning_curve", "remove_sweep_scratch", "run_trial",
    "sweep_scratch", "train_loop", "trial_dir_name", "trial_job", "trial_scratch",
]


@dataclass(frozen=True)
class TrialSetup:
    """Everything a trial needs besides its Tune config; shipped once with ``tune.with_parameters``."""

    plan: SweepPlan
    cells: Mapping[str, Cell]
    """The grid's trials by label, each with the config :func:`sweeps.plan.trials.expand` built once."""
    sweep_dir: str
    tracking_uri: str
    experiment_id: str
    parent_run_id: str
    code: dict[str, str]
    """The driver's :func:`cdm.provenance.code_version` (trials may run on a copy without git)."""
    shared_root: str | None = None
    """The sweep's store of shared training views and evaluation sets (:mod:`sweeps.execute.precompute`)."""
    lease_cores: int = 0
    """Core leases the trials take turns on (:mod:`sweeps.execute.cores`); 0 = none."""


class _RayReporter(Callback):
    """Reports each evaluation to Ray together with the checkpoint ``fit`` writes right after it; last among a
    trial's callbacks, since the checkpoint leaves the scratch folder once reported."""

    def __init__(self, local: bool, rank: int):
        self.local, self.rank = local, rank
        self.last_train: dict[str, float] = {}
        self.last_eval: dict[str, float] = {}

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        self.last_train = metrics

    def on_eval(self, step: int, metrics: dict[str, float], files: list[Path]) -> None:
        self.last_eval = metrics

    def on_checkpoint(self, step: int, path: Path) -> None:
        # fit() evaluates, then checkpoints, at the same step: one report carries both. Ray copies the
        # checkpoint into the sweep's storage before the report returns; the scratch copy then goes, so each
        # checkpoint is kept once (Ray Train's own delete_local_checkpoint_after_upload).
        metrics = {**self.last_train, **self.last_eval, "step": step}
        if self.local:
            ray.tune.report(metrics, checkpoint=ray.tune.Checkpoint.from_directory(path))
            shutil.rmtree(path)
        elif self.rank == 0:
            ray.train.report(metrics, checkpoint=ray.train.Checkpoint.from_directory(path),
                             delete_local_checkpoint_after_upload=True)
        else:
            ray.train.report(metrics)


class TrialProgress(Callback):
    """One line per log interval and evaluation; Ray forwards it to the driver's terminal."""

    def __init__(self, label: str, steps: int, metric: str):
        self.label, self.steps, self.metric = label, steps, metric

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        print(f"[{self.label}] step {step}/{self.steps}  loss {metrics['train/loss']:.4f}  "
              f"{metrics['train/steps_per_s']:.2f} steps/s", flush=True)

    def on_eval(self, step: int, metrics: dict[str, float], files: list[Path]) -> None:
        keys = dict.fromkeys((*(m.key for m in METRICS.values()), self.metric))
        shown = "  ".join(f"{k} {metrics[k]:.4g}" for k in keys if k in metrics)
        print(f"[{self.label}] eval at step {step}: {shown}", flush=True)


@dataclass(frozen=True)
class TrialJob:
    """One trial's input to :func:`train_loop`, built once by :func:`trial_job` from its cell."""

    config: Config
    """The trial's validated config (its cell's, :func:`trial_job`), writing into the trial's folder."""
    local: bool
    """Train's local mode: the loop runs in the trial's own actor (``resources.workers_per_trial == 0``)."""
    label: str
    trial_id: str
    metric: str
    tags: dict[str, str]
    prior_dir: str
    """Where ``prior_checkpoint: auto`` caches category priors (:func:`_prior_dir`)."""
    setup: TrialSetup


def train_loop(job: TrialJob) -> None:
    """Ray Train loop (local mode or each worker): resume if Ray has a checkpoint, fit."""
    quiet_loggers()
    rank = 0 if job.local else ray.train.get_context().get_world_rank()
    checkpoint = ray.tune.get_checkpoint() if job.local else ray.train.get_checkpoint()
    with checkpoint.as_directory() if checkpoint is not None else nullcontext() as resume_from:
        if resume_from is not None:  # named where it is kept: as_directory() may be a temporary download
            print(f"[{job.label}] resuming from {storage_location(job.setup.sweep_dir, checkpoint.path)}", flush=True)
        fit_trial(job, rank, functools.partial(_trackers, job), resume_from)


def _trackers(job: TrialJob, config: Config) -> list[Callback]:
    """Rank 0's links to the sweep: the driver's step counter and the trial's MLflow child run."""
    setup = job.setup
    return [
        StepReporter(setup.parent_run_id, job.label),
        TrialRun(setup.tracking_uri, setup.experiment_id, setup.parent_run_id, job.trial_id, job.label, job.tags,
                 config, job.metric, learning_curve),
    ]


def learning_curve(history: Mapping[str, Sequence[tuple[int, float]]], folder: Path, metric: str, title: str,
                   f1_threshold: float) -> Path | None:
    """One trial's training curves (:func:`sweeps.compare.plots.training_curves`: the loss terms apart, ``metric``
    once the run holds two evaluations) as ``folder/learning_curve.png``, titled ``title``, F1 labelled at the
    run's ``f1_threshold``; None while ``history`` (series of :data:`sweeps.store.trial_run.CURVE_KEYS` and
    ``metric``) holds no curve (no loss logged, fewer than two evaluations)."""
    from sweeps.compare.plots import has_curve, training_curves

    if not has_curve(history, metric):
        return None
    return training_curves({title: history}, {title: title}, metric, title, folder / "learning_curve.png",
                           f1_thresholds=f1_threshold)


def fit_trial(job: TrialJob, rank: int, trackers: Callable[[Config], list[Callback]],
              resume_from: str | None = None) -> None:
    """``cdm.train.fit`` of the trial's handed-down config on one worker: its rank's folder, its category
    priors, Ray's reporter, the core lease and, on rank 0, the progress lines and ``trackers(config)``."""
    config = job.config
    if rank > 0:  # workers on one node must not overwrite rank 0's checkpoints and evaluation files
        config = config.replace(**{"train.out_dir": str(Path(config.train.out_dir) / f"rank_{rank}")})
    # sampling.blend.prior_checkpoint: auto — one category prior per category, trained once per sweep
    # in its folder (the first trial to need it trains it, the others wait on its lock).
    config = ensure_priors(config, job.prior_dir, lambda line: print(f"[{job.label}] {line}", flush=True))
    callbacks: list[Callback] = []
    setup = job.setup
    lease = CoreLease(f"{setup.sweep_dir}/cores", setup.lease_cores) if setup.lease_cores else None
    if lease is not None:
        callbacks.append(lease)
    if rank == 0:
        callbacks += [TrialProgress(job.label, config.train.steps, job.metric), *trackers(config)]
    callbacks.append(_RayReporter(job.local, rank))
    shared = None if setup.shared_root is None else SharedStore(setup.shared_root)
    try:
        fit(config, callbacks, resume_from=resume_from, shared=shared)
    finally:
        if lease is not None:  # reused actors outlive the trial: the next one must find the core free
            lease.release()


def trial_dir_name(trial_id: str) -> str:
    """The trial's folder in the sweep's storage (Tune's ``trial_dirname_creator``): its checkpoints and results."""
    return f"trial_{trial_id}"


def trial_scratch(sweep_dir: str, trial_id: str) -> Path:
    """The node-local folder a trial trains in (``train.out_dir``), in this user's private temporary folder.

    Only files on their way live there: a checkpoint until Ray has copied it into the sweep's storage
    (:class:`_RayReporter` then deletes it), evaluation files for the child run to log; the folder goes when
    the trial ends (:func:`run_trial`; a Train worker's stays on its node, never recorded), the sweep's when the
    sweep ends (:func:`remove_sweep_scratch`). Not Tune's
    trial folder (``get_trial_dir()``): that lies in Ray's temporary session folder, gone after ``ray stop``,
    and on the head node Tune's syncer copies it whole into the sweep folder, which then held every
    checkpoint twice.
    """
    return sweep_scratch(sweep_dir) / trial_dir_name(trial_id)


def sweep_scratch(sweep_dir: str) -> Path:
    """This node's folder of the sweep's trial scratch folders (:func:`trial_scratch`), in this user's private
    temporary folder: one per sweep folder, which one driver at a time runs (:mod:`sweeps.execute.claim`)."""
    sweep = hashlib.sha256(sweep_dir.encode()).hexdigest()[:16]
    return private_folder(Path(tempfile.gettempdir()) / f"cdm-trials-{os.getuid()}") / sweep


def remove_sweep_scratch(sweep_dir: str, whole: bool) -> None:
    """At the sweep's end (its trials are over), this node's :func:`sweep_scratch`: with what it holds when
    ``whole`` (trials in Train's local mode, each folder its own trial's: a killed trial's files and an object-store
    sweep's prior cache go too), else only if empty (a Train worker's folder stays on its node). A link there is
    removed, never followed: ``shutil.rmtree`` refuses one at the top and unlinks those below."""
    folder = sweep_scratch(sweep_dir)
    if whole:  # a file that cannot be removed stays rather than failing a finished sweep
        shutil.rmtree(folder, ignore_errors=True)
    with suppress(OSError):  # absent, or not empty
        folder.rmdir()


def trial_job(setup: TrialSetup, tune_config: dict[str, Any], trial_id: str, node_id: str, scratch: Path) -> TrialJob:
    """The trial a Tune config stands for (``{"cell": label}``: a grid cell as the plan built it; sampled
    values: :meth:`~sweeps.plan.trials.SweepPlan.sampled_cell`), training in ``scratch`` (:func:`trial_scratch`)."""
    plan = setup.plan
    cell = plan.sampled_cell(tune_config) if plan.spec.search.sampled else setup.cells[tune_config["cell"]]
    categories = ",".join(cell.config.data.categories) or "all"
    tags = {
        "cell": cell.name,
        "group": cell.group,
        "seed": str(cell.seed),
        "spec": plan.spec.name,
        "profile": plan.profile.name,
        # `category` is the short name the UI's search box is documented with (docs/mlflow.md, Search box).
        "categories": categories,
        "category": categories,
        # Where Ray keeps the trial in the sweep's storage (its checkpoints, result.json), not a node's disk.
        "tune_trial_dir": f"{setup.sweep_dir}/{trial_dir_name(trial_id)}",
        "ray_node_id": node_id,
        **{f"repro.{k}": v for k, v in setup.code.items()},
    }
    return TrialJob(
        config=cell.config.replace(**{"train.out_dir": str(scratch)}),
        local=plan.profile.resources.workers_per_trial == 0,
        label=cell.label,
        trial_id=trial_id,
        metric=plan.spec.metric.name,
        tags=tags,
        prior_dir=_prior_dir(setup.sweep_dir, scratch),
        setup=setup,
    )


def run_trial(tune_config: dict[str, Any], setup: TrialSetup) -> None:
    """Tune function trainable: one trial = one ``TorchTrainer.fit`` of :func:`train_loop`."""
    quiet_loggers()  # "Running in local mode …" and the like, logged in this process
    quiet_actor_exit()
    ctx = ray.tune.get_context()
    trial_id = ctx.get_trial_id()
    scratch = trial_scratch(setup.sweep_dir, trial_id)
    job = trial_job(setup, tune_config, trial_id, ray.get_runtime_context().get_node_id(), scratch)
    done = finished_trial_metrics(setup.tracking_uri, setup.experiment_id, setup.parent_run_id, trial_id)
    if done is not None:
        print(
            f"[{job.label}] already finished before the driver stopped (its MLflow run says so): not re-run",
            flush=True,
        )
        ray.tune.report(done)
        return
    r = setup.plan.profile.resources
    per_worker = {"CPU": r.cpus_per_worker, **({"GPU": r.gpus_per_worker} if r.gpus_per_worker else {})}
    trainer = TorchTrainer(
        # Bound, not passed as train_loop_config: Train hands that on as a plain dict.
        functools.partial(train_loop, job),
        scaling_config=ray.train.ScalingConfig(
            num_workers=r.workers_per_trial,
            use_gpu=r.gpus_per_worker > 0,
            resources_per_worker=per_worker if r.workers_per_trial else None,
        ),
        run_config=ray.train.RunConfig(
            # Named after the trial so a restored trial resumes its own Train run.
            name=f"trial_{trial_id}",
            storage_path=f"{setup.sweep_dir}/train",
            failure_config=ray.train.FailureConfig(max_failures=setup.plan.spec.failure.max_retries),
            # Safe here, unlike Tune's (sweeps/execute/pruning.py): Train writes the state naming its newest
            # checkpoints before deleting older ones (ray/train/v2/.../checkpoint_manager.py).
            checkpoint_config=ray.train.CheckpointConfig(num_to_keep=KEEP),
            callbacks=_tune_report_callbacks() if r.workers_per_trial else None,
        ),
    )
    try:
        trainer.fit()
    finally:  # its checkpoints are in storage, its evaluation files in MLflow: nothing left to keep
        if job.local and scratch.exists():  # (a Train worker's folder is on its own node; absent: failed early)
            shutil.rmtree(scratch)
        with suppress(OSError):  # the sweep's folder on this node, once its last trial here is gone
            scratch.parent.rmdir()


def _prior_dir(sweep_dir: str, scratch: Path) -> str:
    """Where ``prior_checkpoint: auto`` caches category priors: the sweep folder, shared by every trial.

    Its lock needs a file system, so with an object-store ``sweep_dir`` (``s3://…``) each node keeps
    its own cache beside the sweep's trial scratch folders (:func:`trial_scratch`).
    """
    if is_uri(sweep_dir):
        return str(scratch.parent / "priors")
    return str(Path(sweep_dir) / "priors")


def _tune_report_callbacks() -> list:
    from ray.tune.integration.ray_train import TuneReportCallback

    return [TuneReportCallback()]
