"""Run a sweep: train every trial of a spec on Ray, track it in MLflow and print the results table;
or re-run one finished trial (``--rerun RUN_ID``), or rebuild a finished sweep's report (``--report``).

The spec is expanded and every cell's config validated before Ray starts; a bad spec exits with
code 2 and one message naming the field, having written nothing. Then the trials run on Ray (a local
cluster bound to 127.0.0.1, or ``--address``/``RAY_ADDRESS``), tracked in MLflow, and the results
table is printed and written to ``<storage>/<spec name>/<profile>/results.{md,csv}``.
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
from dataclasses import replace
from pathlib import Path

if __package__ in (None, ""):  # `python sweeps/run.py` puts sweeps/ first on sys.path, not the repo root
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pydantic import ValidationError

from cdm.config import ConfigError, load_config, parse_override
from cdm.memory import check_memory
from sweeps.compare.rules import PROTOCOL_NOTE, settings_notes
from sweeps.compare.settle import check_budget, describe_rule
from sweeps.execute.claim import ClaimError, SweepClaim, claim
from sweeps.execute.precompute import check_space, shared_root
from sweeps.execute.stopping import discard_start, kill_running_children, no_space_left, one_line, resume_command
from sweeps.plan.budget import SeedBudget, budget_option
from sweeps.plan.describe import describe, wrapped
from sweeps.plan.limits import (
    LISTED_TRIALS,
    MAX_TRIALS,
    LimitError,
    check_progress,
    check_set_text,
    check_trials,
    count_trials,
)
from sweeps.plan.preflight import check_inputs, dry_run, estimate_line
from sweeps.plan.protocol import CARD_TAG, plan_card
from sweeps.plan.resources import plan_concurrency
from sweeps.plan.spec import Spec, SpecError, load_spec
from sweeps.plan.trials import SweepPlan, expand
from sweeps.storage import (
    TRUST_FLAG,
    StoreError,
    check_no_links,
    check_parent_run,
    check_resume_trust,
    check_storage,
    check_tracking_uri,
    exists,
    is_uri,
    parse_state,
    publish_files,
    read_text,
    record_digest,
    sweep_location,
)

__all__ = ["main"]

STATE_FILE = "sweep.json"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sweeps/run.py", description=__doc__.split("\n\n")[0])
    p.add_argument("spec", type=Path, nargs="?", help="sweep spec, e.g. sweeps/point_size.yaml")
    p.add_argument("--profile", default=None, help="profile in sweeps/profiles.yaml or the spec (default: local)")
    p.add_argument("--smoke", action="store_true", help="same as --profile smoke")
    p.add_argument(
        "--resume", action="store_true", help="continue an interrupted sweep; re-runs only unfinished trials"
    )
    p.add_argument(
        TRUST_FLAG,
        action="store_true",
        help="with --resume: unpickle Tune's state even where others could have written it (docs/security.md)",
    )
    p.add_argument(
        "--until-settled",
        action="store_true",
        help="run seeds until each cell's comparison settles: a list of seeds becomes {min: 2, max: 5} (docs/sweeps.md, Seeds until settled)",
    )
    p.add_argument("--budget", default=None, metavar="2h|45m|30s|N",
                   help="with seeds until settled: no seed starts past this wall time, or past N trials")
    p.add_argument(
        "--dry-run",
        action="store_true",
        help="print the trials, the resource plan and the protocol card; start nothing",
    )
    p.add_argument(
        "--no-estimate", action="store_true", help="with --dry-run: skip the cost estimate's calibration steps"
    )
    p.add_argument("--address", default=None, help="Ray cluster address (default: RAY_ADDRESS, else a local cluster)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override for every trial")
    p.add_argument("--storage", default="results",
                   help="parent folder of sweep folders: a path (shared by every node on a cluster) or a URI "
                        "(s3://, gs://, file://) (default: ./results)")
    p.add_argument("--tracking-uri", default=None, help="MLflow URI (default: MLFLOW_TRACKING_URI, else sqlite:///<cwd>/mlflow.db)")
    p.add_argument(
        "--rerun", metavar="RUN_ID", default=None, help="re-run the trial of this MLflow child run from its record"
    )
    p.add_argument(
        "--force", action="store_true", help="with --rerun: run even if the code or config differs from the record"
    )
    p.add_argument("--max-cells", type=int, default=MAX_TRIALS, metavar="N",
                   help=f"refuse a sweep of more than N trials (default {MAX_TRIALS}; docs/security.md)")
    p.add_argument(
        "--report",
        metavar="EXPERIMENT",
        default=None,
        help="rebuild the results table and plots of this finished sweep from MLflow",
    )
    return p


def _rule(plan: SweepPlan, budget: SeedBudget | None) -> list[str]:
    """A sequential sweep's dry-run lines (:func:`sweeps.compare.settle.describe_rule`); none otherwise."""
    return describe_rule(plan, budget) if plan.sequential is not None else []


def _settings(plan: SweepPlan) -> list[str]:
    """What produced the numbers, for the table's notes: budget, the cells' training target and λ, the card."""
    trials = ((c.config.diffusion.prediction, c.config.priors.lambda_3d) for c in plan.cells)
    return settings_notes(plan.spec, plan.profile.name, plan.profile.steps, plan.fixed, plan.sets,
                          plan_card(plan).lines(), trials)


def _ui_hint(uri: str, path: str) -> str:
    """Where to see ``path`` (``#/experiments/…``) of the MLflow UI: its address, or how to start it."""
    from sweeps.execute.tracking import ui_command, ui_link

    if uri.startswith(("http://", "https://")):
        return f"open {uri.rstrip('/')}/{ui_link(path)}"
    return f"{ui_command(uri)}\n  (then open http://127.0.0.1:5000/{ui_link(path)})"


def _fail(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if sum(a is not None for a in (args.spec, args.rerun, args.report)) != 1:
        return _fail("give one of a sweep spec (e.g. sweeps/point_size.yaml), --rerun RUN_ID or --report EXPERIMENT")
    if args.report is not None or args.rerun is not None:
        from sweeps.execute.tracking import resolve_tracking_uri

        try:
            check_tracking_uri(resolve_tracking_uri(args.tracking_uri))
        except StoreError as exc:
            return _fail(str(exc))
    if args.report is not None:
        from sweeps.results import publish

        return publish.main([args.report, *(["--tracking-uri", args.tracking_uri] if args.tracking_uri else [])])
    if args.rerun is not None:
        from sweeps.execute.tracking import resolve_tracking_uri
        from sweeps.results.rerun import RerunError, rerun

        if is_uri(args.storage):
            return _fail(
                f"--rerun trains in this process and writes its files here: give --storage a local folder, not {args.storage}"
            )
        try:
            return rerun(
                args.rerun,
                resolve_tracking_uri(args.tracking_uri),
                (Path(args.storage) / "reruns").resolve(),
                args.force,
            )
        except RerunError as exc:
            return _fail(str(exc))
    if args.smoke and args.profile not in (None, "smoke"):
        return _fail(f"--smoke means --profile smoke; got --profile {args.profile} too")
    profile = "smoke" if args.smoke else (args.profile or "local")
    remote = args.address is not None or "RAY_ADDRESS" in os.environ
    if remote and not args.dry_run and not is_uri(args.storage) and not Path(args.storage).is_absolute():
        # Under `ray job submit` the driver's working directory is the job's temporary copy of the
        # repository: checkpoints there vanish with the job and other nodes never see them.
        return _fail(f"--storage {args.storage}: on a cluster give an absolute path that every node shares "
                     "(e.g. /mnt/shared/results) or an object-store URI (s3://bucket/results)")
    state = None
    try:
        spec = load_spec(args.spec)
        sweep_dir = sweep_location(args.storage, spec.name, profile)
        state_file = f"{sweep_dir}/{STATE_FILE}"
        for text in args.set:
            check_set_text(text)
        sets = dict(parse_override(text) for text in args.set)
        if args.resume:
            if not exists(state_file):
                return _fail(f"--resume: {sweep_dir} holds no sweep to resume (no {STATE_FILE})")
            if sets:
                return _fail("--resume continues a sweep with the spec and --set values it started with; drop --set")
            if args.until_settled or args.budget is not None:
                return _fail(
                    "--resume continues a sweep with the seeds and budget it started with; drop --until-settled and --budget"
                )
            # The spec as it started, even if the file was edited since: trials must stay the same.
            state = parse_state(read_text(state_file), state_file)
            try:
                spec, sets = Spec.model_validate(state["spec"]), state["sets"]
            except ValidationError as exc:
                return _fail(
                    f"--resume: {state_file} is damaged ({' '.join(str(exc).split())}); remove the folder to start over"
                )
        if args.until_settled:
            spec = spec.until_settled()
        budget = budget_option((state or {}).get("budget") if args.resume else args.budget)
        check_trials(spec, args.max_cells)
        if args.dry_run and (count := count_trials(spec)[0]) > LISTED_TRIALS and not spec.search.sampled:
            print(f"checking up to {count} trials one at a time (listing the first {LISTED_TRIALS}) …", flush=True)
            plan = expand(spec, profile, sets, keep=LISTED_TRIALS, each=check_progress(count))
        else:
            plan = expand(spec, profile, sets)
        check_budget(plan, budget)
        if not remote:  # a cluster's nodes have their own memory; this machine's says nothing of them
            check_memory([c.config for c in plan.cells] or [load_config(None, {**plan.fixed, **plan.sets})],
                         _local_concurrency(plan))
    except (SpecError, ConfigError, LimitError, StoreError) as exc:
        return _fail(str(exc))
    print(wrapped(f"spec {spec.name} ({args.spec}): {spec.description}"), flush=True)
    missing = None
    try:
        check_inputs(plan, remote)
    except ValueError as exc:
        if not args.dry_run:
            return _fail(str(exc))
        missing = str(exc)  # a dry run still plans: the card, the plan and the estimate, then this
    if not args.dry_run:
        from sweeps.execute.tracking import resolve_tracking_uri

        try:  # before Ray starts and before any MLflow run exists
            check_no_links(sweep_dir)
            check_storage(sweep_dir)
            uri = resolve_tracking_uri(args.tracking_uri or (state or {}).get("tracking_uri"))
            check_tracking_uri(uri)
            if state is not None:
                check_parent_run(uri, state["parent_run_id"])
            check_space(plan, sweep_dir, remote)
            held = claim(sweep_dir)
        except (StoreError, ClaimError) as exc:
            return _fail(str(exc))
        if not args.resume and exists(sweep_dir):
            held.release()
            return _fail(
                f"{sweep_dir} already holds a sweep: pass --resume to continue it, or remove the folder to start over"
            )
        if args.resume:
            try:  # under the claim: no other copy of this runner rewrites Tune's state meanwhile
                if not args.trust_storage:
                    check_resume_trust(sweep_dir)
                if plan.sequential is not None:
                    from sweeps.execute.seed_search import check_searcher_state

                    check_searcher_state(sweep_dir, plan)  # Tune would start a fresh searcher on a damaged one
            except StoreError as exc:
                held.release()
                return _fail(str(exc))
    if args.dry_run:
        shared = shared_root(sweep_dir, remote) is not None and bool(plan.cells)
        return dry_run(plan, remote, _rule(plan, budget), not args.no_estimate, shared, missing)
    print(describe(plan, None, None, _rule(plan, budget)), flush=True)
    try:
        return _run(plan, args, sweep_dir, state_file, state or {}, sets, remote, held)
    finally:
        if is_uri(sweep_dir) and exists(sweep_dir):
            record_digest(sweep_dir)  # what this driver leaves is what the next --resume may unpickle
        held.release()


def _write_new(path: Path, text: str) -> None:
    """Create ``path`` with ``text``; a file or link already there (planted in the folder) is refused by the OS."""
    with os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644), "w") as out:
        out.write(text)


def _local_concurrency(plan: SweepPlan) -> int:
    """Trials this machine runs at once (GPUs not counted: the memory check is about host RAM)."""
    try:
        return plan_concurrency(plan.profile.resources, os.cpu_count() or 1, 1e9, plan.num_trials).max_concurrent
    except SpecError:
        return 1


def _run(
    plan: SweepPlan,
    args: argparse.Namespace,
    sweep_dir: str,
    state_file: str,
    stored: dict,
    sets: dict,
    remote: bool,
    held: SweepClaim,
) -> int:
    # The results table downloads each trial's per-object scores: no progress bar per small file.
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    from sweeps.execute.progress import SweepProgress, is_tty, plain_log_handlers, quiet_environment, quiet_loggers

    tty = is_tty(sys.stdout)
    quiet_environment(tty)
    import ray

    from sweeps.compare.table import build_table
    from sweeps.execute.cluster import cluster_capacity, cluster_machines, connect
    from sweeps.execute.tracking import SweepRun, baselines_by_eval_set, resolve_tracking_uri
    from sweeps.execute.trial import run_sweep
    from sweeps.results.publish import describe_sweep, publish

    # The sweep folder's own files are written locally, then copied: in place for a path; for a URI
    # in a staging folder, copied at once (sweep.json, so a crashed sweep can be resumed) and at the end.
    staging = Path(tempfile.mkdtemp(prefix="cdm-sweep-")) if is_uri(sweep_dir) else Path(sweep_dir)
    # A resumed sweep keeps logging into the store it started with (``stored``: its sweep.json, read and
    # checked once by main), wherever it is resumed from.
    uri = resolve_tracking_uri(args.tracking_uri or stored.get("tracking_uri"))
    started = connect(args.address)
    quiet_loggers()
    if not tty:
        plain_log_handlers()
    sweep_run = None
    # `kill`, `timeout` and batch schedulers stop a job with SIGTERM, which ends Python at once and leaves
    # its MLflow runs RUNNING: taken as Ctrl-C, Tune stops the trials and the runs close as KILLED below.
    previous_sigterm = signal.signal(signal.SIGTERM, lambda signum, frame: signal.raise_signal(signal.SIGINT))
    try:
        machines = cluster_machines(remote)
        if uri.startswith("sqlite:") and machines > 1:
            return _fail(
                f"MLflow store {uri}: this cluster spans (or may grow to) {machines} machines and trials on the others "
                "cannot write a SQLite file here; start an MLflow server every node reaches (`mlflow server "
                "--host <private ip> --port 5000 …`, cluster/README.md) and pass --tracking-uri http://<private ip>:5000"
            )
        capacity = cluster_capacity(remote)
        try:
            conc = plan_concurrency(plan.profile.resources, capacity["CPU"], capacity["GPU"], plan.num_trials, remote)
        except SpecError as exc:
            return _fail(str(exc))
        if args.resume:
            sweep_run = SweepRun.reopen(uri, stored["parent_run_id"])
        else:
            sweep_run = SweepRun.start(
                uri, plan.spec.name, f"{plan.spec.name} · {plan.profile.name} · {time.strftime('%Y-%m-%d %H:%M')}",
                tags={"spec": plan.spec.name, "profile": plan.profile.name, "sweep_dir": sweep_dir,
                      CARD_TAG: "\n".join(plan_card(plan).lines())},
                params={"profile": plan.profile.name, "search": plan.spec.search.kind, "trials": plan.num_trials,
                        "metric": plan.spec.metric.name, "steps": plan.profile.steps, "sets": json.dumps(sets),
                        **({"budget": args.budget} if args.budget else {})},
            )
            staging.mkdir(parents=True, exist_ok=True)
            state = {
                "spec": plan.spec.model_dump(mode="json"),
                "sets": sets,
                "profile": plan.profile.name,
                "budget": args.budget,
                "tracking_uri": uri,
                "parent_run_id": sweep_run.run_id,
            }
            _write_new(staging / STATE_FILE, json.dumps(state, indent=2))
            plan_file = staging / "plan.json"
            _write_new(plan_file, json.dumps(
                {"fixed": plan.fixed, "sets": sets, "cells": [
                    {"label": c.label, "values": c.values, "seed": c.seed, "paper": c.paper} for c in plan.cells]},
                indent=2, default=str))
            if is_uri(sweep_dir):
                publish_files(staging, sweep_dir)
            sweep_run.log_artifacts([args.spec.resolve(), plan_file])
        held.record(uri, sweep_run.run_id)
        print(f"profile in force: {plan.profile.name}; MLflow: {uri} (parent run {sweep_run.run_id})", flush=True)
        live = f"#/experiments/{sweep_run.experiment_id}/runs/{sweep_run.run_id}"
        print(f"watch it live: {_ui_hint(uri, live)}", flush=True)
        predicted = None
        if not args.resume:  # a resumed sweep has only its unfinished trials left: the estimate would not apply
            cluster = ray.cluster_resources()
            now = conc
            if remote:  # sized above by the most the cluster could offer; the estimate wants the nodes up now
                try:
                    now = plan_concurrency(
                        plan.profile.resources, cluster.get("CPU", 0.0), cluster.get("GPU", 0.0), plan.num_trials
                    )
                except SpecError:  # no node up fits a trial before the autoscaler adds one
                    now = None
            if now is None:
                print(
                    "estimate: none — no node up yet fits one trial; trials wait for the autoscaler to add one",
                    flush=True,
                )
            else:
                try:
                    predicted = estimate_line(plan, cluster.get("CPU", 1.0), now.max_concurrent,
                                          shared_root(sweep_dir, remote) is not None and bool(plan.cells))
                except (ValueError, OSError) as exc:  # an input every trial would fail on (an unreadable mesh)
                    kill_running_children(sweep_run)
                    sweep_run.end("FAILED")
                    discard_start(sweep_dir)
                    return _fail(f"the cost estimate could not read an input: {one_line(exc)}")
        started_at = time.perf_counter()
        # A resumed sweep keeps the callbacks it started with (Tune restores them): no line of its own.
        progress = None if args.resume else SweepProgress(
            sweep_run.run_id, plan.num_trials, plan.profile.steps, lambda t: plan.names(t.config)[1],
            predicted.wall_s if predicted else None, tty, rounds=plan.rounds,
            round_of=(lambda t: plan.round_of(plan.grid_cell(t.config["cell"]))) if plan.sequential else None)
        budget = budget_option(stored.get("budget") if args.resume else args.budget)
        try:
            outcomes = run_sweep(
                plan,
                conc,
                sweep_dir,
                sweep_run,
                args.resume,
                remote,
                callbacks=[progress] if progress else [],
                budget=budget,
            )
        finally:
            if progress is not None:
                progress.close()
        took = time.perf_counter() - started_at
        settled = None
        if plan.sequential is not None:
            from sweeps.compare.settle import final_round, write_settle_json

            settled = final_round(plan, outcomes, budget, sweep_run.client.get_run(sweep_run.run_id).data.tags).records
            sweep_run.log_artifacts([write_settle_json(staging / "settle.json", settled, budget)])
        table = build_table(outcomes, plan.spec.metric.name, plan.spec.metric.mode,
                            f"{plan.spec.name} — profile {plan.profile.name}",
                            f"{plan.spec.paper.table}: {plan.spec.paper.note}" if plan.spec.paper else "",
                            compare_to=plan.spec.compare_to, settings=_settings(plan), settled=settled)
        md, csv = table.write(staging)
        sweep_run.log_artifacts([md, csv])
        sweep_run.log_results(
            baselines_by_eval_set(outcomes),
            describe_sweep(plan.spec, plan.profile.name, plan.profile.description, table, plan_card(plan).lines()),
        )
        view = publish(uri, sweep_run.run_id, staging / "plots")
        if is_uri(sweep_dir):
            publish_files(staging, sweep_dir)
        unfinished = any(o.status == "pending" for o in outcomes)
        kill_running_children(sweep_run)
        sweep_run.end("KILLED" if unfinished else "FINISHED")
    except BaseException as exc:
        # Whatever stopped the sweep, its parent run must not stay RUNNING in the UI; re-raised as is,
        # but for a full disk: said as such, and the shared cache that filled it removed.
        if sweep_run is not None:
            kill_running_children(sweep_run)
            sweep_run.end("KILLED" if isinstance(exc, KeyboardInterrupt) else "FAILED")
        if no_space_left(exc):
            shared = shared_root(sweep_dir, remote)
            if shared is not None:
                shutil.rmtree(shared, ignore_errors=True)
            return _fail(
                f"no space left on the device of {sweep_dir}"
                + (f" (removed the shared cache {shared})" if shared else "")
                + f": {one_line(exc)[:200]}; free space, then resume with: "
                + resume_command(args.spec, plan.profile.name, args.storage)
            )
        raise
    finally:
        signal.signal(signal.SIGTERM, previous_sigterm)
        if started:
            ray.shutdown()
        if is_uri(sweep_dir):
            shutil.rmtree(staging)
    # The card was printed before the trials: the terminal's table leaves it to results.md.
    shown = replace(
        table,
        notes=[n for n in table.notes if not n.startswith(PROTOCOL_NOTE)]
        + ["protocol card: printed above, and in results.md"],
    )
    print("\n" + shown.text() + "\n")
    if predicted is not None:
        print(f"time: estimated ~{predicted.wall_s / 60:.1f} min, took {took / 60:.1f} min "
              f"(actual / estimate = {took / predicted.wall_s:.2f})")
    print(f"results: {sweep_dir}/{md.name} and {sweep_dir}/{csv.name}")
    print(f"MLflow: {_ui_hint(uri, view)}")
    if unfinished:
        print(
            f"some trials did not finish; continue with: {resume_command(args.spec, plan.profile.name, args.storage)}"
        )
    return 0 if any(o.finished for o in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
