"""Does the quick config learn? Train ``configs/quick.yaml`` once and score it beside the baselines.

Issue 3's bar: on held-out procedural objects the model's CD must be below both the Gaussian cloud
and the category's mean training shape (an oracle), scored on the same objects. Takes the quick
config's full training (about 5–8 minutes on one thread), so it is not part of ``--quick``.
"""

from __future__ import annotations

import time
from pathlib import Path

from cdm.config import load_config
from cdm.train import fit

__all__ = ["quick_config_quality"]


def quick_config_quality(quick: bool, out_dir: str) -> list[dict]:
    cfg = load_config(
        Path(__file__).resolve().parents[1] / "configs" / "quick.yaml", {"train.out_dir": f"{out_dir}/quality"}
    )
    start = time.perf_counter()
    metrics = fit(cfg).metrics
    minutes = (time.perf_counter() - start) / 60
    rows = []
    for baseline in ("sphere", "gaussian", "category_mean"):
        ours, theirs = metrics["eval/cd"], metrics[f"baseline/{baseline}/cd"]
        rows.append(
            {
                "benchmark": f"quick config CD×1000 vs {baseline} ({minutes:.1f} min)",
                "case": f"{cfg.train.steps} steps, F1 {metrics['eval/f1']:.3f} vs "
                f"{metrics[f'baseline/{baseline}/f1']:.3f}",
                "without_s": theirs,
                "with_s": ours,
                "ratio": ours / theirs,
                "target": "< 1 (model below baseline)",
            }
        )
    return rows
