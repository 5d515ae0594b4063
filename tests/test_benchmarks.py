"""The benchmark entry point runs and writes its rows (timings themselves are never asserted)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_metrics_benchmark_runs_and_agrees_with_scipy(tmp_path):
    out = subprocess.run(
        [sys.executable, "benchmarks/run.py", "--quick", "--only", "metrics", "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    rows = json.loads((tmp_path / "results.json").read_text())
    assert {r["benchmark"] for r in rows} == {
        "chamfer_f1 (kdtree) vs scipy cKDTree",
        "chamfer_f1 (brute) vs scipy cKDTree",
    }
    assert all(r["max_abs_cd_diff"] < 1e-3 for r in rows)  # CD×1000 ~ 20: float32 rounding only
    assert "| chamfer_f1 (kdtree) vs scipy cKDTree | B=8, 4096x4096 |" in out.stdout


def test_growth_exponent_recovers_a_known_power_law():
    from benchmarks.render import growth_exponent

    points = [1024, 4096, 16384]
    assert growth_exponent(points, [3e-6 * n for n in points]) == pytest.approx(1.0)
    assert growth_exponent(points, [1e-9 * n**2 for n in points]) == pytest.approx(2.0)


def test_rendering_and_paper_scaling_rows(tmp_path):
    out = subprocess.run(
        [sys.executable, "benchmarks/run.py", "--quick", "--only", "render", "paper_scaling", "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    rows = json.loads((tmp_path / "results.json").read_text())
    growth = {r["benchmark"] for r in rows if r["benchmark"].endswith("growth")}
    assert growth == {"render: rasterize growth", "render: splat growth"}
    scaling = {r["spec"]: r for r in rows if r["benchmark"] == "paper scaling"}
    point_size = scaling["point_size"]
    assert point_size["trials"] == 5
    # The paper profile trains PC²'s PVCNN2, whose GPU step no session has measured: no stale figure.
    assert point_size["trial_gpu_hours"] is None and point_size["wall_h_8_gpus"] is None
    assert point_size["device"].startswith("not measured for model.denoiser=pvcnn2")
    assert "| point_size | 5 | not measured | not measured |" in out.stdout


def test_median_s_warms_up_untimed_and_brackets_each_timed_call_with_sync():
    from benchmarks.common import median_s

    events = []
    seconds = median_s(lambda: events.append("call"), repeats=3, warmup=2, sync=lambda: events.append("sync"))
    assert events == ["call", "call"] + ["sync", "call", "sync"] * 3
    assert 0 <= seconds < 1


def test_median_s_reads_the_clock_it_is_given():
    from benchmarks.common import median_s

    ticks = iter(range(100))
    # Each timed call spans one tick of this clock (read before and after): the median is 1.
    assert median_s(lambda: None, repeats=4, clock=lambda: float(next(ticks))) == 1.0


COMMITTED_COSTS = ROOT / "benchmarks" / "gpu_costs.json"


@pytest.mark.slow  # PC²'s PVCNN2 at toy scale, three sizes × precisions on one CPU: ~1-2 min
def test_gpu_check_runs_at_toy_scale_on_cpu_and_writes_every_figure(tmp_path):
    committed = COMMITTED_COSTS.read_bytes()
    out = tmp_path / "gpu_costs.json"
    run = subprocess.run([sys.executable, "benchmarks/gpu_check.py", "--device", "cpu", "--quick", "--out", str(out)],
                         cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr
    assert COMMITTED_COSTS.read_bytes() == committed
    figures = json.loads(out.read_text())
    assert figures["device"] == "CPU" and figures["denoiser"] == "pvcnn2" and figures["quick"] is True
    assert set(figures["by_points"]) == {"256", "64"}  # Co3D's 16,384 and ShapeNet's 4,096 points, ÷ 64
    for n, entry in figures["by_points"].items():
        assert entry["size"] == {"256": "co3d", "64": "shapenet"}[n] and entry["batch_size"] == 2
        assert entry["by_precision"]["fp16"] == {"note": "fp16 needs CUDA"}
        for precision in ("fp32", "bf16"):
            row = entry["by_precision"][precision]
            assert 0 < row["sample_step_s"] and 0 < row["train_step_s"]
            assert row["sample_batch_s"] > row["sample_step_s"]  # 1,000 steps, extrapolated from 2 timed ones
            assert row["sample_batch_note"] == "extrapolated: 2 timed sampler steps × 1000/2"
            assert row["peak_memory_gib"] is None and row["flop_fraction"] is None  # CUDA only; no CPU peak
        assert entry["largest_batch"] is None and entry["largest_batch_note"] == "CUDA only"
        counted = figures["flops"]["by_points"][n]
        assert counted["train_step"] > 2 * counted["sample_step"] > 0  # forward and backward against forward
    # the paper profile trains in fp16, which a CPU does not run: no GPU-hours, and why
    assert figures["trial_gpu_hours"] == {"co3d.yaml": "not measured in train.precision=fp16 (fp16 needs CUDA)",
                                          "shapenet.yaml": "not measured in train.precision=fp16 (fp16 needs CUDA)"}


def test_only_a_device_check_at_paper_scale_writes_the_committed_table_by_default():
    import argparse

    from benchmarks.gpu_check import TOY_COSTS, _out_path

    def out(*argv: str):
        args = argparse.Namespace(device="cuda", quick=False, count_flops=False, out=None)
        for flag in argv:
            key, _, value = flag.partition("=")
            setattr(args, key, value or True)
        return _out_path(args)

    assert out() == COMMITTED_COSTS
    assert out("count_flops", "device=cpu") == COMMITTED_COSTS  # counted FLOPs: the same on any device
    assert out("device=cpu", "quick") == TOY_COSTS and TOY_COSTS.parent.name == "out"
    assert out("device=cpu") == TOY_COSTS and out("quick") == TOY_COSTS and out("count_flops", "quick") == TOY_COSTS
    assert out("device=cpu", "quick", "out=/tmp/x.json").as_posix() == "/tmp/x.json"


@pytest.mark.slow  # a fresh interpreter importing torch and the library: ~6 s on a busy 2-CPU machine
@pytest.mark.parametrize("via_link", [False, True])
def test_a_cpu_or_toy_check_refuses_to_replace_the_device_figures(tmp_path, via_link):
    committed = COMMITTED_COSTS.read_bytes()
    target = tmp_path / "costs.json" if via_link else COMMITTED_COSTS
    if via_link:
        target.symlink_to(COMMITTED_COSTS)
    argv = ["benchmarks/gpu_check.py", "--device", "cpu", "--quick", "--out", str(target)]
    run = subprocess.run([sys.executable, *argv], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and run.stderr.startswith(f"error: --out {target}: a --quick check does not replace")
    assert "benchmarks/out/gpu_costs.json" in run.stderr and len(run.stderr.strip().splitlines()) == 1
    assert COMMITTED_COSTS.read_bytes() == committed


@pytest.mark.slow  # a fresh interpreter importing torch and the library: ~6 s on a busy 2-CPU machine
def test_gpu_check_on_a_machine_without_cuda_says_so_and_writes_nothing(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA: the default device runs")
    out = tmp_path / "gpu_costs.json"
    run = subprocess.run([sys.executable, "benchmarks/gpu_check.py", "--out", str(out)], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 2 and run.stderr.startswith("error: --device cuda: no CUDA device here")
    assert len(run.stderr.strip().splitlines()) == 1 and not out.exists()


@pytest.mark.slow
def test_lean_step_benchmark_times_both_trees_and_finds_them_equal(tmp_path):
    from benchmarks.lean_step import BASE, TOLERANCE

    if subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", BASE], capture_output=True).returncode != 0:
        pytest.skip(f"this clone has no {BASE} to compare with")
    out = subprocess.run(
        [sys.executable, "benchmarks/run.py", "--quick", "--only", "lean_step", "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )
    assert out.returncode == 0, out.stderr
    timing, ops, equality = json.loads((tmp_path / "results.json").read_text())
    assert timing["benchmark"] == "lean step" and timing["without_s"] > 0 and timing["with_s"] > 0
    assert 0 < ops["with_s"] < ops["without_s"]  # fewer top-level ops: deterministic, unlike the times
    assert abs(equality["with_s"] - equality["without_s"]) <= TOLERANCE * equality["without_s"]
    assert equality["max_grad_diff"] <= TOLERANCE and equality["ratio"] <= 1
    assert "| lean step | local step: quick.yaml" in out.stdout


def test_lean_step_refuses_a_round_count_below_one():
    out = subprocess.run([sys.executable, "benchmarks/lean_step.py", "--rounds", "0"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.strip() == "error: --rounds must be >= 1, got 0"


def test_cpu_modes_train_each_mode_in_its_own_process_with_its_pins():
    from benchmarks.cpu_modes import cpu_modes
    from cdm.provenance import machine_record

    rows = cpu_modes(steps=1, rounds=1)
    assert [r["case"].split(" (")[0] for r in rows] == ["avx2", "portable"]
    assert "(MKL_CBWR=COMPATIBLE ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2; ATen " in rows[1]["case"]
    if "avx2" in machine_record()["cpu_isa"].split():  # the pin took: ATen dispatches to AVX2 in the child
        assert all("; ATen AVX2 against " in r["case"] for r in rows)
    assert all(r["with_s"] > 0 and r["without_s"] > 0 and r["ratio"] > 0 for r in rows)


def test_kornia_ops_rows_name_each_comparison_and_agree_in_value():
    """``benchmarks/kornia_ops.py --quick``: OpenCV's distance transform, kornia's projection,
    footprint filter and erosion give our values (float rounding); kornia's Canny is another detector."""
    from benchmarks.kornia_ops import kornia_ops

    rows = {r["benchmark"]: r for r in kornia_ops(quick=True, out_dir="")}
    assert len(rows) == 6
    difference = {name: float(r["case"].rpartition("max |a − b| ")[2]) for name, r in rows.items()}
    assert difference["mask distance transform: torch O(S³) vs OpenCV"] < 1e-6
    assert difference["camera projection: ours vs kornia"] < 1e-5
    assert difference["splat footprint filter: ours vs kornia filter2d"] < 1e-4
    assert difference["front-layer window minimum: -max_pool2d(-z) vs kornia erosion"] == 0.0
    assert 0.0 < difference["contour prior: OpenCV Canny vs kornia canny"] < 0.5
    assert all(r["without_s"] > 0 and r["with_s"] > 0 and r["ratio"] > 0 for r in rows.values())
