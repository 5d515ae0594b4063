"""Re-run one finished trial of a sweep from its MLflow record: its code, config and seed checked before it trains.

``cdm-lab rerun RUN_ID [--force] [--out DIR] [--tracking-uri URI]``, also ``python sweeps/rerun.py RUN_ID`` and,
for one release, ``python sweeps/run.py --rerun RUN_ID``: the command line of :mod:`sweeps.results.rerun`. The
re-run trains in this process, files its run under the sweep's parent run and prints how its metrics compare.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __package__ in (None, ""):  # `python sweeps/rerun.py` puts sweeps/ first on sys.path, not the repo root
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from cdm.cli import add_out, command_parser
from sweeps.store.files import StoreError, is_uri
from sweeps.store.tracking import check_tracking_uri

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    p = command_parser("rerun", __doc__.split("\n\n")[0], "3f2a9c0d1e4b47a5 --tracking-uri sqlite:///mlflow.db")
    p.add_argument("run_id", metavar="RUN_ID", help="the trial's MLflow child run id")
    p.add_argument("--force", action="store_true", help="run even if the code or config differs from the record")
    add_out(p, "<RUN_ID>/, the re-run's checkpoints and files, a local path (default: ./results/reruns)",
            default="results/reruns")
    p.add_argument("--tracking-uri", default=None, metavar="URI",
                   help="MLflow URI (default: MLFLOW_TRACKING_URI, else sqlite:///<cwd>/mlflow.db)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # MLflow and torch take seconds to import: only once the arguments are read.
    from sweeps.results.rerun import RerunError, rerun
    from sweeps.store.tracking import resolve_tracking_uri

    try:
        uri = resolve_tracking_uri(args.tracking_uri)
        check_tracking_uri(uri)
        if is_uri(args.out):
            raise StoreError(f"--out {args.out}: a re-run trains in this process and writes its files here; "
                             "give a local folder")
        return rerun(args.run_id, uri, Path(args.out).resolve(), args.force)
    except (StoreError, RerunError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
