"""CPU per training step inside a real sweep ÷ the isolated step (issue 19: ≤ 1.15, was ~1.85).

Reads a finished sweep from its MLflow store (``--tracking-uri``, ``--experiment``: run the sweep
first, e.g. the main job ``python sweeps/run.py sweeps/point_size.yaml`` on the local profile) and
times the isolated step of its first cell here: one thread, on ready batches, nothing else running
(run this with the machine otherwise idle). Three rows:

- in-trial: the trials' own CPU seconds per step (``train/cpu_s_per_step``, the process's CPU time
  over its logging windows, data included) ÷ the isolated step: what sharing the cores costs a step.
  The isolated step is the mean over the cell's first 40 batches (the ratio's target row) and, for
  comparison with earlier figures, the median on one fixed batch;
- whole sweep: ``CPUs × wall of the trial phase ÷ Σ steps`` ÷ the isolated step: everything else a
  sweep spends (driver, evaluations, set-up, idle cores) counted against its training steps.
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

from benchmarks.common import median_s  # noqa: E402

if TYPE_CHECKING:
    from cdm.config import Config

__all__ = ["sweep_cpu_per_step"]


def _isolated_steps(config: Config, steps: int = 40) -> tuple[float, float]:
    """CPU seconds of one step alone: the median on one fixed batch, and the mean over the run's first
    ``steps`` batches (drawn before timing), as a trial computes them: batches differ in how many
    voxels their clouds fill, so one batch's step is not the run's average step."""
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
        fixed = median_s(lambda: trainer.train_step(batches[0]), 8, clock=time.process_time)
        times = []
        for batch in batches:
            start = time.process_time()
            trainer.train_step(batch)
            times.append(time.process_time() - start)
        return fixed, statistics.fmean(times)


def sweep_cpu_per_step(tracking_uri: str, experiment: str, cpus: float | None = None) -> list[dict]:
    from mlflow import MlflowClient

    from sweeps.plan import expand
    from sweeps.spec import load_spec

    client = MlflowClient(tracking_uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        raise ValueError(f"--experiment: no experiment {experiment!r} in {tracking_uri}")
    runs = client.search_runs([exp.experiment_id])
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags and r.info.end_time]
    if not children:
        raise ValueError(f"--experiment {experiment!r}: no finished trial runs")
    in_trial = []
    steps = 0
    for r in children:
        history = client.get_metric_history(r.info.run_id, "train/cpu_s_per_step")
        in_trial += [m.value for m in history]
        steps += int(max(m.step for m in client.get_metric_history(r.info.run_id, "train/loss")))
    spec_name = children[0].data.tags.get("spec", experiment)
    profile = children[0].data.tags.get("profile", "local")
    plan = expand(load_spec(f"sweeps/{spec_name}.yaml"), profile)
    fixed, isolated = _isolated_steps(plan.cells[0].config)
    spans = [(r.info.start_time / 1000, r.info.end_time / 1000) for r in children]
    wall = max(e for _, e in spans) - min(b for b, _ in spans)
    cpus = cpus or float(os.cpu_count() or 1)
    per_step = cpus * wall / steps
    in_trial_s = statistics.fmean(in_trial)
    return [
        {"benchmark": "CPU per step in a sweep ÷ isolated", "case": f"{spec_name}, {profile}: in-trial train/cpu_s_per_step ÷ one fixed batch alone",
         "without_s": fixed, "with_s": in_trial_s, "ratio": in_trial_s / fixed, "target": "report"},
        {"benchmark": "CPU per step in a sweep ÷ isolated", "case": f"{spec_name}, {profile}: in-trial train/cpu_s_per_step ÷ the run's first batches alone",
         "without_s": isolated, "with_s": in_trial_s, "ratio": in_trial_s / isolated, "target": "<= 1.15"},
        {"benchmark": "CPU per step in a sweep ÷ isolated", "case": f"{spec_name}, {profile}: {cpus:g} CPUs × trial-phase wall ÷ Σ steps",
         "without_s": isolated, "with_s": per_step, "ratio": per_step / isolated, "target": "<= 1.15"},
    ]


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracking-uri", required=True)
    parser.add_argument("--experiment", default="point_size")
    parser.add_argument("--cpus", type=float, default=None)
    args = parser.parse_args()
    for row in sweep_cpu_per_step(args.tracking_uri, args.experiment, args.cpus):
        print(f"| {row['benchmark']} | {row['case']} | {row['without_s']:.4f} | {row['with_s']:.4f} | {row['ratio']:.3f} | {row['target']} |")
