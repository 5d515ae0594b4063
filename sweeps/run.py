"""Run a sweep: train every trial of a spec on Ray, track it in MLflow and print the results table.

The spec is expanded and every cell's config validated before Ray starts; a bad spec exits with
code 2 and one message naming the field, having written nothing. Then the trials run on Ray (a local
cluster bound to 127.0.0.1, or ``--address``/``RAY_ADDRESS``), tracked in MLflow, and the results
table is printed and written to ``<out>/<spec name>/<profile>/results.{md,csv}``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __package__ in (None, ""):  # `python sweeps/run.py` puts sweeps/ first on sys.path, not the repo root
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from cdm.cli import add_out, add_set, command_parser
from sweeps.execute.precompute import precomputes
from sweeps.execute.settle import UntilSettled
from sweeps.plan.describe import describe, wrapped
from sweeps.plan.limits import MAX_TRIALS
from sweeps.plan.preflight import dry_run
from sweeps.plan.request import RequestError, SweepRequest, missing_inputs, plan_request
from sweeps.store.files import TRUST_FLAG, StoreError, exists, is_uri, record_digest

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    p = command_parser("run", __doc__.split("\n\n")[0].replace("\n", " "), "sweeps/point_size.yaml --smoke")
    p.add_argument("spec", type=Path, metavar="SPEC", help="sweep spec YAML, e.g. sweeps/point_size.yaml")
    p.add_argument("--profile", default=None, metavar="NAME",
                   help="profile in sweeps/profiles.yaml or the spec: smoke, local or paper (default: local)")
    p.add_argument("--smoke", action="store_true", help="same as --profile smoke")
    p.add_argument(
        "--resume", action="store_true",
        help="continue an interrupted sweep: unfinished trials, and failed ones up to failure.max_retries times"
    )
    p.add_argument(
        TRUST_FLAG,
        action="store_true",
        help="with --resume: unpickle Tune's state even where others could have written it (docs/security.md)",
    )
    p.add_argument(
        "--until-settled",
        action="store_true",
        help="run seeds until each cell's comparison settles: a list of seeds becomes {min: 2, max: 5} "
        "(docs/sweeps.md, Seeds until settled)",
    )
    p.add_argument("--budget", default=None, metavar="2h|45m|30s|N",
                   help="with seeds until settled: no seed starts past this wall time (hours, minutes, seconds), "
                        "or past N trials")
    p.add_argument(
        "--dry-run",
        action="store_true",
        help="print the trials, the resource plan and the protocol card; start nothing",
    )
    p.add_argument(
        "--no-estimate", action="store_true", help="with --dry-run: skip the cost estimate's calibration steps"
    )
    p.add_argument("--address", default=None, metavar="HOST:PORT|auto",
                   help="Ray cluster address (default: RAY_ADDRESS, else a local cluster on 127.0.0.1)")
    add_set(p, "priors.lambda_3d=0.5 (every trial)")
    add_out(p, "one folder per sweep, <spec>/<profile>/: a path (shared by every node on a cluster) or a URI "
               "(s3://, gs://, file://) (default: ./results)", dest="storage", default="results")
    p.add_argument("--tracking-uri", default=None, metavar="URI",
                   help="MLflow URI (default: MLFLOW_TRACKING_URI, else sqlite:///<cwd>/mlflow.db)")
    p.add_argument("--max-cells", type=int, default=MAX_TRIALS, metavar="N",
                   help=f"refuse a sweep of more than N trials (default {MAX_TRIALS}; docs/security.md)")
    p.add_argument("--register", default=None, metavar="NAME",
                   help="when the sweep ends, register its best cell's model in MLflow's model registry as NAME "
                        "(as `cdm-lab register`; then evaluate --checkpoint models:/NAME/<version>)")
    return p


def _fail(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


# Ray, MLflow and torch take seconds to import: the functions below import the stages that need them
# only on the path that runs them, so --help, a dry run and a refused spec answer at once.


def _destinations(request: SweepRequest) -> list[str]:
    """Where a run of this request would keep its files and log its runs (the dry run's lines)."""
    from sweeps.store.tracking import artifact_location, resolve_tracking_uri

    uri = resolve_tracking_uri(request.tracking_uri)
    name = request.plan.spec.name
    artifacts = artifact_location(uri, name)
    return [
        f"storage: {request.sweep_dir} (results.md, results.csv, the trials' folders and checkpoints, Tune's state)",
        f"MLflow tracking URI: {uri}, experiment {name}"
        + (f" (artifacts: {artifacts.removeprefix('file://')})" if artifacts else " (artifacts: the server's store)"),
    ]


def _sweep(args: argparse.Namespace, request: SweepRequest) -> int:
    from sweeps.execute.driver import DriverError, Publisher, claim_sweep, run_claimed
    from sweeps.results import register
    from sweeps.results.publish import describe_sweep, publish

    try:
        if args.register is not None:
            register.check_name(args.register, "--register")
        uri, held = claim_sweep(request, args)
    except (DriverError, register.RegisterError) as exc:
        return _fail(str(exc))
    plan = request.plan
    print(describe(plan, None, None, UntilSettled(plan, request.budget).lines()), flush=True)
    try:
        code = run_claimed(request, args, uri, held, Publisher(describe_sweep, publish))
    except DriverError as exc:
        return _fail(str(exc))
    finally:
        if is_uri(request.sweep_dir) and exists(request.sweep_dir):
            record_digest(request.sweep_dir)  # what this driver leaves is what the next --resume may unpickle
        held.release()
    if args.register is None:
        return code
    if code != 0:
        print(f"--register {args.register}: nothing registered, the sweep ended with exit code {code}; register it "
              f"later with `cdm-lab register {plan.spec.name} --name {args.register}`", file=sys.stderr)
        return code
    return register.main([plan.spec.name, "--name", args.register, "--tracking-uri", uri])


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        request = plan_request(args)
        plan = request.plan
        print(wrapped(f"spec {plan.spec.name} ({args.spec}): {plan.spec.description}"), flush=True)
        missing = missing_inputs(plan, request.remote, args.dry_run)
    except (RequestError, StoreError) as exc:
        return _fail(str(exc))
    if args.dry_run:
        return dry_run(plan, request.remote, UntilSettled(plan, request.budget).lines(), not args.no_estimate,
                       precomputes(plan, request.sweep_dir, request.remote), missing, _destinations(request))
    return _sweep(args, request)


if __name__ == "__main__":
    sys.exit(main())
