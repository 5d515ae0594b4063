"""Peak memory (RSS) of training steps, dense vs sparse voxel back-end, at paper widths on CPU.

Each variant runs in its own process (peak RSS is per process and never goes down), takes three
training steps at B=8, and reports ``VmHWM`` from ``/proc/self/status`` — not ``ru_maxrss``, which Linux
carries over from the forking parent across ``exec`` and so reported the benchmark driver's own peak.
Issue 13: sparse must not need more than dense. Linux only.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

__all__ = ["peak_rss"]

ROOT = Path(__file__).resolve().parents[1]

_CHILD = """
import json, re, sys, torch
sys.path.insert(0, {root!r})
torch.set_num_threads(1)
from benchmarks.training_step import QUICK, _step_fn
from cdm.config import load_config
cfg = load_config(QUICK, {overrides!r})
step = _step_fn(cfg, {out!r})
for _ in range(3):
    step()
hwm_kb = int(re.search(r"VmHWM:\\s+(\\d+) kB", open("/proc/self/status").read()).group(1))
print(json.dumps({{"peak_rss_mb": hwm_kb / 1024}}))
"""


def _measure(overrides: dict, out_dir: str) -> float:
    code = _CHILD.format(root=str(ROOT), overrides=overrides, out=out_dir)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=1200)
    return json.loads(done.stdout.strip().splitlines()[-1])["peak_rss_mb"]


def peak_rss(quick: bool, out_dir: str) -> list[dict]:
    rows = []
    paper_model = {"model.widths": [64, 128, 256], "model.voxel_resolutions": [32, 16, 16], "priors.prior_3d": False}
    for n in (1024,) if quick else (1024, 4096):
        dense = _measure({**paper_model, "data.num_points": n, "model.voxel_backend": "dense"}, out_dir)
        sparse = _measure({**paper_model, "data.num_points": n, "model.voxel_backend": "sparse"}, out_dir)
        rows.append({"benchmark": "peak RSS MB, dense vs sparse", "case": f"paper widths, N={n}, B=8",
                     "without_s": dense, "with_s": sparse, "ratio": sparse / dense, "target": "<= 1.0 (sparse/dense)"})
    return rows
