"""One sweep on Ray, start to results table: the sweep folder claimed, the MLflow parent run, ``sweep.json``
and ``plan.json``, the estimate, the Tuner, the table, and the lines printed at the end.

:func:`claim_sweep` checks where the sweep is kept and takes its folder, before Ray starts and before any
MLflow run exists; :func:`run_claimed` runs it. A sweep that cannot go on raises :class:`DriverError`, which
``sweeps/run.py`` prints as ``error: …`` with exit code 2.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import ray

from cdm.interrupt import take_sigterm_as_ctrl_c
from sweeps.compare.outcomes import TrialOutcome
from sweeps.compare.rules import PROTOCOL_NOTE, settings_notes
from sweeps.compare.table import ResultsTable, build_table
from sweeps.execute.claim import ClaimError, SweepClaim, claim
from sweeps.execute.cluster import cluster_capacity, cluster_machines, connect
from sweeps.execute.precompute import check_space, precomputes, shared_root
from sweeps.execute.progress import SweepProgress, is_tty, plain_log_handlers, quiet_environment, quiet_loggers
from sweeps.execute.settle import UntilSettled
from sweeps.execute.stopping import discard_start, kill_running_children, no_space_left, one_line, resume_command
from sweeps.execute.tuner import run_sweep
from sweeps.plan.address import AddressError
from sweeps.plan.preflight import UnreadableInput, estimate_line
from sweeps.plan.protocol import CARD_TAG, plan_card
from sweeps.plan.request import STATE_FILE, SweepRequest
from sweeps.plan.resources import Concurrency, plan_concurrency
from sweeps.plan.schema_base import SpecError
from sweeps.plan.spec import Spec
from sweeps.plan.trials import SweepPlan
from sweeps.store.files import (
    StoreError,
    check_no_links,
    check_resume_trust,
    check_storage,
    exists,
    is_uri,
    publish_files,
)
from sweeps.store.read import trial_runs
from sweeps.store.sweep_run import SweepRun, baselines_by_eval_set, with_logged_baselines
from sweeps.store.tracking import check_parent_run, check_tracking_uri, resolve_tracking_uri, ui_command, ui_link

__all__ = ["DriverError", "Publisher", "claim_sweep", "run_claimed", "table_settings"]


class DriverError(Exception):
    """A sweep that cannot start or go on; the message names the cause and the fix."""


@dataclass(frozen=True)
class Publisher:
    """The results stage's steps once the table is written, handed in by the runner (a stage imports only
    earlier ones): ``describe(spec, profile, profile description, table, card)`` is the parent run's
    description, ``publish(tracking uri, parent run id, plots folder)`` returns the runs view's path."""

    describe: Callable[[Spec, str, str, ResultsTable, list[str]], str]
    publish: Callable[[str, str, Path], str]


def table_settings(plan: SweepPlan, sweep_run: SweepRun | None = None) -> list[str]:
    """What produced the numbers, for the table's notes: budget, the cells' training target and λ, the machine
    the trials' child runs under ``sweep_run`` name (none before there are trials), the card."""
    trials = ((c.config.diffusion.prediction, c.config.priors.lambda_3d) for c in plan.cells)
    machines = None if sweep_run is None else [
        r.data.tags for r in trial_runs(sweep_run.client, sweep_run.experiment_id, sweep_run.run_id)]
    return settings_notes(plan.spec, plan.profile.name, plan.profile.steps, plan.fixed, plan.sets,
                          plan_card(plan).lines(), trials, machines, plan.profile.compute_s)


def _ui_hint(uri: str, path: str) -> str:
    """Where to see ``path`` (``#/experiments/…``) of the MLflow UI: its address, or how to start it."""
    if uri.startswith(("http://", "https://")):
        return f"open {uri.rstrip('/')}/{ui_link(path)}"
    return f"{ui_command(uri)}\n  (then open http://127.0.0.1:5000/{ui_link(path)})"


def _write_new(path: Path, text: str) -> None:
    """Create ``path`` with ``text``; a file or link already there (planted in the folder) is refused by the OS."""
    with os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644), "w") as out:
        out.write(text)


def claim_sweep(request: SweepRequest, args: argparse.Namespace) -> tuple[str, SweepClaim]:
    """(MLflow tracking URI, the claim on the sweep folder), the store and folder checked first."""
    sweep_dir, state = request.sweep_dir, request.state
    try:
        check_no_links(sweep_dir)
        check_storage(sweep_dir)
        uri = resolve_tracking_uri(request.tracking_uri)
        check_tracking_uri(uri)
        if state is not None:
            check_parent_run(uri, state["parent_run_id"])
        check_space(request.plan, sweep_dir, request.remote)
        held = claim(sweep_dir)
    except (StoreError, ClaimError) as exc:
        raise DriverError(str(exc)) from None
    if not args.resume and exists(sweep_dir):
        held.release()
        raise DriverError(
            f"{sweep_dir} already holds a sweep: pass --resume to continue it, or remove the folder to start over"
        )
    if args.resume:
        try:  # under the claim: no other copy of this runner rewrites Tune's state meanwhile
            if not args.trust_storage:
                check_resume_trust(sweep_dir)
            if request.plan.sequential is not None:
                UntilSettled(request.plan).check_resume(sweep_dir)  # Tune would start a fresh searcher on a damaged one
        except StoreError as exc:
            held.release()
            raise DriverError(str(exc)) from None
    return uri, held


def _concurrency(request: SweepRequest, uri: str) -> Concurrency:
    """How the trials fit the cluster, sized by the most it could offer; a SQLite store refused on several machines."""
    machines = cluster_machines(request.remote)
    if uri.startswith("sqlite:") and machines > 1:
        raise DriverError(
            f"MLflow store {uri}: this cluster spans (or may grow to) {machines} machines and trials on the others "
            "cannot write a SQLite file here; start an MLflow server every node reaches (`mlflow server "
            "--host <private ip> --port 5000 …`, cluster/README.md) and pass --tracking-uri http://<private ip>:5000"
        )
    capacity = cluster_capacity(request.remote)
    plan = request.plan
    try:
        return plan_concurrency(plan.profile.resources, capacity["CPU"], capacity["GPU"], plan.num_trials,
                                request.remote)
    except SpecError as exc:
        raise DriverError(str(exc)) from None


def _open_parent_run(request: SweepRequest, args: argparse.Namespace, uri: str) -> SweepRun:
    """The sweep's MLflow parent run: reopened on ``--resume``, else started with its tags and params."""
    if args.resume:
        return SweepRun.reopen(uri, request.state["parent_run_id"])
    plan = request.plan
    return SweepRun.start(
        uri, plan.spec.name, f"{plan.spec.name} · {plan.profile.name} · {time.strftime('%Y-%m-%d %H:%M')}",
        tags={"spec": plan.spec.name, "profile": plan.profile.name, "sweep_dir": request.sweep_dir,
              CARD_TAG: "\n".join(plan_card(plan).lines())},
        params={"profile": plan.profile.name, "search": plan.spec.search.kind, "trials": plan.num_trials,
                "metric": plan.spec.metric.name, "steps": plan.profile.steps, "sets": json.dumps(request.sets),
                **({"budget": args.budget} if args.budget else {}),
                **({"compute_s": plan.profile.compute_s} if plan.profile.compute_s is not None else {})},
    )


def _write_start(request: SweepRequest, args: argparse.Namespace, sweep_run: SweepRun, staging: Path) -> None:
    """``sweep.json`` (what ``--resume`` reads) and ``plan.json``, published at once, the spec and plan logged."""
    plan, sets = request.plan, request.sets
    staging.mkdir(parents=True, exist_ok=True)
    state = {"spec": plan.spec.model_dump(mode="json"), "sets": sets, "profile": plan.profile.name,
             "budget": args.budget, "tracking_uri": sweep_run.uri, "parent_run_id": sweep_run.run_id}
    _write_new(staging / STATE_FILE, json.dumps(state, indent=2))
    plan_file = staging / "plan.json"
    _write_new(plan_file, json.dumps(
        {"fixed": plan.fixed, "sets": sets, "cells": [
            {"label": c.label, "values": c.values, "seed": c.seed, "paper": c.paper} for c in plan.cells]},
        indent=2, default=str))
    if is_uri(request.sweep_dir):
        publish_files(staging, request.sweep_dir)
    sweep_run.log_artifacts([args.spec.resolve(), plan_file])


def _estimate(request: SweepRequest, conc: Concurrency, sweep_run: SweepRun):
    """The cost estimate printed before the trials (None when none applies); an unreadable input ends the start."""
    plan, remote = request.plan, request.remote
    cluster = ray.cluster_resources()
    now = conc
    if remote:  # sized by the most the cluster could offer; the estimate wants the nodes up now
        try:
            now = plan_concurrency(plan.profile.resources, cluster.get("CPU", 0.0), cluster.get("GPU", 0.0),
                                   plan.num_trials)
        except SpecError:  # no node up fits a trial before the autoscaler adds one
            print("estimate: none — no node up yet fits one trial; trials wait for the autoscaler to add one",
                  flush=True)
            return None
    try:
        return estimate_line(plan, cluster.get("CPU", 1.0), now.max_concurrent,
                             precomputes(plan, request.sweep_dir, remote))
    except UnreadableInput as exc:
        kill_running_children(sweep_run)
        sweep_run.end("FAILED")
        discard_start(request.sweep_dir)
        raise DriverError(str(exc)) from None


def _trials(request: SweepRequest, args: argparse.Namespace, conc: Concurrency, sweep_run: SweepRun,
            predicted, tty: bool) -> list[TrialOutcome]:
    """The trials on Tune, with the sweep's progress line (a resumed sweep keeps the callbacks it started with)."""
    plan = request.plan
    progress = None if args.resume else SweepProgress(
        sweep_run.run_id, plan.num_trials, plan.profile.steps, lambda t: plan.label(t.config),
        predicted.wall_s if predicted else None, tty, rounds=plan.rounds,
        round_of=(lambda t: plan.round_of(plan.grid_cell(t.config["cell"]))) if plan.sequential else None)
    try:
        return run_sweep(plan, conc, request.sweep_dir, sweep_run, args.resume, request.remote,
                         callbacks=[progress] if progress else [], budget=request.budget)
    finally:
        if progress is not None:
            progress.close()


def _table(request: SweepRequest, outcomes: list[TrialOutcome], sweep_run: SweepRun, staging: Path,
           publisher: Publisher) -> tuple[ResultsTable, str]:
    """The results table written and logged, the parent run described and its views published; (table, view)."""
    plan = request.plan
    settled = None
    if plan.sequential is not None:
        tags = sweep_run.client.get_run(sweep_run.run_id).data.tags
        rule = UntilSettled(plan, request.budget)
        settled = rule.final(outcomes, tags).records
        sweep_run.log_artifacts([rule.write_json(staging / "settle.json", settled)])
    baselines = baselines_by_eval_set(outcomes)
    # The numbers the parent run holds, so that `report` rebuilds this results.csv byte for byte.
    table = build_table(with_logged_baselines(outcomes, baselines), plan.spec.metric.name, plan.spec.metric.mode,
                        f"{plan.spec.name} — profile {plan.profile.name}",
                        f"{plan.spec.paper.table}: {plan.spec.paper.note}" if plan.spec.paper else "",
                        compare_to=plan.spec.compare_to, settings=table_settings(plan, sweep_run), settled=settled)
    sweep_run.log_artifacts(list(table.write(staging)))
    sweep_run.log_results(
        baselines,
        publisher.describe(plan.spec, plan.profile.name, plan.profile.description, table, plan_card(plan).lines()),
    )
    view = publisher.publish(sweep_run.uri, sweep_run.run_id, staging / "plots")
    if is_uri(request.sweep_dir):
        publish_files(staging, request.sweep_dir)
    return table, view


@dataclass(frozen=True)
class _Finished:
    table: ResultsTable
    outcomes: list[TrialOutcome]
    view: str
    predicted: object
    took: float


def run_claimed(request: SweepRequest, args: argparse.Namespace, uri: str, held: SweepClaim,
                publisher: Publisher) -> int:
    """Run the claimed sweep on Ray and print its table; the exit code (1: no trial finished)."""
    tty = is_tty(sys.stdout)
    quiet_environment(tty)
    # The sweep folder's own files are written locally, then copied: in place for a path; for a URI
    # in a staging folder, copied at once (sweep.json, so a crashed sweep can be resumed) and at the end.
    sweep_dir = request.sweep_dir
    try:
        started = connect(args.address)
    except AddressError as exc:
        raise DriverError(str(exc)) from None
    staging = Path(tempfile.mkdtemp(prefix="cdm-sweep-")) if is_uri(sweep_dir) else Path(sweep_dir)
    quiet_loggers()
    if not tty:
        plain_log_handlers()
    # `kill`, `timeout` and batch schedulers stop a job with SIGTERM, which ends Python at once and leaves
    # its MLflow runs RUNNING: taken as Ctrl-C, Tune stops the trials and the runs close as KILLED below.
    previous_sigterm = take_sigterm_as_ctrl_c()
    sweep_run = None
    try:
        conc = _concurrency(request, uri)
        sweep_run = _open_parent_run(request, args, uri)
        if not args.resume:
            _write_start(request, args, sweep_run, staging)
        held.record(uri, sweep_run.run_id)
        print(f"profile in force: {request.plan.profile.name}; MLflow: {uri} (parent run {sweep_run.run_id})",
              flush=True)
        print(f"watch it live: {_ui_hint(uri, f'#/experiments/{sweep_run.experiment_id}/runs/{sweep_run.run_id}')}",
              flush=True)
        # A resumed sweep has only its unfinished trials left: the estimate would not apply.
        predicted = None if args.resume else _estimate(request, conc, sweep_run)
        started_at = time.perf_counter()
        outcomes = _trials(request, args, conc, sweep_run, predicted, tty)
        took = time.perf_counter() - started_at
        table, view = _table(request, outcomes, sweep_run, staging, publisher)
        kill_running_children(sweep_run)
        sweep_run.end("KILLED" if any(o.status == "pending" for o in outcomes) else "FINISHED")
    except DriverError:
        raise
    except BaseException as exc:
        _stopped(request, args, sweep_run, exc)
        raise
    finally:
        signal.signal(signal.SIGTERM, previous_sigterm)
        if started:
            ray.shutdown()
        if is_uri(sweep_dir):
            shutil.rmtree(staging)
    return _print_results(request, args, uri, _Finished(table, outcomes, view, predicted, took))


def _stopped(request: SweepRequest, args: argparse.Namespace, sweep_run: SweepRun | None, exc: BaseException) -> None:
    """Whatever stopped the sweep, its parent run must not stay RUNNING in the UI; a full disk is said as
    such (:class:`DriverError`), the shared cache that filled it removed."""
    if sweep_run is not None:
        kill_running_children(sweep_run)
        sweep_run.end("KILLED" if isinstance(exc, KeyboardInterrupt) else "FAILED")
    if no_space_left(exc):
        shared = shared_root(request.sweep_dir, request.remote)
        if shared is not None:
            shutil.rmtree(shared, ignore_errors=True)
        raise DriverError(
            f"no space left on the device of {request.sweep_dir}"
            + (f" (removed the shared cache {shared})" if shared else "")
            + f": {one_line(exc)[:200]}; free space, then resume with: "
            + resume_command(args.spec, request.plan.profile.name, args.storage)
        ) from None


def _print_results(request: SweepRequest, args: argparse.Namespace, uri: str, done: _Finished) -> int:
    """The table (its protocol card left to results.md, printed before the trials), the time against the
    estimate, where the results are, and how to resume unfinished trials."""
    sweep_dir, table = request.sweep_dir, done.table
    shown = replace(
        table,
        notes=[n for n in table.notes if not n.startswith(PROTOCOL_NOTE)]
        + ["protocol card: printed above, and in results.md"],
    )
    print("\n" + shown.text() + "\n")
    if done.predicted is not None:
        wall_s = done.predicted.wall_s
        print(f"time: estimated ~{wall_s / 60:.1f} min, took {done.took / 60:.1f} min "
              f"(actual / estimate = {done.took / wall_s:.2f})")
    print(f"results: {sweep_dir}/results.md and {sweep_dir}/results.csv")
    print(f"MLflow: {_ui_hint(uri, done.view)}")
    if any(o.status == "pending" for o in done.outcomes):
        print(f"some trials did not finish; continue with: "
              f"{resume_command(args.spec, request.plan.profile.name, args.storage)}")
    return 0 if any(o.finished for o in done.outcomes) else 1
