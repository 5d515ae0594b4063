"""Re-run one finished trial of a sweep from its MLflow record: its code, config and seed checked before it trains.

``cdm-lab rerun RUN_ID [--force] [--out DIR] [--tracking-uri URI]`` (also ``python sweeps/rerun.py RUN_ID``).
The child run holds the resolved config (``config.yaml``) and the reproducibility record (``repro.*`` tags,
:mod:`cdm.provenance`). The re-run refuses to start when the checked-out code is not the recorded commit or the
config no longer hashes the same (the schema changed), unless forced; then it trains in this process with the
recorded torch thread count, files a new run tagged ``rerun_of`` under the sweep's parent run, and prints recorded
against re-run final metrics. Exit 0 when they are identical, 1 when not, 2 when it cannot start.

Before training it names each part of the machine that differs from the record (CPU model and ISA, ATen's
capability, the BLAS/oneDNN build, kernel pins, the installed packages: :data:`cdm.provenance.MACHINE_KEYS`),
since on CPU any of them can change the numbers (docs/local-results.md).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):  # `python sweeps/rerun.py` puts sweeps/ first on sys.path, not the repo root
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch
from mlflow import MlflowClient
from mlflow.entities import Run
from mlflow.exceptions import MlflowException

from cdm.cli import add_out, command_parser
from cdm.config import Config, load_config
from cdm.io.files import is_uri, read_text
from cdm.metric_names import CD, METRICS
from cdm.provenance import MACHINE_KEYS, code_version, config_hash, installed_packages, machine_record
from cdm.train import Callback, fit
from sweeps.store.files import StoreError, one_line
from sweeps.store.tracking import check_tracking_uri, resolve_tracking_uri
from sweeps.store.tracking import client as store_client
from sweeps.store.trial_run import PACKAGES_FILE, TrialRun

__all__ = ["RerunError", "build_parser", "machine_differences", "main", "rerun"]


class RerunError(ValueError):
    """The run cannot be re-run as recorded; the message says why and what to do."""


class _Record(Callback):
    def __init__(self) -> None:
        self.record: dict[str, str] = {}

    def on_start(self, record: dict[str, str]) -> None:
        self.record = record


def _shown(value: str, width: int = 60) -> str:
    """A recorded tag value as one short line: quoted when it is not plain (a newline, a quote, more than
    ``width`` characters)."""
    return value if value.isprintable() and len(value) <= width and "'" not in value else repr(value[:width])


def _code_warnings(tags: dict[str, str], force: bool) -> list[str]:
    """Refuse another commit (unless ``force``); uncommitted changes on either side only warn."""
    code = code_version()
    # Recorded values are shown, never run, and one line each: a planted newline or a page of text stays quoted.
    recorded = {k: _shown(tags.get(f"repro.{k}", "missing")) for k in code}
    if recorded["git_commit"] != code["git_commit"] and not force:
        raise RerunError(f"recorded commit {recorded['git_commit']}, checked out {code['git_commit']} — check out the "
                         "recorded commit, or pass --force to re-run anyway")
    warnings = []
    if recorded["git_commit"] != code["git_commit"]:
        warnings.append(f"recorded commit {recorded['git_commit']}, checked out {code['git_commit']} (--force)")
    if "true" in (recorded["git_dirty"], code["git_dirty"]):
        warnings.append(
            f"uncommitted changes (recorded run: {recorded['git_dirty']}, this checkout: {code['git_dirty']}); "
            "the code may differ from the recorded run's"
        )
    return warnings


SHOWN_PACKAGES = 8
"""Most differing packages named one by one; the rest are counted."""

MAX_PACKAGES_FILE = 1 << 20
"""Largest recorded package list read (bytes): a few hundred lines take ~10 KB."""


def _recorded_packages(client: MlflowClient, run_id: str) -> dict[str, str] | None:
    """The run's recorded package list as {name: version}; None when it holds none (or not a readable one)."""
    with tempfile.TemporaryDirectory() as tmp:
        try:
            text = read_text(Path(client.download_artifacts(run_id, PACKAGES_FILE, tmp)), "package list",
                             MAX_PACKAGES_FILE)
        except (MlflowException, OSError, ValueError):
            return None
    return dict(line.partition("==")[::2] for line in text.splitlines() if "==" in line)


def _package_changes(recorded: dict[str, str]) -> str:
    """``numpy 2.1.0 → 2.2.0, +rich 13.0 (only here), -tqdm 4.6 (only recorded)``, at most :data:`SHOWN_PACKAGES`."""
    here = dict(line.partition("==")[::2] for line in installed_packages())
    changes = [f"{_shown(n)} {_shown(recorded[n])} → {here[n]}" for n in sorted(recorded.keys() & here.keys())
               if recorded[n] != here[n]]
    changes += [f"+{n} {here[n]} (only here)" for n in sorted(here.keys() - recorded.keys())]
    changes += [f"-{_shown(n)} {_shown(recorded[n])} (only recorded)" for n in sorted(recorded.keys() - here.keys())]
    more = len(changes) - SHOWN_PACKAGES
    return ", ".join(changes[:SHOWN_PACKAGES]) + (f" and {more} more" if more > 0 else "")


def machine_differences(client: MlflowClient, run_id: str, tags: dict[str, str]) -> list[str]:
    """One line per part of this machine (:func:`cdm.provenance.machine_record`) that differs from the run's
    ``repro.*`` record; for the packages, which ones changed (from the run's package list, where it holds one)."""
    here = machine_record()
    if not any(f"repro.{k}" in tags for k in MACHINE_KEYS):
        return [f"the record names no machine (a run from before it was recorded); this one: {here['cpu_model']}, "
                f"{here['cpu_capability']}, {here['math_libraries']}"]
    lines = []
    for key in MACHINE_KEYS:
        recorded = tags.get(f"repro.{key}", "not recorded")
        if recorded != here[key]:
            lines.append(f"repro.{key}: recorded {_shown(recorded, 120)}, here {here[key]}")
    if "repro.packages_digest" in tags and tags["repro.packages_digest"] != here["packages_digest"]:
        packages = _recorded_packages(client, run_id)
        if packages is not None:
            lines.append(f"packages: {_package_changes(packages)}")
    return lines


MAX_THREADS = 4096
"""Most torch threads a recorded ``repro.torch_threads`` may name."""


def _recorded_threads(text: str | None) -> int:
    """The recorded torch thread count (this process's when none was recorded), 1 to :data:`MAX_THREADS`."""
    if text is None:
        return torch.get_num_threads()
    if not (text.isascii() and text.isdigit() and len(text) <= 4 and 1 <= int(text) <= MAX_THREADS):
        raise RerunError(
            f"rerun: the record's repro.torch_threads is {text[:40]!r}; expected a whole number from 1 to "
            f"{MAX_THREADS} (a damaged or edited record)"
        )
    return int(text)


def _recorded_run(client: MlflowClient, run_id: str, uri: str) -> Run:
    """The child run ``run_id``, holding a reproducibility record."""
    try:
        run = client.get_run(run_id)
    except MlflowException:
        raise RerunError(f"rerun: no run {run_id!r} in {uri}") from None
    if "repro.config_hash" not in run.data.tags:
        raise RerunError(f"rerun: run {run_id} has no reproducibility record (repro.* tags); was it a sweep trial?")
    return run


def _recorded_config(client: MlflowClient, run_id: str, out: Path) -> Config:
    """The run's ``config.yaml`` as this code reads it, writing its files to ``out``."""
    with tempfile.TemporaryDirectory() as tmp:
        try:
            return load_config(client.download_artifacts(run_id, "config.yaml", tmp), {"train.out_dir": str(out)})
        except (MlflowException, OSError) as exc:
            raise RerunError(
                f"rerun: run {run_id} has no readable config.yaml ({one_line(exc)[:200]})"
            ) from None
        except ValueError as exc:  # ConfigError: a recorded value this code no longer accepts
            raise RerunError(f"rerun: run {run_id}'s config.yaml: {exc}") from None


def _config_warnings(config: Config, recorded: str, force: bool) -> list[str]:
    """Refuse a config that no longer hashes as ``recorded`` (unless ``force``: then a warning)."""
    if config_hash(config) == recorded:
        return []
    message = f"config hash {config_hash(config)} differs from the recorded {_shown(recorded)} (defaults changed?)"
    if not force:
        raise RerunError(message + "; pass --force to re-run anyway")
    return [message]


def _train_again(client: MlflowClient, uri: str, run: Run, config: Config) -> tuple[Run, dict[str, str]]:
    """Train ``config`` in this process as a new child run of ``run``'s parent; that run and what training
    recorded at its start (:class:`cdm.train.Callback`'s ``on_start`` record)."""
    from sweeps.execute.trial import TrialProgress, learning_curve  # imports Ray (seconds): only once a re-run trains

    name = f"rerun of {run.info.run_name}"
    tracked = TrialRun(uri, run.info.experiment_id, run.data.tags.get("mlflow.parentRunId", ""),
                       f"rerun:{run.info.run_id}:{time.time_ns()}", name, {"rerun_of": run.info.run_id}, config,
                       curve=learning_curve)
    seen = _Record()
    try:
        fit(config, [TrialProgress(name, config.train.steps, CD.key), tracked, seen])
    except BaseException:  # re-raised: only marks the re-run's MLflow run failed instead of left running
        client.set_terminated(tracked.run_id, "FAILED")
        raise
    client.set_terminated(tracked.run_id)
    return client.get_run(tracked.run_id), seen.record


def _compare(run: Run, again: Run, record: dict[str, str]) -> int:
    """Print both runs' final metrics and any differing ``repro.*`` value side by side; 0 when all are equal."""
    # Both runs' scores as their child runs hold them: the floats the trainer reported, compared exactly.
    tags = run.data.tags
    rows = [(m, run.data.metrics.get(m), again.data.metrics.get(m)) for m in (r.key for r in METRICS.values())]
    rows += [(f"repro.{k}", tags.get(f"repro.{k}"), v) for k, v in record.items() if tags.get(f"repro.{k}") != v]
    width = max(len(r[0]) for r in rows)
    print(f"\n{'':{width}}  recorded ({run.info.run_id[:8]})  re-run ({again.info.run_id[:8]})")
    for key, recorded, value in rows:
        print(f"{key:{width}}  {recorded!s:20}  {value!s:20}  {'same' if recorded == value else 'DIFFERENT'}")
    same = all(a == b for _, a, b in rows)
    print("reproduced exactly" if same else "not reproduced: see the rows marked DIFFERENT")
    return 0 if same else 1


def rerun(run_id: str, uri: str, out_root: Path, force: bool = False) -> int:
    """Re-run child run ``run_id`` of the MLflow store at ``uri``; files go under ``out_root/<run_id>``.

    Raises:
        RerunError: unknown run, no record, other code or config (without ``force``).
    """
    client = store_client(uri)
    run = _recorded_run(client, run_id, uri)
    tags = run.data.tags
    warnings = _code_warnings(tags, force)
    threads = _recorded_threads(tags.get("repro.torch_threads"))
    config = _recorded_config(client, run_id, out_root / run_id)
    warnings += _config_warnings(config, tags["repro.config_hash"], force)
    machine = machine_differences(client, run_id, tags)
    if machine:
        warnings.append("this machine differs from the recorded run's; on CPU each of these can change the numbers "
                        "(docs/local-results.md, What varies):" + "".join(f"\n  {line}" for line in machine))
    for w in warnings:
        print(f"warning: {w}", flush=True)
    # Float sums depend on how work is split between threads; the trial's count makes them equal.
    torch.set_num_threads(threads)
    return _compare(run, *_train_again(client, uri, run, config))


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
