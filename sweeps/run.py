"""Run a sweep: ``python sweeps/run.py SPEC [--profile smoke|local|paper] [--smoke] [--resume] [--dry-run]
[--address ADDR] [--set key=value ...] [--storage PATH] [--tracking-uri URI]``, or re-run one finished
trial from its MLflow record: ``python sweeps/run.py --rerun RUN_ID [--force]``.

The spec is expanded and every cell's config validated before Ray starts; a bad spec exits with
code 2 and one message naming the field, having written nothing. Then the trials run on Ray (a local
cluster bound to 127.0.0.1, or ``--address``/``RAY_ADDRESS``), tracked in MLflow, and the results
table is printed and written to ``<storage>/<spec name>/<profile>/results.{md,csv}``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # `python sweeps/run.py` puts sweeps/ first on sys.path, not the repo root
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pydantic import ValidationError

from cdm.config import ConfigError, parse_override
from sweeps.spec import Spec, SpecError, SweepPlan, expand, load_spec, plan_concurrency

__all__ = ["describe", "main"]

STATE_FILE = "sweep.json"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sweeps/run.py", description=__doc__.split("\n\n")[1])
    p.add_argument("spec", type=Path, nargs="?", help="sweep spec, e.g. sweeps/point_size.yaml")
    p.add_argument("--profile", default=None, help="profile in sweeps/profiles.yaml or the spec (default: local)")
    p.add_argument("--smoke", action="store_true", help="same as --profile smoke")
    p.add_argument("--resume", action="store_true", help="continue an interrupted sweep; re-runs only unfinished trials")
    p.add_argument("--dry-run", action="store_true", help="print the trials and the resource plan; start nothing")
    p.add_argument("--address", default=None, help="Ray cluster address (default: RAY_ADDRESS, else a local cluster)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override for every trial")
    p.add_argument("--storage", type=Path, default=Path("results"), help="parent folder of sweep folders (default: ./results)")
    p.add_argument("--tracking-uri", default=None, help="MLflow URI (default: MLFLOW_TRACKING_URI, else sqlite:///<cwd>/mlflow.db)")
    p.add_argument("--rerun", metavar="RUN_ID", default=None, help="re-run the trial of this MLflow child run from its record")
    p.add_argument("--force", action="store_true", help="with --rerun: run even if the code or config differs from the record")
    return p


def describe(plan: SweepPlan, cpus: float | None, gpus: float | None) -> str:
    """The dry-run text: profile, search, resource plan and every trial (or the Optuna space)."""
    spec, prof, r = plan.spec, plan.profile, plan.profile.resources
    out = [
        f"profile {prof.name}: {prof.description}".rstrip(": "),
        f"budget: {prof.steps} steps, evaluation every {prof.eval_every}",
        (f"metric: {spec.metric.name} ({spec.metric.mode}); scheduler: {spec.scheduler.kind}; "
         f"max retries per trial: {spec.failure.max_retries}"),
    ]
    mode = "Train local mode (loop inside the trial)" if r.workers_per_trial == 0 else f"{r.workers_per_trial} Train workers"
    line = f"resources: {mode}, {r.cpus_per_worker:g} CPUs + {r.gpus_per_worker:g} GPUs per worker"
    if cpus is None:
        line += "; concurrency derived from the cluster at run time"
    else:
        try:
            conc = plan_concurrency(r, cpus, gpus or 0.0, plan.num_trials)
            line += f"; this machine: {cpus:g} CPUs, {gpus or 0:g} GPUs → {conc.max_concurrent} concurrent trials"
        except SpecError as exc:
            line += f"; this machine cannot run it: {exc}"
    out.append(line)
    out.append("fixed: " + ", ".join(f"{k}={v}" for k, v in {**plan.fixed, **plan.sets}.items()))
    if spec.search.kind == "optuna":
        s = spec.search
        out.append(f"search: Optuna {s.sampler} (seed {s.seed}), {plan.num_trials} trials, seed {spec.seeds[0]}, over:")
        for key, p in s.space.items():
            rng = f"{p.choices}" if p.type == "categorical" else f"[{p.low:g}, {p.high:g}]"
            out.append(f"  {key}: {p.type} {rng}")
    else:
        out.append(f"search: grid, {plan.num_trials} trials ({plan.num_trials // len(spec.seeds)} cells × {len(spec.seeds)} seeds):")
        for i, cell in enumerate(plan.cells, 1):
            values = ", ".join(f"{k}={v}" for k, v in cell.values.items())
            line = f"  {i:3d}. {cell.label}" + (f"   ({values})" if values else "")
            if cell.paper_label and spec.paper:
                numbers = ", ".join(f"{k} {v:g}" for k, v in cell.paper.items() if k.count("/") == 1)
                line += f"   [paper {spec.paper.table} · {cell.paper_label}: {numbers}]"
            out.append(line)
    return "\n".join(out)


def _fail(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if (args.spec is None) == (args.rerun is None):
        return _fail("give a sweep spec (e.g. sweeps/point_size.yaml) or --rerun RUN_ID, not both or neither")
    if args.rerun is not None:
        from sweeps.rerun import RerunError, rerun
        from sweeps.tracking import resolve_tracking_uri

        try:
            return rerun(args.rerun, resolve_tracking_uri(args.tracking_uri), (args.storage / "reruns").resolve(), args.force)
        except RerunError as exc:
            return _fail(str(exc))
    if args.smoke and args.profile not in (None, "smoke"):
        return _fail(f"--smoke means --profile smoke; got --profile {args.profile} too")
    profile = "smoke" if args.smoke else (args.profile or "local")
    try:
        spec = load_spec(args.spec)
        sweep_dir = (args.storage / spec.name / profile).resolve()
        state_file = sweep_dir / STATE_FILE
        sets = dict(parse_override(text) for text in args.set)
        if args.resume:
            if not state_file.is_file():
                return _fail(f"--resume: {sweep_dir} holds no sweep to resume (no {STATE_FILE})")
            if sets:
                return _fail("--resume continues a sweep with the spec and --set values it started with; drop --set")
            # The spec as it started, even if the file was edited since: trials must stay the same.
            try:
                state = json.loads(state_file.read_text())
                spec, sets = Spec.model_validate(state["spec"]), state["sets"]
            except (json.JSONDecodeError, KeyError, ValidationError) as exc:
                return _fail(f"--resume: {state_file} is damaged ({type(exc).__name__}: {exc}); remove the folder to start over")
        plan = expand(spec, profile, sets)
    except (SpecError, ConfigError) as exc:
        return _fail(str(exc))
    print(f"spec {spec.name} ({args.spec}): {spec.description}", flush=True)
    if args.dry_run:
        import torch

        from sweeps.estimate import estimate

        local = args.address is None and "RAY_ADDRESS" not in os.environ
        cpus, gpus = (os.cpu_count() or 1, torch.cuda.device_count()) if local else (None, None)
        print(describe(plan, cpus, gpus), flush=True)
        if cpus is None:
            print("estimate: run --dry-run on the cluster's head (without --address) to size it")
            return 0
        try:
            concurrent = plan_concurrency(plan.profile.resources, cpus, gpus, plan.num_trials).max_concurrent
        except SpecError:
            return 0  # describe() has said why this machine cannot run it
        print("calibrating (a few training steps and one evaluation) ...", flush=True)
        print(estimate(plan, cpus, concurrent).text())
        return 0
    if not args.resume and sweep_dir.exists():
        return _fail(f"{sweep_dir} already holds a sweep: pass --resume to continue it, or remove the folder to start over")
    print(describe(plan, None, None), flush=True)
    return _run(plan, args, sweep_dir, state_file, sets)


def _run(plan: SweepPlan, args: argparse.Namespace, sweep_dir: Path, state_file: Path, sets: dict) -> int:
    # Read when ray is imported: progress lines of concurrent trials differ only in numbers, and
    # Ray's log de-duplication would fold them into "[repeated 3x]".
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    # The results table downloads each trial's per-object scores: no progress bar per small file.
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    import ray

    from sweeps.estimate import estimate
    from sweeps.results import build_table
    from sweeps.tracking import SweepRun, resolve_tracking_uri, ui_command
    from sweeps.trial import connect, run_sweep

    # A resumed sweep keeps logging into the store it started with, wherever it is resumed from.
    stored_uri = json.loads(state_file.read_text()).get("tracking_uri") if args.resume else None
    uri = resolve_tracking_uri(args.tracking_uri or stored_uri)
    started = connect(args.address)
    try:
        if args.resume:
            sweep_run = SweepRun.reopen(uri, json.loads(state_file.read_text())["parent_run_id"])
        else:
            sweep_run = SweepRun.start(
                uri, plan.spec.name, f"{plan.spec.name} · {plan.profile.name} · {time.strftime('%Y-%m-%d %H:%M')}",
                tags={"spec": plan.spec.name, "profile": plan.profile.name, "sweep_dir": str(sweep_dir)},
                params={"profile": plan.profile.name, "search": plan.spec.search.kind, "trials": plan.num_trials,
                        "metric": plan.spec.metric.name, "steps": plan.profile.steps, "sets": json.dumps(sets)},
            )
            sweep_dir.mkdir(parents=True)
            state = {"spec": plan.spec.model_dump(mode="json"), "sets": sets, "profile": plan.profile.name,
                     "tracking_uri": uri, "parent_run_id": sweep_run.run_id}
            state_file.write_text(json.dumps(state, indent=2))
            plan_file = sweep_dir / "plan.json"
            plan_file.write_text(json.dumps(
                {"fixed": plan.fixed, "sets": sets, "cells": [
                    {"label": c.label, "values": c.values, "seed": c.seed, "paper": c.paper} for c in plan.cells]},
                indent=2, default=str))
            sweep_run.log_artifacts([args.spec.resolve(), plan_file])
        print(f"profile in force: {plan.profile.name}; MLflow: {uri} (parent run {sweep_run.run_id})", flush=True)
        predicted = None
        if not args.resume:  # a resumed sweep has only its unfinished trials left: the estimate would not apply
            cluster = ray.cluster_resources()
            conc = plan_concurrency(plan.profile.resources, cluster.get("CPU", 0.0), cluster.get("GPU", 0.0), plan.num_trials)
            predicted = estimate(plan, cluster.get("CPU", 1.0), conc.max_concurrent)
            print(predicted.text(), flush=True)
        started_at = time.perf_counter()
        outcomes = run_sweep(plan, sweep_dir, sweep_run, args.resume)
        took = time.perf_counter() - started_at
        table = build_table(outcomes, plan.spec.metric.name, plan.spec.metric.mode,
                            f"{plan.spec.name} — profile {plan.profile.name}",
                            f"{plan.spec.paper.table}: {plan.spec.paper.note}" if plan.spec.paper else "",
                            compare_to=plan.spec.compare_to)
        md, csv = table.write(sweep_dir)
        sweep_run.log_artifacts([md, csv])
        unfinished = any(o.status == "pending" for o in outcomes)
        sweep_run.end("KILLED" if unfinished else "FINISHED")
    finally:
        if started:
            ray.shutdown()
    print("\n" + table.text() + "\n")
    if predicted is not None:
        print(f"time: estimated ~{predicted.wall_s / 60:.1f} min, took {took / 60:.1f} min "
              f"(actual / estimate = {took / predicted.wall_s:.2f})")
    print(f"results: {md} and {csv}")
    print(f"MLflow: {ui_command(uri)}   (then open http://127.0.0.1:5000)")
    if unfinished:
        print(f"some trials did not finish; continue with: python sweeps/run.py {args.spec} --profile {plan.profile.name} --resume")
    return 0 if any(o.status in ("ok", "stopped") for o in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
