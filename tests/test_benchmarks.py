"""The benchmark entry point runs and writes its rows (timings themselves are never asserted)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_metrics_benchmark_runs_and_agrees_with_scipy(tmp_path):
    out = subprocess.run(
        [sys.executable, "benchmarks/run.py", "--quick", "--only", "metrics", "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    rows = json.loads((tmp_path / "results.json").read_text())
    assert {r["benchmark"] for r in rows} == {"chamfer_f1 (kdtree) vs scipy cKDTree", "chamfer_f1 (brute) vs scipy cKDTree"}
    assert all(r["max_abs_cd_diff"] < 1e-3 for r in rows)  # CD×1000 ~ 20: float32 rounding only
    assert "| chamfer_f1 (kdtree) vs scipy cKDTree | B=8, 4096x4096 |" in out.stdout
