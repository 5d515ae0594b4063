"""A finished sweep's best cell registered in MLflow's model registry: ``models:/<name>/<version>``.

The best cell is the one the sweep's results table stars (:func:`sweeps.compare.table.build_table`: the best mean
of the spec's metric, apart from the next at the printed precision); of its seeds, the trial with the best value
of that metric, the first in the sweep's order on a tie. Its run's MLflow model (:mod:`sweeps.mlflow_model`)
becomes a new version of the registered model ``name``, which ``cdm-lab evaluate --checkpoint
models:/<name>/<version>`` scores and ``mlflow.pyfunc.load_model`` loads.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from mlflow.utils.mlflow_tags import MLFLOW_MODEL_VERSIONS

from cdm.cli import command_parser
from cdm.io.json import parse_json
from sweeps.compare.outcomes import sweep_order
from sweeps.mlflow_model import logged_model
from sweeps.results.publish import open_given, sweep_arguments
from sweeps.results.sweep import SweepRecord, TrialRecord, results_table, trial_records
from sweeps.store.read import ReportError

__all__ = ["RegisterError", "best_trial", "build_parser", "check_name", "main", "register_best", "register_run"]

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")
"""A registered model's name: a ``models:/<name>/<version>`` URI holds it unquoted."""


class RegisterError(ValueError):
    """Nothing to register, or a name the registry's URIs cannot hold; the message says which and why."""


def check_name(name: str, field: str = "--name") -> str:
    """``name`` when a ``models:/`` URI can hold it, else :class:`RegisterError` naming ``field`` and the rule."""
    if not _NAME.fullmatch(name):
        raise RegisterError(f"{field}: {name!r} is not a model name: give 1 to 100 letters, digits, '.', '_' or '-', "
                            "starting with a letter or digit")
    return name


def best_trial(record: SweepRecord) -> TrialRecord:
    """The trial whose model stands for the sweep: the starred cell's best seed by the spec's metric.

    Raises:
        RegisterError: no cell is starred (none finished, or the leaders tie at the printed precision).
    """
    trials = trial_records(record, objects=False)  # the star needs the means only, not the paired rows
    best = results_table(record, trials).best
    metric, mode = record.spec.metric.name, record.spec.metric.mode
    if best is None:
        raise RegisterError(f"sweep {record.parent.info.run_id} has no best cell by {metric} ({mode}): none finished, "
                            "or the leaders tie at the printed precision (the results table marks them tied)")
    seeds = [t for t in trials if t.outcome.cell == best and t.outcome.finished and metric in t.outcome.metrics]
    best_first = sweep_order(None, metric, mode)
    return min(seeds, key=lambda t: best_first(t.outcome))


def register_run(client, run_id: str, name: str, description: str = ""):
    """A new version of the registered model ``name`` (created if new) holding run ``run_id``'s MLflow model;
    returns the ``ModelVersion``.

    Raises:
        RegisterError: the run logged no MLflow model (a run of cdm-lab 0.1.0 kept a plain folder).
    """
    model = logged_model(client, run_id)
    if model is None:
        raise RegisterError(f"run {run_id} logged no MLflow model (runs of cdm-lab 0.1.0 kept a plain model/ folder: "
                            f"score it with cdm-lab evaluate --checkpoint runs:/{run_id}/model)")
    if not client.search_registered_models(filter_string=f"name = '{check_name(name)}'"):
        client.create_registered_model(name)
    # The model's own artifact location, not models:/<id>: a SQLite registry would resolve that against
    # MLflow's process-wide tracking URI, not this client's store.
    version = client.create_model_version(name, model.artifact_location, run_id=run_id, model_id=model.model_id,
                                          description=description)
    # How MLflow links a logged model to its versions (mlflow.register_model does the same): the Models tab
    # lists the version on the model's page.
    earlier = parse_json(model.tags.get(MLFLOW_MODEL_VERSIONS, "[]").encode(), "--name",
                         Path(f"models:/{model.model_id}") / MLFLOW_MODEL_VERSIONS)
    linked = (earlier if isinstance(earlier, list) else []) + [{"name": name, "version": version.version}]
    client.set_logged_model_tags(model.model_id, {MLFLOW_MODEL_VERSIONS: json.dumps(linked)})
    return version


def register_best(record: SweepRecord, name: str):
    """Register :func:`best_trial`'s model as a new version of ``name``; returns the ``ModelVersion`` and a line
    saying which trial it holds and why (also the version's description)."""
    trial = best_trial(record)
    metric = record.spec.metric.name
    said = (f"sweep {record.experiment} (parent run {record.parent.info.run_id}): best cell {trial.outcome.cell} "
            f"by {metric} ({record.spec.metric.mode}), its trial {trial.outcome.label} at "
            f"{trial.outcome.metrics[metric]:g}")
    return register_run(record.client, trial.run_id, name, said), said


def build_parser() -> argparse.ArgumentParser:
    p = sweep_arguments(command_parser("register", "Register a finished sweep's best cell's model in MLflow's model "
                                       "registry", "point_size --name cdm-point-size"))
    p.add_argument("--name", required=True, metavar="NAME",
                   help="registered model name: letters, digits, '.', '_', '-' (a new version when it exists)")
    return p


def main(argv: list[str] | None = None) -> int:
    from mlflow.exceptions import MlflowException

    from sweeps.store.files import StoreError

    args = build_parser().parse_args(argv)
    try:
        check_name(args.name)
        version, said = register_best(open_given(args), args.name)
    except (RegisterError, ReportError, StoreError, MlflowException) as exc:
        print(f"error: {' '.join(str(exc).split())[:300]}", file=sys.stderr)
        return 2
    print(said)
    print(f"registered as models:/{version.name}/{version.version}: cdm-lab evaluate --checkpoint "
          f"models:/{version.name}/{version.version}")
    return 0
