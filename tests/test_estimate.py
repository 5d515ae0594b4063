"""Sweep cost estimate: the arithmetic of trial and wall time, and paper GPU-hours from the GPU figures."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from sweeps.plan.estimate import (
    GPU_COSTS,
    STARTUP_S,
    Estimate,
    TrialCost,
    _calibration_configs,
    _eval_signature,
    asha_share,
    calibrate,
    estimate,
    paper_gpu_line,
    paper_trial_gpu_hours,
    paper_trial_gpu_hours_bound,
    peak_flops,
)
from sweeps.plan.spec import load_spec
from sweeps.plan.trials import expand

SWEEPS = Path(__file__).resolve().parent.parent / "sweeps"


def test_trial_time_counts_steps_and_every_evaluation():
    cost = TrialCost(setup_s=3.0, step_s=0.5, eval_s=10.0)
    assert cost.trial_s(steps=800, eval_every=400) == STARTUP_S + 3.0 + 400.0 + 20.0
    assert cost.trial_s(steps=20, eval_every=15) == STARTUP_S + 3.0 + 10.0 + 20.0  # evaluates at 15 and at the end


def test_shared_work_leaves_the_trial_and_waves_round_up():
    cost = TrialCost(setup_s=3.0, step_s=0.5, eval_s=10.0, batch_s=0.1, eval_set_s=4.0)
    # Two evaluations, the evaluation set built for the first only (the trainer keeps it): 10 + (10 − 4).
    assert cost.trial_s(steps=800, eval_every=400) == STARTUP_S + 3.0 + 400.0 + 80.0 + 16.0
    # With the shared store the trial renders no batch and builds no evaluation set.
    assert cost.trial_s(steps=800, eval_every=400, shared=True) == STARTUP_S + 3.0 + 400.0 + 16.0 - 4.0
    plan = expand(load_spec(SWEEPS / "point_size.yaml"), "smoke")
    waves = estimate(plan, cpus=2, concurrent=2)
    assert waves.wall_s == pytest.approx(3 * waves.trial_s)  # 5 trials, 2 at a time: 3 waves
    shared = estimate(plan, cpus=2, concurrent=2, shared=True)
    assert shared.wall_s > 3 * shared.trial_s  # plus the shared work, once, before the trials


def test_paper_gpu_hours_follow_the_measured_figures():
    figures = json.loads(GPU_COSTS.read_text())
    plan = expand(load_spec(SWEEPS / "shapenet.yaml"), "local")
    hours, why = paper_trial_gpu_hours(expand(plan.spec, "paper"))  # PC²'s PVCNN2: no GPU figures yet
    assert (
        hours is None
        and why == f"not measured for model.denoiser=pvcnn2 (gpu_costs.json holds {figures['denoiser']}'s)"
    )
    measured = {"model.denoiser": figures["denoiser"]}
    hours, device = paper_trial_gpu_hours(expand(plan.spec, "paper", measured))
    cfg = expand(plan.spec, "paper", measured).cells[0].config
    evals = 100_000 // 5_000
    batches = math.ceil(cfg.eval.num_objects * 1 / 8)  # one category per cell, batch 8
    step = figures["by_points"]["4096"]  # the paper profile's ShapeNet size
    assert cfg.diffusion.sampler == "ddpm"  # PC²'s sampler: every one of the 1,000 steps per evaluation
    per_trial = 100_000 * step["train_step_s"] + evals * batches * 1000 * step["sample_step_s"]
    assert hours == pytest.approx(per_trial / 3600)
    assert device == figures["device"]


def test_calibration_and_wall_time_on_this_machine():
    plan = expand(load_spec(SWEEPS / "point_size.yaml"), "smoke")
    cost = calibrate(plan.cells[0].config)
    assert 0 < cost.step_s < cost.eval_s and cost.setup_s > 0
    est = estimate(plan, cpus=2, concurrent=5)
    assert est.trials == 5 and est.concurrent == 5
    assert est.wall_s == pytest.approx(5 * est.trial_s / 2)  # five one-thread trials share two cores


def test_every_cell_of_a_small_grid_is_calibrated_and_evaluations_are_timed_once_per_cost():
    """A grid's cells can differ in step cost (the priors sweep: depth renders or none), so every distinct
    cell's steps are timed; evaluation costs depend on the sampler and model, not the loss."""
    point_size = expand(load_spec(SWEEPS / "point_size.yaml"), "local")
    assert [c.priors.point_size for c in _calibration_configs(point_size)] == [
        c.config.priors.point_size for c in point_size.cells
    ]
    assert len({_eval_signature(c.config) for c in point_size.cells}) == 1  # point size is the loss's
    priors = expand(load_spec(SWEEPS / "priors_2d_3d.yaml"), "local")
    assert len({_eval_signature(c.config) for c in priors.cells}) == 1
    prediction = expand(load_spec(SWEEPS / "prediction.yaml"), "local")
    assert len({_eval_signature(c.config) for c in prediction.cells}) == len(
        prediction.cells
    )  # the target is the model's
    bigger = point_size.cells[0].config.replace(**{"train.batch_size": 8})  # also the sampling batch
    assert _eval_signature(bigger) != _eval_signature(point_size.cells[0].config)
    assert _eval_signature(point_size.cells[0].config.replace(**{"train.lr": 3e-3})) == _eval_signature(
        point_size.cells[0].config
    )


def test_a_cell_calibrated_without_evaluation_times_no_evaluation():
    plan = expand(load_spec(SWEEPS / "point_size.yaml"), "smoke")
    cost = calibrate(plan.cells[1].config, eval_set=False, evaluate=False)
    assert cost.eval_s == 0.0 and cost.eval_set_s == 0.0 and cost.step_s > 0


def _pvcnn2_figures(**flops) -> dict:
    """gpu_costs.json as benchmarks/gpu_check.py writes it: per size and precision, and counted FLOPs."""
    sizes = {"4096": {"batch_size": 16, "by_precision": {
        "fp32": {"train_step_s": 0.4, "sample_step_s": 0.1},
        "fp16": {"train_step_s": 0.2, "sample_step_s": 0.05},
        "bf16": {"note": "not measured"}}}}
    return {"device": "NVIDIA H100 80GB HBM3", "denoiser": "pvcnn2", "by_points": sizes,
            "flops": {"by_points": {"4096": {"train_step": 4e12, "sample_step": 1e12, "batch_size": 8}, **flops}}}


def test_measured_pvcnn2_figures_are_read_in_the_profiles_precision_scaled_to_its_batch():
    paper = expand(load_spec(SWEEPS / "shapenet.yaml"), "paper")  # the procedural stand-in: PC²'s batch 8
    cfg = paper.cells[0].config
    assert (cfg.train.precision, cfg.train.batch_size, cfg.data.num_points) == ("fp16", 8, 4096)
    hours, device = paper_trial_gpu_hours(paper, _pvcnn2_figures())
    batches = math.ceil(cfg.eval.num_objects / 8)
    # measured at batch 16: the profile's batch 8 is taken as half of it, linearly
    assert hours == pytest.approx((100_000 * 0.1 + 20 * batches * 1000 * 0.025) / 3600) and device.startswith(
        "NVIDIA H100"
    )
    fp32 = expand(load_spec(SWEEPS / "shapenet.yaml"), "paper", {"train.precision": "fp32", "train.batch_size": 16})
    hours, _ = paper_trial_gpu_hours(fp32, _pvcnn2_figures())
    assert hours == pytest.approx((100_000 * 0.4 + 20 * math.ceil(cfg.eval.num_objects / 16) * 1000 * 0.1) / 3600)
    bf16 = expand(load_spec(SWEEPS / "shapenet.yaml"), "paper", {"train.precision": "bf16"})
    assert paper_trial_gpu_hours(bf16, _pvcnn2_figures()) == (
        None,
        "not measured in train.precision=bf16 (not measured)",
    )


def test_without_a_measurement_the_bound_is_counted_flops_at_an_h100s_peak():
    paper = expand(load_spec(SWEEPS / "shapenet.yaml"), "paper", {"train.batch_size": 16})
    cfg = paper.cells[0].config
    bound, basis = paper_trial_gpu_hours_bound(paper, _pvcnn2_figures())
    flops = 100_000 * 4e12 * 2 + 20 * math.ceil(cfg.eval.num_objects / 16) * 1000 * 1e12 * 2  # batch 16 = 2 × counted 8
    assert bound == pytest.approx(flops / 989.4e12 / 3600)
    assert basis == "H100 SXM dense fp16 peak, 989.4 TFLOP/s"
    fp32, _ = paper_trial_gpu_hours_bound(
        expand(paper.spec, "paper", {"train.batch_size": 16, "train.precision": "fp32"}), _pvcnn2_figures()
    )
    assert fp32 == pytest.approx(bound * 2)  # TF32's dense peak is half fp16's
    assert peak_flops("NVIDIA H100 PCIe", "fp16") == 756e12 and peak_flops("NVIDIA A100-SXM4-80GB", "bf16") == 312e12
    assert peak_flops("CPU", "fp32") is None
    co3d = expand(load_spec(SWEEPS / "co3d.yaml"), "paper", {"data.num_points": 16384})
    assert paper_trial_gpu_hours_bound(co3d, _pvcnn2_figures()) == (
        None,
        "no counted FLOPs for model.denoiser=pvcnn2 at 16384 points",
    )


def test_the_shipped_figures_give_the_paper_profile_a_labelled_bound():
    """benchmarks/gpu_costs.json holds no pvcnn2 GPU step yet, only its counted FLOPs: the line says so."""
    paper = expand(load_spec(SWEEPS / "shapenet.yaml"), "paper")
    line = paper_gpu_line(paper)
    assert line.startswith("paper-profile GPU-hours: not measured for model.denoiser=pvcnn2")
    assert "lower bound, not a measurement: ≥ " in line and "H100 SXM dense fp16 peak, 989.4 TFLOP/s" in line
    bound, _ = paper_trial_gpu_hours_bound(paper)
    assert f"({bound:.3f} per trial × {paper.num_trials})" in line


@pytest.mark.parametrize("device, quick, left", [
    ("CPU", True, set()),  # a toy check: nothing of it is read
    ("CPU", False, {"device", "denoiser", "flops", "quick"}),  # a CPU's: only its counted FLOPs (any device's)
    ("NVIDIA H100 80GB HBM3", True, set()),
])
def test_a_cpu_or_toy_checks_figures_are_never_read_as_a_devices(tmp_path, monkeypatch, device, quick, left):
    from sweeps.plan import estimate

    figures = {**_pvcnn2_figures(), "device": device, "quick": quick}
    monkeypatch.setattr(estimate, "GPU_COSTS", tmp_path / "gpu_costs.json")
    estimate.GPU_COSTS.write_text(json.dumps(figures))
    read = estimate._figures()
    assert set(read) == left and "by_points" not in read
    paper = expand(load_spec(SWEEPS / "shapenet.yaml"), "paper")
    assert paper_trial_gpu_hours(paper, read) == (None, "no GPU figures")
    assert paper_trial_gpu_hours(paper, {**figures, "quick": False, "device": "NVIDIA H100 80GB HBM3"})[0] > 0


def test_measured_figures_are_printed_with_what_gpu_check_measured_beside_them():
    figures = _pvcnn2_figures()
    figures["by_points"]["4096"].update(largest_batch=64)
    figures["by_points"]["4096"]["by_precision"]["fp16"].update(
        peak_memory_gib=21.04, sample_batch_s=51.2, sample_batch_note="extrapolated: 20 timed sampler steps × 1000/20",
        flop_fraction=0.123)
    paper = expand(load_spec(SWEEPS / "shapenet.yaml"), "paper")
    hours, _ = paper_trial_gpu_hours(paper, figures)
    line = paper_gpu_line(paper, figures)
    assert line == (f"{hours * paper.num_trials:.1f} GPU-hours with the paper profile ({hours:.2f} per trial × "
                    f"{paper.num_trials} trials, measured on NVIDIA H100 80GB HBM3: training step 0.200 s in fp16 at "
                    "batch 16; peak memory 21.0 GiB; largest batch that fits 64; a batch through 1,000 DDPM steps 51 s "
                    "(extrapolated: 20 timed sampler steps × 1000/20); 12.3 % of the device's peak FLOP/s)")


def test_the_estimate_says_the_wall_time_when_asha_stops_its_share():
    # Half the trials stop at step 700 of 1400 (reduction factor 2): a trial costs on average halfway between.
    cost = {700: 100.0, None: 180.0}.__getitem__
    assert asha_share([700], 2.0, cost) == pytest.approx((0.5 * 100 + 0.5 * 180) / 180)
    # Rungs at 10 and 30 of 90, factor 3: 2/3 stop at 10, 2/9 at 30, 1/9 run to the end.
    cost = {10: 10.0, 30: 30.0, None: 90.0}.__getitem__
    assert asha_share([10, 30], 3.0, cost) == pytest.approx((2 / 3 * 10 + 2 / 9 * 30 + 1 / 9 * 90) / 90)
    text = Estimate(8, 240.0, 5, 960.0, stopping="asha stops 1 in 2 at step 700", stopped_wall_s=720.0).text()
    assert text.startswith("estimate: 8 trials × ~4.0 min, 5 at a time → ~16.0 min wall on this machine if none "
                           "stops, ~12.0 min if asha stops 1 in 2 at step 700;")
    # Calibrated: the λ search's smoke profile (20 steps, evaluations at 10 and 20) lets ASHA stop at step 10.
    est = estimate(expand(load_spec(SWEEPS / "lambda.yaml"), "smoke"), cpus=2, concurrent=2)
    assert est.stopping == "asha stops 1 in 2 at step 10" and 0 < est.stopped_wall_s < est.wall_s
