"""Training-step costs on CPU: the 3D prior constraint's overhead, and sparse vs dense voxel branch.

- prior overhead: one training step with the constraint (H=10, point size 0.04) ÷ the same step
  without it, at the quick/local config and at paper scale (224², N=4,096). Target ≤ 1.3× (issue 3;
  the paper calls the overhead negligible).
- voxel back-ends: dense ÷ sparse step time at paper widths (64/128/256, res 32/16/16), B=8, one
  thread. Targets ≥ 5× at N=1,024 and ≥ 2.5× at N=4,096 (issue 13); and the local step time.
"""

from __future__ import annotations

from pathlib import Path

from benchmarks.common import median_s, paired
from cdm.config import Config, load_config
from cdm.train import Trainer

__all__ = ["prior_overhead", "voxel_backends"]

QUICK = Path(__file__).resolve().parents[1] / "configs" / "quick.yaml"
PAPER_SCALE = {"data.image_size": 224, "data.num_points": 4096, "priors.render_size": 224,
               "model.widths": [64, 128, 256], "model.voxel_resolutions": [32, 16, 16]}


def _step_fn(cfg: Config, out_dir: str):
    """One training step on a fixed batch, on one torch thread (figures are per thread)."""
    trainer = Trainer(cfg.replace(**{"train.out_dir": out_dir, "train.threads": 1}))
    batch = trainer.next_batch()
    return lambda: trainer.train_step(batch)


def prior_overhead(quick: bool, out_dir: str) -> list[dict]:
    rows = []
    scales = [("quick config (64², N=512)", {})] + (
        [] if quick else [("paper scale (224², N=4096, widths 64/128/256, sparse)", PAPER_SCALE)]
    )
    for label, extra in scales:
        on = load_config(QUICK, {**extra, "priors.prior_3d": True, "priors.num_views": 10, "priors.point_size": 0.04})
        off = load_config(QUICK, {**extra, "priors.prior_3d": False})
        result = paired(_step_fn(off, out_dir), _step_fn(on, out_dir), repeats=4 if quick else 8)
        rows.append({"benchmark": "3D prior overhead", "case": label, "without_s": result.a_s, "with_s": result.b_s,
                     "ratio": result.ratio, "target": "<= 1.3"})
    return rows


def voxel_backends(quick: bool, out_dir: str) -> list[dict]:
    rows = []
    paper_model = {"model.widths": [64, 128, 256], "model.voxel_resolutions": [32, 16, 16], "priors.prior_3d": False}
    for n, target in ((1024, ">= 5"), (4096, ">= 2.5")):
        if quick and n == 4096:
            continue
        dense = load_config(QUICK, {**paper_model, "data.num_points": n, "model.voxel_backend": "dense"})
        sparse = load_config(QUICK, {**paper_model, "data.num_points": n, "model.voxel_backend": "sparse"})
        result = paired(_step_fn(sparse, out_dir), _step_fn(dense, out_dir), repeats=2 if quick else 4)
        rows.append({"benchmark": "dense / sparse step", "case": f"paper widths, N={n}", "without_s": result.a_s,
                     "with_s": result.b_s, "ratio": result.ratio, "target": target})
    seconds = median_s(_step_fn(load_config(QUICK), out_dir), 10)
    rows.append({"benchmark": "quick config step", "case": "B=8, 1 thread, with 3D prior", "without_s": seconds,
                 "with_s": seconds, "ratio": seconds / 0.25, "target": "<= 1.0 (step / 0.25 s)"})
    return rows
