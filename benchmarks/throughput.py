"""Training throughput and peak memory of the paper-scale model, on CPU or CUDA.

Batch 8, 224² images, PC²'s PVCNN2 (the paper profile's denoiser), the CDM step with the 3D prior constraint
(H=10, point size 0.04), at 4,096 points (ShapeNet) and 16,384 (Co3D). Each row: ``a`` = seconds per training
step, ``b`` = seconds per sampling step (one denoiser forward on the batch, what evaluation repeats
``diffusion.sample_steps`` times), ``ratio`` = training samples per second. On CUDA it also writes
``gpu_costs.json`` (figures per cloud size), which ``sweeps/plan/estimate.py`` reads for paper-profile GPU-hours
once copied to ``benchmarks/gpu_costs.json``.
"""

from __future__ import annotations

import json
import time
from functools import partial
from pathlib import Path

import torch

from benchmarks.common import denoiser_eval_s, device_median_s
from cdm.config import load_config
from cdm.train import Trainer

__all__ = ["throughput"]

# The paper profile's network (sweeps/profiles.yaml): PC²'s PVCNN2. The encoder is the trainable CNN (the
# frozen ViT's weights are a local file; it runs once per image, outside the denoiser's steps).
PAPER = {
    "model.denoiser": "pvcnn2",
    "data.image_size": 224,
    "priors.render_size": 224,
    "diffusion.prediction": "eps",
    "train.batch_size": 8,
    "priors.prior_3d": True,
    "priors.num_views": 10,
    "priors.point_size": 0.04,
    "data.train_objects": 8,
    "data.val_objects": 1,
}


def throughput(quick: bool, out_dir: str, device: str) -> list[dict]:
    rows, by_points = [], {}
    dev = torch.device(device)
    for n in (4096,) if quick and dev.type == "cpu" else (4096, 16384):
        cfg = load_config(None, {**PAPER, "data.num_points": n, "train.device": device, "train.out_dir": out_dir})
        trainer = Trainer(cfg)
        batch = trainer.next_batch()
        if dev.type == "cuda":
            torch.cuda.reset_peak_memory_stats(dev)
        step_s = device_median_s(partial(trainer.train_step, batch), dev, 3 if quick else 6)
        sample_s = denoiser_eval_s(trainer.network, batch, dev, 3 if quick else 10)
        memory = (f"peak {torch.cuda.max_memory_allocated(dev) / 2**30:.2f} GiB GPU memory" if dev.type == "cuda"
                  else "one CPU thread")
        name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "CPU"
        rows.append({"benchmark": f"throughput ({name})", "case": f"B=8, N={n}, 224², H=10; {memory}",
                     "without_s": step_s, "with_s": sample_s, "ratio": 8 / step_s, "target": "samples/s (report)"})
        by_points[str(n)] = {"train_step_s": step_s, "sample_step_s": sample_s}
    if dev.type == "cuda":
        costs = {"device": torch.cuda.get_device_name(dev), "date": time.strftime("%Y-%m-%d"),
                 "denoiser": PAPER["model.denoiser"], "by_points": by_points}
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "gpu_costs.json").write_text(json.dumps(costs, indent=2))
    return rows
