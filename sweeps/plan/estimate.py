"""What a sweep will cost, said before it starts: trials, wall time on this machine, paper-profile GPU-hours.

Local time comes from a short calibration in this process, on one torch thread (how trials run on a small
machine): a few training steps of every distinct cell (up to :data:`CALIBRATED_CELLS`, spread over the grid; a
cell's loss can cost more than its neighbour's, e.g. depth renders against none) and one evaluation per distinct
evaluation cost (:func:`_eval_signature`, at most :data:`EVALUATED_CELLS`). Trials run one thread each; when the
sweep shares its training views and evaluation set (:mod:`sweeps.execute.precompute`), they are rendered once
before the trials, on every CPU, and the trials no longer pay them:

    trial ≈ start-up + set-up + steps × (step [+ batch]) + evaluations × evaluation [− building the set]
    wall  ≈ shared work + ⌈trials ÷ concurrent⌉ × trial       (concurrent ≤ CPUs: waves)
    wall  ≈ shared work + Σ trials ÷ CPUs                     (more trials than CPUs share the cores)

The paper profile's GPU-hours use per-step GPU figures measured by ``benchmarks/gpu_check.py``
(``benchmarks/gpu_costs.json``: the step in the profile's ``train.precision`` where the file has it per
precision); an evaluation samples with the profile's sampler (DDPM: all T steps) and scores every
held-out object under ``eval.protocol: paper`` when ``data.root`` is given (counted), else
``eval.num_objects`` per category. Where no GPU has measured the profile's denoiser, a **lower bound**
stands in: the FLOPs counted in one step (the file's ``flops``, ``torch.utils.flop_counter``) at a named
GPU's dense peak (:data:`BOUND_GPU`, :data:`PEAK_FLOPS`), as if every counted FLOP ran at peak and nothing
else cost time. Estimates assume every cell costs what the calibrated cells cost on average.
"""

from __future__ import annotations

import json
import math
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from cdm.config import Config
from cdm.data import build_dataset, list_categories
from cdm.evaluate import build_eval_set
from cdm.io.json import read_json
from cdm.optim import TrainingDiverged
from cdm.prior_model import ensure_priors
from cdm.train import Trainer
from sweeps.plan.trials import ResolvedProfile, SweepPlan, expand

__all__ = ["BOUND_GPU", "GPU_COSTS", "PEAK_FLOPS", "Estimate", "TrialCost", "asha_share", "calibrate", "estimate",
           "paper_gpu_line", "paper_trial_gpu_hours", "paper_trial_gpu_hours_bound", "peak_flops"]

GPU_COSTS = Path(__file__).resolve().parents[2] / "benchmarks" / "gpu_costs.json"
STARTUP_S = 2.0
"""Seconds per trial outside training in local mode with reused actors (measured with ray 2.60 on 2 CPUs;
benchmarks/RESULTS.md, sweep efficiency)."""
PEAK_FLOPS: dict[str, dict[str, float]] = {
    # Dense (no sparsity) tensor-core peaks, FLOP/s, from NVIDIA's datasheets: "NVIDIA H100 Tensor Core GPU"
    # (SXM: FP16/BF16 1,979 and TF32 989 TFLOPS with sparsity; PCIe 1,513 and 756), "NVIDIA H200 Tensor
    # Core GPU" (as H100 SXM), "NVIDIA A100 Tensor Core GPU" (FP16/BF16 312, TF32 156). fp32 is rated
    # at TF32, which cuDNN's convolutions use by default: the most an fp32 step could reach.
    "H100 PCIe": {"fp16": 756e12, "bf16": 756e12, "fp32": 378e12},
    "H100": {"fp16": 989.4e12, "bf16": 989.4e12, "fp32": 494.7e12},
    "H200": {"fp16": 989.4e12, "bf16": 989.4e12, "fp32": 494.7e12},
    "A100": {"fp16": 312e12, "bf16": 312e12, "fp32": 156e12},
}
"""Dense peak FLOP/s per GPU (matched in the device name, first match, ``H100 PCIe`` before ``H100``) and
``train.precision``."""
BOUND_GPU = "H100"
"""The GPU of the lower bound when no GPU measured: an H100 SXM (``NVIDIA H100 80GB HBM3``)."""
CALIBRATED_CELLS = 8
"""At most this many distinct cells have their set-up and steps timed (evenly spread over the grid)."""
EVALUATED_CELLS = 3
"""At most this many of them are also evaluated; the others take the evaluation time of a calibrated
cell with the same :func:`_eval_signature`, else the mean of those measured."""


@dataclass(frozen=True)
class TrialCost:
    setup_s: float
    """Building the data sets and the model (once per trial)."""
    step_s: float
    """One training step on a ready batch, one thread."""
    eval_s: float
    """One evaluation, building the evaluation set included (a trial builds it once, for its first)."""
    batch_s: float = 0.0
    """Rendering one training batch (the samples of one step)."""
    eval_set_s: float = 0.0
    """Building the evaluation set: held-out views, baselines, retrieval bank."""

    def trial_s(self, steps: int, eval_every: int, shared: bool = False) -> float:
        data = 0.0 if shared else steps * self.batch_s
        # The trainer keeps its evaluation set (cdm.train.Trainer.evaluate): built once, or not at all when shared.
        evals = math.ceil(steps / eval_every) * (self.eval_s - self.eval_set_s) + (0.0 if shared else self.eval_set_s)
        return STARTUP_S + self.setup_s + steps * self.step_s + data + evals


@dataclass(frozen=True)
class Estimate:
    trials: int
    trial_s: float
    concurrent: int
    wall_s: float
    worst_case: bool = False
    """The trials are a sequential sweep's most (every cell at ``max`` seeds); it may stop sooner."""
    gpu_line: str = ""
    """What :func:`paper_gpu_line` says: measured GPU-hours, or the counted-FLOP lower bound, labelled."""
    stopping: str = ""
    """Where a scheduler stops trials early (``asha stops 1 in 2 at step 700``); ``wall_s`` counts every trial
    to its last step."""
    stopped_wall_s: float | None = None
    """The expected wall time when the scheduler stops its share (:func:`asha_share`)."""

    def text(self) -> str:
        return (
            f"estimate: {'worst case, ' if self.worst_case else ''}"
            f"{self.trials} trials × ~{self.trial_s / 60:.1f} min, "
            f"{self.concurrent} at a time → "
            f"~{self.wall_s / 60:.1f} min wall on this machine"
            + (f" if none stops, ~{self.stopped_wall_s / 60:.1f} min if {self.stopping}" if self.stopping else "")
            + f";\n  {self.gpu_line}"
        )


def asha_share(stops: list[float], reduction_factor: float, cost: Callable[[float | None], float]) -> float:
    """A trial's expected cost under ASHA stopping at the steps ``stops`` (each before the last), over its
    cost run to the end: at each rung it goes on with probability 1 / ``reduction_factor`` (Ray's ASHA
    stops a trial below the rung's (1 − 1/rf) quantile of the results judged there before it; the first
    trial at a rung always goes on, so this slightly overstates the saving). ``cost(step)``: a trial ending
    at ``step`` (``stops`` and the last step, ``cost(None)``)."""
    go_on, expected = 1.0, 0.0
    for step in stops:
        expected += go_on * (1.0 - 1.0 / reduction_factor) * cost(step)
        go_on /= reduction_factor
    return (expected + go_on * cost(None)) / cost(None)


def calibrate(config: Config, steps: int = 3, eval_set: bool = True, evaluate: bool = True) -> TrialCost:
    """Time the set-up, ``steps`` training steps (after one warm-up) and, with ``evaluate``, one
    evaluation of ``config`` (else ``eval_s`` is 0); with ``eval_set``, also building its evaluation
    set alone (else ``eval_set_s`` is 0)."""
    with tempfile.TemporaryDirectory() as tmp:
        # A blended cell (sampling.blend.prior_checkpoint: auto) samples with category priors; one-step
        # priors on one object sample as fast as trained ones, and are not part of the timed set-up.
        stub = ensure_priors(config.replace(**{"train.steps": 1, "data.train_objects": 1}), tmp)
        config = config.replace(**{"sampling.blend.prior_checkpoint": stub.sampling.blend.prior_checkpoint})
        start = time.perf_counter()
        trainer = Trainer(config.replace(**{"train.out_dir": tmp, "train.threads": 1}))
        setup_s = time.perf_counter() - start
        trainer.train_step(trainer.next_batch())
        times, batches = [], []
        for _ in range(steps):
            start = time.perf_counter()
            batch = trainer.next_batch()
            batches.append(time.perf_counter() - start)
            start = time.perf_counter()
            trainer.train_step(batch)
            times.append(time.perf_counter() - start)
        start = time.perf_counter()
        if evaluate:
            trainer.evaluate()
        eval_s = time.perf_counter() - start if evaluate else 0.0
        start = time.perf_counter()
        if eval_set:
            build_eval_set(trainer.cfg, trainer.val_set, trainer.train_set, trainer.cfg.eval.seed)
        eval_set_s = time.perf_counter() - start if eval_set else 0.0
        return TrialCost(setup_s, statistics.median(times), eval_s, statistics.median(batches), eval_set_s)


def _eval_signature(cfg: Config) -> str:
    """What an evaluation's cost depends on: every setting but the loss's (``priors``) and the training
    schedule's (of ``train`` only the batch size, which is also the sampling batch)."""
    d = cfg.to_dict()
    kept = {k: v for k, v in d.items() if k not in ("priors", "train")}
    return json.dumps({**kept, "train.batch_size": d["train"]["batch_size"]}, sort_keys=True, default=str)


def _calibration_configs(plan: SweepPlan) -> list[Config]:
    if not plan.cells:  # Optuna: the spec's fixed settings stand for every sampled trial
        return [plan.shared_config(**{"train.seed": plan.spec.seed_values[0]})]
    distinct = list({c.name: c.config for c in plan.cells}.values())
    picks = sorted({round(i * (len(distinct) - 1) / max(1, CALIBRATED_CELLS - 1)) for i in range(CALIBRATED_CELLS)})
    return [distinct[i] for i in picks]


def _sample_steps(cfg: Config) -> int:
    return cfg.diffusion.num_steps if cfg.diffusion.sampler == "ddpm" else cfg.diffusion.sample_steps


def _eval_objects(cfg: Config) -> int:
    """Objects one evaluation scores: every held-out one under ``eval.protocol: paper`` when the data set
    is on disk (counted), else ``eval.num_objects`` per category."""
    if cfg.eval.protocol == "paper" and cfg.data.root is not None:
        # Counted on the data set alone: the external inputs (depth maps, weights) change no count, and a
        # machine planning a cluster run need not hold them.
        return len(
            build_dataset(cfg.replace(**{"priors.prior_2d": "none", "priors.depth_source": "ground_truth"}), "val")
        )
    return cfg.eval.num_objects * len(list_categories(cfg))


def _figures() -> dict:
    """``benchmarks/gpu_costs.json``; a toy check's figures (``quick``) count as none, a CPU's keep only their
    device-independent counted FLOPs (benchmarks/gpu_check.py writes neither there, but a copy could)."""
    figures = read_json(GPU_COSTS, "GPU costs") if GPU_COSTS.is_file() else {}
    if figures.get("quick"):
        return {}
    if figures.get("device") == "CPU":
        return {k: v for k, v in figures.items() if k != "by_points"}
    return figures


def _trial_gpu_hours(paper: SweepPlan, batch: int, train_step: float, sample_step: float, rate: float = 1.0) -> float:
    """GPU-hours of one paper-profile trial whose training step costs ``train_step`` and sampling step
    ``sample_step`` at ``batch`` objects (scaled linearly to the profile's batch), each divided by ``rate``:
    ``steps × train_step + evaluations × ⌈objects ÷ batch⌉ × sampling steps × sample_step``, on every GPU
    the trial holds."""
    cfg, prof, r = paper.configs[0], paper.profile, paper.profile.resources
    scale = cfg.train.batch_size / batch / rate
    evals = math.ceil(prof.steps / prof.eval_every)
    batches = math.ceil(_eval_objects(cfg) / cfg.train.batch_size)
    seconds = prof.steps * train_step * scale + evals * batches * _sample_steps(cfg) * sample_step * scale
    return seconds * max(1, r.workers_per_trial) * max(r.gpus_per_worker, 1.0) / 3600.0


def peak_flops(device_name: str, precision: str) -> float | None:
    """The dense peak FLOP/s of the GPU named ``device_name`` in ``precision`` (:data:`PEAK_FLOPS`); None if unknown."""
    gpu = next((g for g in PEAK_FLOPS if g in device_name), None)
    return PEAK_FLOPS[gpu][precision] if gpu is not None else None


def _measured(figures: dict, cfg: Config) -> tuple[dict, dict] | str:
    """The measured size entry of ``figures`` for ``cfg`` and its step in ``train.precision``, or why none."""
    if not figures.get("by_points"):
        return "no GPU figures"
    if cfg.model.denoiser != figures["denoiser"]:
        return f"not measured for model.denoiser={cfg.model.denoiser} ({GPU_COSTS.name} holds {figures['denoiser']}'s)"
    sizes = sorted(int(n) for n in figures["by_points"])
    # The smallest measured cloud size that holds the config's (else the largest measured).
    entry = figures["by_points"][str(next((n for n in sizes if n >= cfg.data.num_points), sizes[-1]))]
    step = entry.get("by_precision", {}).get(cfg.train.precision, entry)
    if "train_step_s" not in step:
        return f"not measured in train.precision={cfg.train.precision} ({step.get('note', 'absent')})"
    return entry, step


def paper_trial_gpu_hours(paper: SweepPlan, figures: dict | None = None) -> tuple[float | None, str]:
    """GPU-hours of one trial of a spec expanded with the paper profile and the GPU they were measured
    on, or None and why not: no figures, or figures of another denoiser (never another network's time).

    ``figures``: ``benchmarks/gpu_costs.json``'s contents (default: read it). A size's figures hold
    ``train_step_s`` and ``sample_step_s`` directly, or per precision (``by_precision``, the profile's
    ``train.precision`` taken) at ``batch_size`` objects, scaled linearly to the profile's batch.
    """
    figures = _figures() if figures is None else figures
    cfg = paper.configs[0]
    measured = _measured(figures, cfg)
    if isinstance(measured, str):
        return None, measured
    entry, step = measured
    batch = entry.get("batch_size", cfg.train.batch_size)
    return _trial_gpu_hours(paper, batch, step["train_step_s"], step["sample_step_s"]), figures["device"]


def _measured_details(figures: dict, cfg: Config) -> str:
    """What ``benchmarks/gpu_check.py`` measured beside the step time, for the GPU-hours line."""
    entry, step = _measured(figures, cfg)
    parts = [f"training step {step['train_step_s']:.3f} s in {cfg.train.precision} at batch "
             f"{entry.get('batch_size', cfg.train.batch_size)}"]
    if step.get("peak_memory_gib") is not None:
        parts.append(f"peak memory {step['peak_memory_gib']:.1f} GiB")
    if entry.get("largest_batch") is not None:
        parts.append(f"largest batch that fits {entry['largest_batch']}")
    if step.get("sample_batch_s") is not None:
        parts.append(
            f"a batch through 1,000 DDPM steps {step['sample_batch_s']:.0f} s "
            f"({step.get('sample_batch_note', 'measured')})"
        )
    if step.get("flop_fraction") is not None:
        parts.append(f"{100 * step['flop_fraction']:.1f} % of the device's peak FLOP/s")
    return "; ".join(parts)


def paper_trial_gpu_hours_bound(paper: SweepPlan, figures: dict | None = None) -> tuple[float | None, str]:
    """A lower bound on one paper-profile trial's GPU-hours: the counted FLOPs of its training steps and
    sampling steps (``figures["flops"]``, at the counted batch, scaled linearly to the profile's) at
    :data:`BOUND_GPU`'s dense peak in the profile's precision; None and why where nothing is counted."""
    figures = _figures() if figures is None else figures
    cfg = paper.configs[0]
    counted = figures.get("flops", {}).get("by_points", {}).get(str(cfg.data.num_points))
    if counted is None or cfg.model.denoiser != "pvcnn2":
        return None, f"no counted FLOPs for model.denoiser={cfg.model.denoiser} at {cfg.data.num_points} points"
    peak = PEAK_FLOPS[BOUND_GPU][cfg.train.precision]
    hours = _trial_gpu_hours(paper, counted["batch_size"], counted["train_step"], counted["sample_step"], peak)
    return hours, f"{BOUND_GPU} SXM dense {cfg.train.precision} peak, {peak / 1e12:g} TFLOP/s"


def paper_gpu_line(paper: SweepPlan, figures: dict | None = None) -> str:
    """What the dry run and the estimate say of the paper profile's GPU-hours for ``paper``'s trials:
    measured (with the step, memory, largest batch, sampling cost and FLOP/s share beside), else a
    lower bound labelled as one. ``figures``: as :func:`paper_trial_gpu_hours`."""
    figures = _figures() if figures is None else figures
    hours, gpu = paper_trial_gpu_hours(paper, figures)
    if hours is not None:
        return (f"{hours * paper.num_trials:.1f} GPU-hours with the paper profile ({hours:.2f} per trial × "
                f"{paper.num_trials} trials, measured on {gpu}: {_measured_details(figures, paper.configs[0])})")
    line = f"paper-profile GPU-hours: {gpu} (on a GPU: python benchmarks/gpu_check.py)"
    bound, basis = paper_trial_gpu_hours_bound(paper, figures)
    if bound is None:
        return f"{line}; no lower bound: {basis}"
    return (
        f"{line}; lower bound, not a measurement: ≥ {bound * paper.num_trials:.2f} GPU-hours ({bound:.3f} per trial "
        f"× {paper.num_trials}) if every counted FLOP ran at the {basis} and nothing else took time"
    )


def _budget_steps(cost: TrialCost, prof: ResolvedProfile, spent: float | None = None) -> int:
    """The steps a trial of ``cost`` takes within the profile's budget (to ``spent``, in its unit, if given): a
    budget in compute buys ``compute_s / step_s`` steps (``step_s`` is one thread's, so CPU seconds), at most
    ``steps``."""
    if prof.compute_s is None:
        return int(spent or prof.steps)
    return max(1, min(prof.steps, math.ceil((spent or prof.compute_s) / cost.step_s)))


def _trial_s(cost: TrialCost, prof: ResolvedProfile, shared: bool, spent: float | None = None) -> float:
    """A trial's seconds under the profile's budget, or stopped at ``spent`` (a rung in the budget's unit)."""
    every = prof.eval_every if prof.compute_s is None else _budget_steps(cost, prof, prof.time_axis[2])
    return cost.trial_s(_budget_steps(cost, prof, spent), every, shared)


def estimate(plan: SweepPlan, cpus: float, concurrent: int, shared: bool = False) -> Estimate:
    """Calibrate on this machine and estimate the sweep's wall time and paper-profile GPU-hours.

    ``shared``: the sweep renders its cells' training views and evaluation sets once (:mod:`sweeps.execute.precompute`).

    Raises:
        TrainingDiverged: every calibrated cell diverged in its first steps (the sweep's trials will
            fail the same way and say so; the caller reports the estimate as unavailable).
    """
    costs, diverged = [], None
    evaluated: dict[str, float] = {}
    unevaluated: list[tuple[int, str]] = []
    for cfg in _calibration_configs(plan):
        signature = _eval_signature(cfg)
        evaluate = signature not in evaluated and len(evaluated) < EVALUATED_CELLS
        try:
            # The cells of a sweep share one evaluation set as a rule: building it is timed once.
            cost = calibrate(cfg, eval_set=not costs, evaluate=evaluate)
        except TrainingDiverged as exc:  # a cell meant to diverge (a test of failure handling, a bad lr)
            diverged = exc
            continue
        if evaluate:
            evaluated[signature] = cost.eval_s
        else:
            unevaluated.append((len(costs), signature))
        costs.append(cost)
    if not costs:
        raise diverged
    for i, signature in unevaluated:
        costs[i] = replace(costs[i], eval_s=evaluated.get(signature, statistics.fmean(evaluated.values())))
    prof = plan.profile
    costs = [replace(c, eval_set_s=costs[0].eval_set_s) for c in costs]
    steps = max(_budget_steps(c, prof) for c in costs)
    trial_s = statistics.fmean(_trial_s(c, prof, shared) for c in costs)
    lanes = max(1.0, min(float(concurrent), cpus))
    if concurrent <= cpus:
        trials_wall = math.ceil(plan.num_trials / max(1, concurrent)) * trial_s
    else:
        trials_wall = plan.num_trials * trial_s / lanes
    shared_s = 0.0
    if shared and plan.cells:
        cost = statistics.fmean(c.batch_s for c in costs)
        eval_set = costs[0].eval_set_s
        world = max(1, plan.profile.resources.workers_per_trial)
        # One view set and one evaluation set per distinct data (the usual sweep varies the model or
        # loss, not the data): the batches of the longest run, spread over the CPUs.
        shared_s = (steps * world * cost + eval_set) / max(1.0, cpus)
    paper = expand(plan.spec, "paper", plan.sets)
    sch = plan.spec.scheduler
    stopping, stopped = "", None
    if stops := sch.stops(*prof.time_axis[1:]):
        share = asha_share(stops, sch.reduction_factor,
                           lambda at: statistics.fmean(_trial_s(c, prof, shared, at) for c in costs))
        at, unit = ("step ", "") if prof.compute_s is None else ("", " s of compute")
        stopping = f"{sch.kind} stops 1 in {sch.reduction_factor:g} at {at}{', '.join(f'{s:g}' for s in stops)}{unit}"
        stopped = shared_s + trials_wall * share
    return Estimate(plan.num_trials, trial_s, concurrent, shared_s + trials_wall, plan.sequential is not None,
                    paper_gpu_line(paper), stopping, stopped)
