"""What the runner checks and prints before Ray starts: the external inputs, and the dry run's plan,
card and cost estimate.

A dry run with inputs missing still plans (issue 44): it lists them, each with the command that makes
it, prints the plan, the card and the GPU-hours (which read no input), skips only the calibration steps
(they would read the inputs), and ends with exit 2. A real run refuses at the missing input, before Ray.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

from sweeps.plan.describe import describe, wrapped
from sweeps.plan.limits import LISTED_TRIALS
from sweeps.plan.resources import plan_concurrency
from sweeps.plan.schema_base import SpecError
from sweeps.plan.trials import SweepPlan

__all__ = ["UnreadableInput", "check_inputs", "dry_run", "estimate_line"]


class UnreadableInput(ValueError):
    """An input the calibration reads is present but refused (a checkpoint that is no PC² file, NaN weights, an
    unreadable mesh): every trial would fail on it."""


def check_inputs(plan: SweepPlan, remote: bool) -> None:
    """Print which external inputs (weights, maps, embeddings, images) each cell reads and whether they
    exist; refuse absent ones (``ValueError`` naming the field and the command that makes it) before Ray
    starts. On this machine each distinct config's data sets are also indexed to check that every object
    has its entry; a cluster driver may not see the data, so there the trials check it (``cdm.train.Trainer``)."""
    from cdm.data import build_dataset
    from cdm.external_inputs import check_coverage, describe_inputs, required_inputs
    from cdm.external_inputs import check_inputs as check_present

    configs = plan.configs
    names = [c.label for c in plan.cells] or ["every trial"]
    if not any(required_inputs(cfg) for cfg in configs):
        print("external inputs: none (everything is generated or in data.root)", flush=True)
        return
    print(
        "external inputs:\n" + "\n".join(f"  {n}: {describe_inputs(cfg)}" for n, cfg in zip(names, configs)), flush=True
    )
    check_present(*configs)
    covered = set()
    for cfg in configs:
        key = repr(required_inputs(cfg)) + repr(cfg.data)
        if not remote and required_inputs(cfg) and key not in covered:
            covered.add(key)
            check_coverage(cfg, (build_dataset(cfg, "train"), build_dataset(cfg, "val")))


def estimate_line(plan: SweepPlan, cpus: float, concurrent: int, shared: bool):
    """Print the cost estimate (:mod:`sweeps.plan.estimate`) and return it; None when calibration diverged.

    Raises:
        UnreadableInput: an input the calibration reads is refused.
    """
    from cdm.train import TrainingDiverged
    from sweeps.plan.estimate import estimate

    try:
        predicted = estimate(plan, cpus, concurrent, shared)
    except (ValueError, OSError) as exc:
        raise UnreadableInput(f"the cost estimate could not read an input: {' '.join(str(exc).split())}") from None
    except TrainingDiverged as exc:
        print(
            f"estimate: none — the calibration steps diverged ({exc}); the trials will likely fail the same way",
            flush=True,
        )
        return None
    print(wrapped(predicted.text()), flush=True)
    return predicted


def dry_run(plan: SweepPlan, remote: bool, rule: list[str], calibrate: bool, shared: bool, missing: str | None,
            where: Sequence[str] = ()) -> int:
    """Print the plan and the card (``rule``: the until-settled lines), ``where`` (the storage folder and the
    MLflow store a run would write to), the paper profile's GPU-hours and,
    where ``calibrate`` and this machine allow, the calibrated estimate; return the exit code: 2 with one
    ``error:`` line when inputs are ``missing`` (the calibration, which would read them, is skipped) or
    one the calibration reads is refused (a checkpoint that is no PC² file, holds NaN weights, …)."""
    import torch

    cpus, gpus = (None, None) if remote else (os.cpu_count() or 1, torch.cuda.device_count())
    print(describe(plan, cpus, gpus, rule), flush=True)
    if where:
        print(wrapped("\n".join(where)), flush=True)
    if plan.profile.name == "paper":  # measured GPU-hours, or a lower bound said as one; no calibration needed
        from sweeps.plan.estimate import paper_gpu_line

        print(wrapped(paper_gpu_line(plan)), flush=True)
    if missing is not None:
        print("estimate: no calibration steps (they read the missing inputs); a run stops before Ray starts at:",
              flush=True)
        print(f"error: {missing}", file=sys.stderr)
        return 2
    if not calibrate:
        return 0
    if plan.grid_trials is not None:
        print(f"estimate: none for a dry-run of more than {LISTED_TRIALS} trials (it would build every cell again "
              "at the paper profile); calibrate on a smaller grid")
        return 0
    if cpus is None:
        print("estimate: run --dry-run on the cluster's head (without --address) to size it")
        return 0
    try:
        concurrent = plan_concurrency(plan.profile.resources, cpus, gpus, plan.num_trials).max_concurrent
    except SpecError:
        return 0  # describe() has said why this machine cannot run it
    print("calibrating (a few training steps and one evaluation) ...", flush=True)
    try:
        estimate_line(plan, cpus, concurrent, shared)
    except UnreadableInput as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0
