"""The sweep's trials on Tune: the Tuner (new, or restored by ``--resume``), its search and scheduler, one line
and one MLflow verdict per trial as it ends, and one outcome per trial for the results table.

Each trial is :func:`sweeps.execute.trial.run_trial`.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import ray
import ray.tune

from cdm.io.files import is_uri, read_text
from cdm.provenance import code_version
from sweeps.compare.outcomes import TrialOutcome, sweep_order, unstarted
from sweeps.execute.cores import lease_cores
from sweeps.execute.precompute import precompute, precomputes, shared_root
from sweeps.execute.pruning import CheckpointPruner, prune_finished
from sweeps.execute.resume_retries import refusing, retry_errored
from sweeps.execute.settle import UntilSettled
from sweeps.execute.trial import TrialSetup, remove_sweep_scratch, run_trial, trial_dir_name
from sweeps.plan.budget import SeedBudget
from sweeps.plan.resources import Concurrency
from sweeps.plan.search import search_kind
from sweeps.plan.trials import SweepPlan
from sweeps.store.files import storage_location
from sweeps.store.sweep_run import SweepRun

__all__ = ["checkpoint_location", "error_summary", "run_sweep"]


def error_summary(text: str) -> str:
    """The exception line of a (Ray-wrapped) traceback, e.g. ``TrainingDiverged: loss became nan …``."""
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    for line in reversed(lines):
        if "Error" in line.split(":")[0] or "Diverged" in line.split(":")[0]:
            return line
    return lines[-1] if lines else text


def checkpoint_location(sweep_dir: str, trial) -> str | None:
    """The trial's newest checkpoint in the sweep's storage, as the storage spells it: Tune's (Train's local
    mode) or, with Train workers, the Train run's (``TuneReportCallback`` passes its path on); None if none."""
    fs_path = trial.checkpoint.path if trial.checkpoint is not None else trial.last_result.get("checkpoint_path")
    return None if fs_path is None else storage_location(sweep_dir, fs_path)


class _TrialCloser(ray.tune.Callback):
    """Driver side: closes each child MLflow run with Tune's verdict and where its checkpoint is kept, and prints
    one line per trial."""

    def __init__(self, plan: SweepPlan, sweep_run: SweepRun, sweep_dir: str):
        self.plan, self.sweep_run, self.sweep_dir = plan, sweep_run, sweep_dir

    def _count(self, trials, ending=None) -> str:
        # Counted from Tune's trial list, so trials finished before a resume count too.
        done = {t.trial_id for t in trials if t.status in ("TERMINATED", "ERROR")} | (
            {ending.trial_id} if ending else set()
        )
        at_most = "≤" if self.plan.sequential else ""  # a sequential sweep's count is its worst case
        return f"{len(done)}/{at_most}{self.plan.num_trials} trials done"

    def on_trial_start(self, iteration, trials, trial, **info) -> None:
        print(f"▶ started [{self.plan.label(trial.config)}] ({self._count(trials)})", flush=True)

    def on_trial_complete(self, iteration, trials, trial, **info) -> None:
        label = self.plan.label(trial.config)
        step = trial.last_result.get("step", 0)
        early = not self.plan.completed(label, step, trial.last_result)
        self.sweep_run.close_trial(trial.trial_id, label, "FINISHED", stopped_early=early, last=trial.last_result,
                                   checkpoint=checkpoint_location(self.sweep_dir, trial))
        value = trial.last_result.get(self.plan.spec.metric.name)
        shown = "no evaluation" if value is None else f"{self.plan.spec.metric.name} {value:.4g}"
        print(f"{'■ stopped early' if early else '✓ finished'} [{label}] at step {step}: {shown} "
              f"({self._count(trials, trial)})", flush=True)

    def on_trial_error(self, iteration, trials, trial, **info) -> None:
        label = self.plan.label(trial.config)
        # Tune has just written the traceback to the trial's local error file (before syncing it).
        reason = error_summary(read_text(Path(trial.error_file), "error file")) if trial.error_file else "unknown error"
        self.sweep_run.close_trial(trial.trial_id, label, "FAILED", error=reason,
                                   checkpoint=checkpoint_location(self.sweep_dir, trial))
        print(f"✗ failed [{label}]: {reason} ({self._count(trials, trial)})", flush=True)


def _search(plan: SweepPlan, sweep_run: SweepRun, budget: SeedBudget | None) -> tuple[dict[str, Any], Any, int]:
    """Tune param space, search algorithm and sample count: grid cells by label, seeds until settled
    (:meth:`sweeps.execute.settle.UntilSettled.searcher`, at most every cell at ``max`` seeds), or the searcher
    of a kind that samples ``search.space`` (:data:`sweeps.plan.search.SEARCHES`)."""
    s = plan.spec.search
    if plan.sequential is not None:
        return {}, UntilSettled(plan, budget).searcher(sweep_run), plan.num_trials
    if not s.sampled:
        return {"cell": ray.tune.grid_search([c.label for c in plan.cells])}, None, 1
    study = (
        f"{plan.spec.name}-{plan.profile.name}-{uuid.uuid4().hex[:8]}"  # e.g. Optuna's study names are unique per sweep
    )
    searcher = search_kind(s.kind).tune_searcher(s, plan.spec.metric.name, plan.spec.metric.mode, study)
    return {}, searcher, plan.num_trials


def _scheduler(plan: SweepPlan):
    sch = plan.spec.scheduler
    time_attr, total, every = plan.profile.time_axis
    if not sch.stops(total, every):
        return None  # it could stop nothing (the dry run says so); Ray refuses a grace period past max_t
    from ray.tune.schedulers import ASHAScheduler

    # Time axis = the trainer's step, or with a budget in compute its seconds of compute, so trials of
    # different step cost meet at the same rungs (both reported with every evaluation).
    return ASHAScheduler(
        time_attr=time_attr,
        max_t=total,
        grace_period=sch.grace_evals * every,
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
        status = "pending" if step is None else ("ok" if plan.completed(label, step, result.metrics) else "stopped")
    objects = tuple(sweep_run.trial_objects(trial_id)) if trial_id and status != "failed" else ()
    paper_label, paper = (cell.paper_label, cell.paper) if cell else (None, {})
    return TrialOutcome(label, name, status, metrics, paper_label, paper, error, objects,
                        plan.f1_threshold(label, result.config or {}))


def _tuner(plan: SweepPlan, trainable, conc: Concurrency, sweep_dir: str, sweep_run: SweepRun, resume: bool,
           callbacks: Sequence[ray.tune.Callback], budget: SeedBudget | None, resume_errored: bool = False
           ) -> ray.tune.Tuner:
    """Tune's Tuner over ``trainable``: restored from ``sweep_dir`` on ``resume`` (unfinished trials, and errored ones
    from their last checkpoint with ``resume_errored``), else new."""
    if resume:
        return ray.tune.Tuner.restore(sweep_dir, trainable=trainable, resume_unfinished=True,
                                      resume_errored=resume_errored, restart_errored=False)
    param_space, search_alg, num_samples = _search(plan, sweep_run, budget)
    return ray.tune.Tuner(
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
            trial_name_creator=lambda t: plan.label(t.config),
            trial_dirname_creator=lambda t: trial_dir_name(t.trial_id),
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
            callbacks=[_TrialCloser(plan, sweep_run, sweep_dir), CheckpointPruner(), *callbacks],
            # Tune's own tables list every reported metric (dozens, per category); the trials'
            # step/eval lines and _TrialCloser's lines are the progress display instead.
            verbose=0,
        ),
    )


def _outcomes(plan: SweepPlan, grid, sweep_run: SweepRun, budget: SeedBudget | None) -> list[TrialOutcome]:
    """One outcome per trial of Tune's ``grid``, trials it never created listed as pending, in the table's order."""
    # A trial whose worker never started has no config; grid sweeps list it as pending below.
    outcomes = [_outcome(plan, r, sweep_run) for r in grid if r.config is not None]
    if not plan.spec.search.sampled:  # trials Tune had not created when the sweep was interrupted get their row
        next_round = None
        if plan.sequential is not None:
            tags = sweep_run.client.get_run(sweep_run.run_id).data.tags
            next_round = UntilSettled(plan, budget).final(outcomes, tags).start
        for cell in map(plan.grid_cell, unstarted([c.label for c in plan.cells], outcomes, next_round)):
            outcomes.append(TrialOutcome(cell.label, cell.name, "pending", {}, cell.paper_label, cell.paper,
                                         f1_threshold=cell.config.eval.f1_threshold))
    labels = [c.label for c in plan.cells] if not plan.spec.search.sampled else None
    return sorted(outcomes, key=sweep_order(labels, plan.spec.metric.name, plan.spec.metric.mode))


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

    ``sweep_dir`` is Tune's experiment folder: an absolute path or an object-store URI (``s3://…``). Resume
    re-runs unfinished trials from their last checkpoints, and errored ones as
    :mod:`sweeps.execute.resume_retries` decides. ``conc``: how trials fit the cluster, sized once by the
    caller; ``remote``: the cluster was joined by address. ``callbacks`` join Tune's (a resumed sweep keeps
    those it started with); ``budget``: a sequential sweep's ``--budget`` (a resumed one keeps its searcher's).
    """
    # Snapshot the experiment state every second (and sync it to storage as often, below), so a
    # killed driver resumes trials from their checkpoints instead of from step 0 (with
    # Tune's default period the snapshot a kill found was still the initial one).
    os.environ["TUNE_GLOBAL_CHECKPOINT_S"] = "1"
    os.environ.setdefault("TUNE_WARN_EXCESSIVE_EXPERIMENT_CHECKPOINT_SYNC_THRESHOLD_S", "0")  # that is deliberate
    root = shared_root(sweep_dir, remote)
    if precomputes(plan, sweep_dir, remote):
        done = precompute(plan, root, int(conc.cpus))
        print(f"shared by every cell: {done.rounds} view rounds of {done.view_sets} training set(s), "
              f"{done.eval_sets} evaluation set(s) with baselines, in {done.seconds:.1f} s", flush=True)
    r = plan.profile.resources
    cores = 0 if is_uri(sweep_dir) else lease_cores(conc.cpus, r.cpus_per_worker, r.workers_per_trial, remote)
    setup = TrialSetup(plan, {c.label: c for c in plan.cells}, sweep_dir, sweep_run.uri, sweep_run.experiment_id,
                       sweep_run.run_id, code_version(), root, cores)
    resume_errored, given_up = (retry_errored(sweep_dir, plan.spec.failure.max_retries, plan.label)
                                if resume else (False, {}))
    trainable = ray.tune.with_resources(ray.tune.with_parameters(refusing(run_trial, given_up), setup=setup),
                                        conc.trial_resources)
    print(
        f"cluster{' (at most)' if remote else ''}: {conc.cpus:g} CPUs, {conc.gpus:g} GPUs → up to "
        f"{conc.max_concurrent} concurrent trials ({conc.cpus_per_trial:g} CPUs each)"
        + (f", taking turns on {cores} cores (one computing trial per core)" if cores else ""),
        flush=True,
    )
    grid = _tuner(plan, trainable, conc, sweep_dir, sweep_run, resume, callbacks, budget, resume_errored).fit()
    prune_finished(grid)  # fit() has uploaded Tune's final state: no trial's older checkpoints are needed
    remove_sweep_scratch(sweep_dir, whole=r.workers_per_trial == 0)
    if root is not None:
        # A cache, gigabytes at the local profile: kept only while trials may still read it (a killed
        # driver leaves it for --resume; a resumed sweep that finds it gone renders it again).
        shutil.rmtree(root, ignore_errors=True)
    return _outcomes(plan, grid, sweep_run, budget)
