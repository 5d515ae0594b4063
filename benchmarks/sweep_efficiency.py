"""Sweep efficiency on this machine: 6 identical short trials of the smoke profile through the real runner.

The runner packs trials in Train's local mode with reused actors (sweeps/execute/trial.py): one per CPU at a
time (on 2 CPUs, two). From the MLflow child runs (start = the trial opens its run, end = the driver closes it):

- efficiency = Σ in-trial time ÷ (concurrent trials × wall of the trial phase); target ≥ 0.8;
- gap per trial = (concurrent trials × wall − Σ in-trial time) ÷ trials: scheduling, actor reuse and
  result handling between trials; target ≤ 5 s;
- in-trial overhead = in-trial time − training-loop time (data and model set-up, last evaluation,
  checkpoint, tracking), reported.

A Train worker group per trial (workers_per_trial ≥ 1, what multi-GPU trials need) adds 12–25 s per
trial here (benchmarks/RESULTS.md, trade-off of target (5)); that is why small machines use local mode.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

from mlflow import MlflowClient

from sweeps.plan.resources import plan_concurrency
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand

__all__ = ["sweep_efficiency"]

SPEC = """name: efficiency
grid: {priors.point_size: [0.04]}
seeds: [0, 1, 2, 3, 4, 5]
profiles:
  smoke: {budget: {steps: %d, eval_every: %d}}
"""


def sweep_efficiency(quick: bool, out_dir: str) -> list[dict]:
    from sweeps import run

    steps = 40 if quick else 120
    with tempfile.TemporaryDirectory() as tmp:
        spec = Path(tmp) / "efficiency.yaml"
        spec.write_text(SPEC % (steps, steps))
        smoke = expand(load_spec(spec), "smoke")
        uri = f"sqlite:///{tmp}/mlflow.db"
        start = time.perf_counter()
        code = run.main([str(spec), "--smoke", "--out", f"{tmp}/results", "--tracking-uri", uri])
        total = time.perf_counter() - start
        if code != 0:
            raise RuntimeError(f"the efficiency sweep failed (exit {code})")
        client = MlflowClient(uri)
        exp = client.get_experiment_by_name("efficiency")
        children = [r for r in client.search_runs([exp.experiment_id]) if "mlflow.parentRunId" in r.data.tags]
    spans = [(r.info.start_time / 1000, r.info.end_time / 1000) for r in children]
    in_trial = [end - begin for begin, end in spans]
    loop = [r.data.metrics["train/elapsed_s"] for r in children]
    wall = max(e for _, e in spans) - min(b for b, _ in spans)
    # Lanes = how many trials the runner lets run at once on this machine (its own sizing rule).
    lanes = plan_concurrency(smoke.profile.resources, float(os.cpu_count() or 1), 0.0, smoke.num_trials).max_concurrent
    busy = sum(in_trial)
    return [
        {"benchmark": "sweep efficiency", "case": f"6 trials × {steps} steps, smoke, {lanes} at a time, local mode",
         "without_s": busy / lanes, "with_s": wall, "ratio": busy / (lanes * wall), "target": ">= 0.8"},
        {"benchmark": "sweep gap per trial", "case": "scheduling + actor reuse + result handling",
         "without_s": (lanes * wall - busy) / len(spans), "with_s": (lanes * wall - busy) / len(spans),
         "ratio": (lanes * wall - busy) / len(spans) / 5.0, "target": "<= 1.0 (gap / 5 s)"},
        {"benchmark": "in-trial overhead", "case": "set-up + last evaluation + checkpoint + tracking, per trial",
         "without_s": statistics.fmean(loop), "with_s": statistics.fmean(in_trial),
         "ratio": statistics.fmean(in_trial) / statistics.fmean(loop), "target": "report (in-trial / loop)"},
        {"benchmark": "sweep fixed cost", "case": "Ray start, calibration, table (once per sweep)",
         "without_s": total - wall, "with_s": total, "ratio": (total - wall) / total, "target": "report"},
    ]
