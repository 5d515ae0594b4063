"""Measure the CPU a training step takes inside a real sweep against the same cells' steps alone.

Reads a finished sweep from its MLflow store (``--tracking-uri``, ``--experiment``: run the sweep
first, e.g. the main job ``python sweeps/run.py sweeps/point_size.yaml`` on the local profile) and
then times every cell's step alone here: one thread, on ready batches, nothing else running (run
this right after the sweep, with the machine otherwise idle). Cells cost different amounts a step
(point_size.yaml's 0.08 draws a wider footprint than 0.0075), so each cell is set against itself:

- in-trial: each trial's own CPU seconds per step (``train/cpu_s_per_step``, the process's CPU time
  over its logging windows, data included) ÷ that cell's mean over its first 40 batches alone; a row
  per cell and one for the sweep (the mean over cells of in-trial ÷ the mean of alone): what sharing
  the cores costs a step;
- whole sweep: ``CPUs × wall of the trial phase ÷ Σ steps`` ÷ the cells' mean step alone:
  everything else a sweep spends (driver, evaluations, set-up, idle cores) counted against its steps.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script, as the README does

if TYPE_CHECKING:
    from cdm.config import Config

__all__ = ["sweep_cpu_per_step"]


def _isolated_steps(config: Config, steps: int = 40) -> float:
    """Mean CPU seconds of one step alone over the run's first ``steps`` batches (drawn before timing),
    as a trial computes them: batches differ in how many voxels their clouds fill, so one batch's step
    is not the run's average step."""
    import torch

    from cdm.train import Trainer

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(config.replace(**{"train.out_dir": tmp, "train.threads": 1}))
        batches = []
        for step in range(steps):
            trainer.step = step
            batches.append(trainer.next_batch())
        trainer.step = 0
        times = []
        for batch in batches:
            start = time.process_time()
            trainer.train_step(batch)
            times.append(time.process_time() - start)
        return statistics.fmean(times)


def sweep_cpu_per_step(tracking_uri: str, experiment: str, cpus: float | None = None) -> list[dict]:
    from mlflow import MlflowClient

    from sweeps.plan.spec import load_spec
    from sweeps.plan.trials import expand

    client = MlflowClient(tracking_uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        raise ValueError(f"--experiment: no experiment {experiment!r} in {tracking_uri}")
    runs = client.search_runs([exp.experiment_id])
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags and r.info.end_time]
    if not children:
        raise ValueError(f"--experiment {experiment!r}: no finished trial runs")
    spec_name = children[0].data.tags.get("spec", experiment)
    profile = children[0].data.tags.get("profile", "local")
    cells = {c.label: c for c in expand(load_spec(f"sweeps/{spec_name}.yaml"), profile).cells}
    rows, in_trial, alone, steps = [], [], [], 0
    for r in sorted(children, key=lambda r: r.data.tags["mlflow.runName"]):
        cell = cells[r.data.tags["mlflow.runName"]]
        trial_s = statistics.fmean(m.value for m in client.get_metric_history(r.info.run_id, "train/cpu_s_per_step"))
        steps += int(max(m.step for m in client.get_metric_history(r.info.run_id, "train/loss")))
        alone_s = _isolated_steps(cell.config)
        in_trial.append(trial_s)
        alone.append(alone_s)
        rows.append({"benchmark": "CPU per step in a sweep ÷ alone", "case": f"{spec_name}, {profile}: {cell.label}",
                     "without_s": alone_s, "with_s": trial_s, "ratio": trial_s / alone_s, "target": "report"})
    spans = [(r.info.start_time / 1000, r.info.end_time / 1000) for r in children]
    wall = max(e for _, e in spans) - min(b for b, _ in spans)
    cpus = cpus or float(os.cpu_count() or 1)
    per_step = cpus * wall / steps
    alone_s, trial_s = statistics.fmean(alone), statistics.fmean(in_trial)
    return rows + [
        {
            "benchmark": "CPU per step in a sweep ÷ alone",
            "case": f"{spec_name}, {profile}: every cell, in-trial train/cpu_s_per_step ÷ the cell's first 40 "
            "batches alone",
            "without_s": alone_s,
            "with_s": trial_s,
            "ratio": trial_s / alone_s,
            "target": "<= 1.15",
        },
        {
            "benchmark": "CPU per step in a sweep ÷ alone",
            "case": f"{spec_name}, {profile}: {cpus:g} CPUs × trial-phase wall ÷ Σ steps",
            "without_s": alone_s,
            "with_s": per_step,
            "ratio": per_step / alone_s,
            "target": "<= 1.15",
        },
    ]


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracking-uri", required=True)
    parser.add_argument("--experiment", default="point_size")
    parser.add_argument("--cpus", type=float, default=None)
    args = parser.parse_args()
    for row in sweep_cpu_per_step(args.tracking_uri, args.experiment, args.cpus):
        print(
            f"| {row['benchmark']} | {row['case']} | {row['without_s']:.4f} | {row['with_s']:.4f} "
            f"| {row['ratio']:.3f} | {row['target']} |"
        )
