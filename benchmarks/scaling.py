"""Paper-scale cost of every shipped spec on 1, 8 and 64 GPUs, from the measured GPU step costs.

Per trial: the paper profile's steps × the training-step time plus its evaluations × batches ×
sampling steps × the sampling-step time (``benchmarks/gpu_costs.json``, measured by the throughput
benchmark on CUDA). Assumptions: one GPU per trial (the paper profile), trials of a spec cost alike,
trials run in waves of ``GPUs`` (no trial spans GPUs), data loading keeps up with the GPU (loader
workers decode ahead), and no time between trials. ASHA-stopped trials would shorten Optuna sweeps;
not counted.
"""

from __future__ import annotations

import math
from pathlib import Path

from sweeps.plan.estimate import paper_trial_gpu_hours
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand

__all__ = ["GPUS", "paper_scaling"]

GPUS = (1, 8, 64)
SPECS = Path(__file__).resolve().parents[1] / "sweeps"


def paper_scaling(quick: bool, out_dir: str) -> list[dict]:
    rows = []
    for path in sorted(SPECS.glob("*.yaml")):
        if path.name == "profiles.yaml":
            continue
        plan = expand(load_spec(path), "paper")
        per_trial, device = paper_trial_gpu_hours(plan)  # None: not measured, and ``device`` says why
        hours = {g: None if per_trial is None else math.ceil(plan.num_trials / g) * per_trial for g in GPUS}
        rows.append(
            {
                "benchmark": "paper scaling",
                "spec": path.stem,
                "trials": plan.num_trials,
                "trial_gpu_hours": per_trial,
                "device": device,
                **{f"wall_h_{g}_gpus": h for g, h in hours.items()},
            }
        )
    return rows
