"""Ray glue of a sweep: the Tune trainable, the Ray Train loop around ``cdm.train.fit``, and the Tuner.

Each Tune trial builds and fits a Ray Train ``TorchTrainer`` (Ray Train V2's pattern;
``Tuner(trainer)`` is deprecated) whose loop is :func:`train_loop`, given the trial's
:class:`TrialJob`. ``resources.workers_per_trial`` picks how:

- ``0`` — Train's local mode: the loop runs inside the trial's own actor, seconds of start-up per
  trial where a worker group costs tens (``benchmarks/RESULTS.md``, "Code choices"). So small
  machines run local mode, the default of the smoke and local profiles.
- ``>= 1`` — real Train workers (DDP over gloo on CPU, NCCL on GPU), what scales on a cluster.

Local mode only accepts ``ray.tune.report``/``ray.tune.get_checkpoint`` and real workers only
``ray.train.report``/``ray.train.get_checkpoint``; :class:`_RayReporter` picks the pair once.
Concurrency comes from the cluster's resources (:func:`sweeps.plan.resources.plan_concurrency`, sized
once by the runner), so trials never wait on each other for CPUs.
"""

from __future__ import annotations

import functools
import os
import shutil
import uuid
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ray
import ray.train
import ray.tune
from ray.train.torch import TorchTrainer

from cdm.config import Config
from cdm.prior_model import ensure_priors
from cdm.provenance import code_version
from cdm.shared import SharedStore
from cdm.train import Callback, fit
from sweeps.compare.outcomes import TrialOutcome, sweep_order, unstarted
from sweeps.execute.cores import CoreLease, lease_cores
from sweeps.execute.precompute import precompute, shared_root
from sweeps.execute.progress import StepReporter, quiet_loggers
from sweeps.execute.pruning import KEEP, CheckpointPruner, prune_finished
from sweeps.execute.tracking import SweepRun, TrialRun, finished_trial_metrics
from sweeps.plan.budget import SeedBudget
from sweeps.plan.resources import Concurrency
from sweeps.plan.search import search_kind
from sweeps.plan.trials import SweepPlan

__all__ = ["TrialJob", "TrialProgress", "TrialSetup", "error_summary", "run_sweep", "run_trial", "train_loop"]


@dataclass(frozen=True)
class TrialSetup:
    """Everything a trial needs besides its Tune config; shipped once with ``tune.with_parameters``."""

    plan: SweepPlan
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
    """Reports each evaluation to Ray together with the checkpoint ``fit`` writes right after it."""

    def __init__(self, local: bool, rank: int):
        self.local, self.rank = local, rank
        self.last_train: dict[str, float] = {}
        self.last_eval: dict[str, float] = {}

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        self.last_train = metrics

    def on_eval(self, step: int, metrics: dict[str, float], files: list[Path]) -> None:
        self.last_eval = metrics

    def on_checkpoint(self, step: int, path: Path) -> None:
        # fit() evaluates, then checkpoints, at the same step: one report carries both.
        metrics = {**self.last_train, **self.last_eval, "step": step}
        if self.local:
            ray.tune.report(metrics, checkpoint=ray.tune.Checkpoint.from_directory(path))
        else:
            ckpt = ray.train.Checkpoint.from_directory(path) if self.rank == 0 else None
            ray.train.report(metrics, checkpoint=ckpt)


class TrialProgress(Callback):
    """One line per log interval and evaluation; Ray forwards it to the driver's terminal."""

    def __init__(self, label: str, steps: int, metric: str):
        self.label, self.steps, self.metric = label, steps, metric

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        print(f"[{self.label}] step {step}/{self.steps}  loss {metrics['train/loss']:.4f}  "
              f"{metrics['train/steps_per_s']:.2f} steps/s", flush=True)

    def on_eval(self, step: int, metrics: dict[str, float], files: list[Path]) -> None:
        keys = dict.fromkeys(("eval/cd", "eval/f1", self.metric))
        shown = "  ".join(f"{k} {metrics[k]:.4g}" for k in keys if k in metrics)
        print(f"[{self.label}] eval at step {step}: {shown}", flush=True)


@dataclass(frozen=True)
class TrialJob:
    """One trial's input to :func:`train_loop`, built once by :func:`run_trial` from its cell."""

    config: Config
    """The trial's validated config (resolved once, by :mod:`sweeps.plan.trials`), writing into the trial's folder."""
    local: bool
    """Train's local mode: the loop runs in the trial's own actor (``resources.workers_per_trial == 0``)."""
    label: str
    trial_id: str
    metric: str
    tags: dict[str, str]
    prior_dir: str
    """Where ``prior_checkpoint: auto`` caches category priors (:func:`_prior_dir`)."""
    setup: TrialSetup
    """The sweep's side: MLflow parent run, shared store, core leases (in ``<sweep_dir>/cores``)."""


def train_loop(job: TrialJob) -> None:
    """Ray Train loop (local mode or each worker): resume if Ray has a checkpoint, fit."""
    quiet_loggers()
    rank = 0 if job.local else ray.train.get_context().get_world_rank()
    config = job.config
    if rank > 0:  # workers on one node must not overwrite rank 0's checkpoints and evaluation files
        config = config.replace(**{"train.out_dir": str(Path(config.train.out_dir) / f"rank_{rank}")})
    # sampling.blend.prior_checkpoint: auto — one category prior per category, trained once per sweep
    # in its folder (the first trial to need it trains it, the others wait on its lock).
    config = ensure_priors(config, job.prior_dir, lambda line: print(f"[{job.label}] {line}", flush=True))
    callbacks: list[Callback] = [_RayReporter(job.local, rank)]
    setup = job.setup
    lease = CoreLease(f"{setup.sweep_dir}/cores", setup.lease_cores) if setup.lease_cores else None
    if lease is not None:
        callbacks.append(lease)
    if rank == 0:
        callbacks += [
            TrialProgress(job.label, config.train.steps, job.metric),
            StepReporter(setup.parent_run_id, job.label),
            TrialRun(
                setup.tracking_uri,
                setup.experiment_id,
                setup.parent_run_id,
                job.trial_id,
                job.label,
                job.tags,
                config,
                job.metric,
            ),
        ]
    checkpoint = ray.tune.get_checkpoint() if job.local else ray.train.get_checkpoint()
    with checkpoint.as_directory() if checkpoint is not None else nullcontext() as resume_from:
        if resume_from is not None:
            print(f"[{job.label}] resuming from {resume_from}", flush=True)
        shared = None if setup.shared_root is None else SharedStore(setup.shared_root)
        try:
            fit(config, callbacks, resume_from=resume_from, shared=shared)
        finally:
            if lease is not None:  # reused actors outlive the trial: the next one must find the core free
                lease.release()


def run_trial(tune_config: dict[str, Any], setup: TrialSetup) -> None:
    """Tune function trainable: one trial = one ``TorchTrainer.fit`` of :func:`train_loop`."""
    quiet_loggers()  # "Running in local mode …" and the like, logged in this process
    plan = setup.plan
    cell = plan.trial(tune_config)
    ctx = ray.tune.get_context()
    trial_id = ctx.get_trial_id()
    done = finished_trial_metrics(setup.tracking_uri, setup.experiment_id, setup.parent_run_id, trial_id)
    if done is not None:
        print(
            f"[{cell.label}] already finished before the driver stopped (its MLflow run says so): not re-run",
            flush=True,
        )
        ray.tune.report(done)
        return
    r = plan.profile.resources
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
        "tune_trial_dir": ctx.get_trial_dir(),
        "ray_node_id": ray.get_runtime_context().get_node_id(),
        **{f"repro.{k}": v for k, v in setup.code.items()},
    }
    job = TrialJob(
        config=cell.config.replace(**{"train.out_dir": str(Path(ctx.get_trial_dir()) / "cdm")}),
        local=r.workers_per_trial == 0,
        label=cell.label,
        trial_id=trial_id,
        metric=plan.spec.metric.name,
        tags=tags,
        prior_dir=_prior_dir(setup.sweep_dir, ctx.get_trial_dir()),
        setup=setup,
    )
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
            failure_config=ray.train.FailureConfig(max_failures=plan.spec.failure.max_retries),
            # Safe here, unlike Tune's (sweeps/execute/pruning.py): Train writes the state naming its newest
            # checkpoints before deleting older ones (ray/train/v2/.../checkpoint_manager.py).
            checkpoint_config=ray.train.CheckpointConfig(num_to_keep=KEEP),
            callbacks=_tune_report_callbacks() if r.workers_per_trial else None,
        ),
    )
    trainer.fit()


def _prior_dir(sweep_dir: str, trial_dir: str) -> str:
    """Where ``prior_checkpoint: auto`` caches category priors: the sweep folder, shared by every trial.

    Its lock needs a file system, so with an object-store ``sweep_dir`` (``s3://…``) each node keeps
    its own cache beside the experiment's local trial folders.
    """
    if "://" in sweep_dir:
        return str(Path(trial_dir).parent / "priors")
    return str(Path(sweep_dir) / "priors")


def _tune_report_callbacks() -> list:
    from ray.tune.integration.ray_train import TuneReportCallback

    return [TuneReportCallback()]


def error_summary(text: str) -> str:
    """The exception line of a (Ray-wrapped) traceback, e.g. ``TrainingDiverged: loss became nan …``."""
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    for line in reversed(lines):
        if "Error" in line.split(":")[0] or "Diverged" in line.split(":")[0]:
            return line
    return lines[-1] if lines else text


class _TrialCloser(ray.tune.Callback):
    """Driver side: closes each child MLflow run with Tune's verdict and prints one line per trial."""

    def __init__(self, plan: SweepPlan, sweep_run: SweepRun):
        self.plan, self.sweep_run = plan, sweep_run

    def _label(self, trial) -> str:
        return self.plan.names(trial.config)[1]

    def _count(self, trials, ending=None) -> str:
        # Counted from Tune's trial list, so trials finished before a resume count too.
        done = {t.trial_id for t in trials if t.status in ("TERMINATED", "ERROR")} | (
            {ending.trial_id} if ending else set()
        )
        at_most = "≤" if self.plan.sequential else ""  # a sequential sweep's count is its worst case
        return f"{len(done)}/{at_most}{self.plan.num_trials} trials done"

    def on_trial_start(self, iteration, trials, trial, **info) -> None:
        print(f"▶ started [{self._label(trial)}] ({self._count(trials)})", flush=True)

    def on_trial_complete(self, iteration, trials, trial, **info) -> None:
        label = self._label(trial)
        step = trial.last_result.get("step", 0)
        early = step < self.plan.last_step(label)
        self.sweep_run.close_trial(trial.trial_id, label, "FINISHED", stopped_early=early, last=trial.last_result)
        value = trial.last_result.get(self.plan.spec.metric.name)
        shown = "no evaluation" if value is None else f"{self.plan.spec.metric.name} {value:.4g}"
        print(f"{'■ stopped early' if early else '✓ finished'} [{label}] at step {step}: {shown} "
              f"({self._count(trials, trial)})", flush=True)

    def on_trial_error(self, iteration, trials, trial, **info) -> None:
        label = self._label(trial)
        # Tune has just written the traceback to the trial's local error file (before syncing it).
        reason = error_summary(Path(trial.error_file).read_text()) if trial.error_file else "unknown error"
        self.sweep_run.close_trial(trial.trial_id, label, "FAILED", error=reason)
        print(f"✗ failed [{label}]: {reason} ({self._count(trials, trial)})", flush=True)


def _search(plan: SweepPlan, sweep_run: SweepRun, budget: SeedBudget | None) -> tuple[dict[str, Any], Any, int]:
    """Tune param space, search algorithm and sample count: grid cells by label, seeds until settled
    (:class:`sweeps.execute.seed_search.SeedSearcher`, at most every cell at ``max`` seeds), or the searcher
    of a kind that samples ``search.space`` (:data:`sweeps.plan.search.SEARCHES`)."""
    s = plan.spec.search
    if plan.sequential is not None:
        from sweeps.execute.seed_search import SeedSearcher

        return {}, SeedSearcher(plan, sweep_run, budget), plan.num_trials
    if not s.sampled:
        return {"cell": ray.tune.grid_search([c.label for c in plan.cells])}, None, 1
    study = (
        f"{plan.spec.name}-{plan.profile.name}-{uuid.uuid4().hex[:8]}"  # e.g. Optuna's study names are unique per sweep
    )
    searcher = search_kind(s.kind).tune_searcher(s, plan.spec.metric.name, plan.spec.metric.mode, study)
    return {}, searcher, plan.num_trials


def _scheduler(plan: SweepPlan):
    sch = plan.spec.scheduler
    if sch.kind == "none":
        return None
    from ray.tune.schedulers import ASHAScheduler

    # Time axis = the trainer's step (reported with every evaluation), which survives a resume.
    return ASHAScheduler(
        time_attr="step",
        max_t=plan.profile.steps,
        grace_period=sch.grace_evals * plan.profile.eval_every,
        reduction_factor=sch.reduction_factor,
        brackets=1,
    )


def _outcome(plan: SweepPlan, result, sweep_run: SweepRun) -> TrialOutcome:
    name, label = plan.names(result.config)
    cell = plan.grid_cell(label)
    trial_id = (result.metrics or {}).get("trial_id")
    metrics = {k: float(v) for k, v in (result.metrics or {}).items() if "/" in k and isinstance(v, (int, float))}
    if result.error is not None:
        status, error = "failed", error_summary(str(result.error))
    else:
        error = None
        step = (result.metrics or {}).get("step")
        status = "pending" if step is None else ("stopped" if step < plan.last_step(label) else "ok")
    objects = tuple(sweep_run.trial_objects(trial_id)) if trial_id and status != "failed" else ()
    paper_label, paper = (cell.paper_label, cell.paper) if cell else (None, {})
    return TrialOutcome(label, name, status, metrics, paper_label, paper, error, objects)


def run_sweep(
    plan: SweepPlan,
    conc: Concurrency,
    sweep_dir: str,
    sweep_run: SweepRun,
    resume: bool,
    remote: bool = False,
    callbacks: Sequence[ray.tune.Callback] = (),
    budget: SeedBudget | None = None,
) -> list[TrialOutcome]:
    """Run (or, with ``resume``, continue) the sweep on the connected Ray cluster; one outcome per trial.

    ``sweep_dir`` is Tune's experiment folder: an absolute path or an object-store URI
    (``s3://…``, ``file://…``). Resume re-runs only unfinished trials, each from its last
    checkpoint; errored trials stay failed. ``conc``: how trials fit the cluster
    (:func:`sweeps.plan.resources.plan_concurrency`), sized once by the caller. ``remote``: the cluster was
    joined by address and may autoscale. ``callbacks`` (e.g. the
    progress line, :class:`sweeps.execute.progress.SweepProgress`) join Tune's; a resumed sweep keeps those it
    started with. ``budget``: a sequential sweep's ``--budget`` (a resumed one keeps its searcher's).
    """
    # Snapshot the experiment state every second (and sync it to storage as often, below), so a
    # killed driver resumes trials from their checkpoints instead of from step 0 (with
    # Tune's default period the snapshot a kill found was still the initial one).
    os.environ["TUNE_GLOBAL_CHECKPOINT_S"] = "1"
    os.environ.setdefault("TUNE_WARN_EXCESSIVE_EXPERIMENT_CHECKPOINT_SYNC_THRESHOLD_S", "0")  # that is deliberate
    root = shared_root(sweep_dir, remote)
    if root is not None and plan.cells:
        done = precompute(plan, root, int(conc.cpus))
        print(f"shared by every cell: {done.rounds} view rounds of {done.view_sets} training set(s), "
              f"{done.eval_sets} evaluation set(s) with baselines, in {done.seconds:.1f} s", flush=True)
    r = plan.profile.resources
    cores = 0 if "://" in sweep_dir else lease_cores(conc.cpus, r.cpus_per_worker, r.workers_per_trial, remote)
    setup = TrialSetup(
        plan, sweep_dir, sweep_run.uri, sweep_run.experiment_id, sweep_run.run_id, code_version(), root, cores
    )
    trainable = ray.tune.with_resources(ray.tune.with_parameters(run_trial, setup=setup), conc.trial_resources)
    print(
        f"cluster{' (at most)' if remote else ''}: {conc.cpus:g} CPUs, {conc.gpus:g} GPUs → up to {conc.max_concurrent} "
        f"concurrent trials ({conc.cpus_per_trial:g} CPUs each)"
        + (f", taking turns on {cores} cores (one computing trial per core)" if cores else ""),
        flush=True,
    )
    if resume:
        tuner = ray.tune.Tuner.restore(sweep_dir, trainable=trainable, resume_unfinished=True,
                                       resume_errored=False, restart_errored=False)
    else:
        param_space, search_alg, num_samples = _search(plan, sweep_run, budget)
        tuner = ray.tune.Tuner(
            trainable,
            param_space=param_space,
            tune_config=ray.tune.TuneConfig(
                metric=plan.spec.metric.name,
                mode=plan.spec.metric.mode,
                search_alg=search_alg,
                scheduler=_scheduler(plan),
                num_samples=num_samples,
                max_concurrent_trials=conc.max_concurrent,
                reuse_actors=True,
                trial_name_creator=lambda t: plan.names(t.config)[1],
                trial_dirname_creator=lambda t: f"trial_{t.trial_id}",
            ),
            run_config=ray.tune.RunConfig(
                # Split as a string: a URI is no Path (Path("s3://b/x") collapses the "//").
                name=sweep_dir.rsplit("/", 1)[1],
                storage_path=sweep_dir.rsplit("/", 1)[0],
                failure_config=ray.tune.FailureConfig(max_failures=plan.spec.failure.max_retries),
                # Every checkpoint stays until CheckpointPruner (sweeps/execute/pruning.py) deletes it
                # safely: Tune's num_to_keep deletes before the state naming the newer one is uploaded.
                checkpoint_config=ray.tune.CheckpointConfig(num_to_keep=None),
                sync_config=ray.tune.SyncConfig(sync_period=1),
                callbacks=[_TrialCloser(plan, sweep_run), CheckpointPruner(), *callbacks],
                # Tune's own tables list every reported metric (dozens, per category); the trials'
                # step/eval lines and _TrialCloser's lines are the progress display instead.
                verbose=0,
            ),
        )
    grid = tuner.fit()
    prune_finished(grid)  # fit() has uploaded Tune's final state: no trial's older checkpoints are needed
    if root is not None:
        # A cache, gigabytes at the local profile: kept only while trials may still read it (a killed
        # driver leaves it for --resume; a resumed sweep that finds it gone renders it again).
        shutil.rmtree(root, ignore_errors=True)
    # A trial whose worker never started has no config; grid sweeps list it as pending below.
    outcomes = [_outcome(plan, r, sweep_run) for r in grid if r.config is not None]
    if not plan.spec.search.sampled:  # trials Tune had not created when the sweep was interrupted get their row
        next_round = None
        if plan.sequential is not None:
            from sweeps.compare.settle import final_round

            next_round = final_round(plan, outcomes, budget, sweep_run.client.get_run(sweep_run.run_id).data.tags).start
        for cell in map(plan.grid_cell, unstarted([c.label for c in plan.cells], outcomes, next_round)):
            outcomes.append(TrialOutcome(cell.label, cell.name, "pending", {}, cell.paper_label, cell.paper))
    labels = [c.label for c in plan.cells] if not plan.spec.search.sampled else None
    return sorted(outcomes, key=sweep_order(labels, plan.spec.metric.name, plan.spec.metric.mode))
