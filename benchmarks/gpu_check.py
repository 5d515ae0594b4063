"""One device script: every figure a cluster user needs for the paper profile, written to ``gpu_costs.json``.

    python benchmarks/gpu_check.py                        # CUDA, paper scale, at most ~8 min on one GPU
    python benchmarks/gpu_check.py --device cpu --quick   # toy scale: what the test suite runs
    python benchmarks/gpu_check.py --count-flops --device cpu   # only the counted FLOPs (any device)

Only a device's figures go to the committed ``benchmarks/gpu_costs.json``, which the estimate reads: a check on
CUDA at paper scale, or ``--count-flops`` at paper scale. A check on a CPU or a ``--quick`` one writes to
``benchmarks/out/gpu_costs.json`` (not committed), and is refused if ``--out`` names the committed file.

It trains PC²'s PVCNN2 (the paper profile's denoiser) with the frozen ViT-S/16 (random weights in MSN's
layout, its token cache off so every step pays it) and the 3D prior constraint (H=10, point size 0.04)
on the procedural data at two sizes: Co3D's (B=8, N=16,384, 224², depth prior and renderings, mask
channels) and ShapeNet's (B=16, BDM's batch, N=4,096, contour prior, planar renderings, no mask
channels). For each size and each ``train.precision`` (fp32, fp16, bf16; fp16 only on CUDA, see
:func:`cdm.runtime.resolve_precision`) it writes:

- ``train_step_s``: median seconds of one training step (a ready batch; forward, backward, AdamW);
- ``peak_memory_gib``: CUDA's peak allocated memory over those steps;
- ``flop_fraction``: counted FLOPs per step ÷ step time ÷ the device's dense peak for that precision
  (:data:`sweeps.plan.estimate.PEAK_FLOPS`; fp32 against TF32, which cuDNN's convolutions use by default);
- ``sample_step_s`` and ``sample_batch_s``: one denoiser evaluation at the sampling batch, and a batch
  through PC²'s 1,000 DDPM steps, extrapolated from ``sample_steps_timed`` real sampler steps (said in
  the file);
- ``largest_batch``: doubling from the paper's batch in the paper's precision until CUDA runs out of
  memory (the last that fitted; CUDA only).

FLOPs are counted with ``torch.utils.flop_counter.FlopCounterMode`` over one training step and one
denoiser evaluation (matrix products and convolutions; element-wise work is not counted, so figures built
on them are lower bounds). ``trial_gpu_hours`` is one paper-profile trial of ``sweeps/co3d.yaml`` and
``sweeps/shapenet.yaml`` (training plus every evaluation) from these figures
(:func:`sweeps.plan.estimate.paper_trial_gpu_hours`). ``--count-flops`` only updates the ``flops``
section (device-independent), which the estimate's lower bound reads where no GPU has measured.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import denoiser_call, denoiser_eval_s, device_median_s  # noqa: E402
from cdm.config import Config, load_config  # noqa: E402
from cdm.evaluate import reconstruct  # noqa: E402
from cdm.train import Trainer  # noqa: E402
from sweeps.plan.estimate import GPU_COSTS, paper_trial_gpu_hours, peak_flops  # noqa: E402
from sweeps.plan.spec import load_spec  # noqa: E402
from sweeps.plan.trials import expand  # noqa: E402
from tests.test_encoder import write_msn_checkpoint  # noqa: E402

__all__ = ["SIZES", "TOY_COSTS", "check", "count_flops", "device_figures", "main", "size_config"]

ROOT = Path(__file__).resolve().parents[1]
PRECISIONS = ("fp32", "fp16", "bf16")
PAPER_PRECISION = "fp16"  # sweeps/profiles.yaml, paper: PC²'s mixed_precision
SIZES = {  # the paper profile per data set (sweeps/profiles.yaml): batch, points, 2D prior, renderings, mask channels
    "co3d": {"train.batch_size": 8, "data.num_points": 16384, "priors.prior_2d": "depth", "priors.render_kind": "depth",
             "model.mask_channels": True},
    "shapenet": {"train.batch_size": 16, "data.num_points": 4096, "priors.prior_2d": "contour",
                 "priors.render_kind": "planar", "model.mask_channels": False},
}
QUICK = {"train.batch_size": 2, "data.image_size": 32, "priors.render_size": 32, "priors.num_views": 2,
         "model.width_multiplier": 0.25, "model.voxel_resolution_multiplier": 0.25}
"""--quick: toy sizes, each size's points ÷ 64 (256 and 64), so the two stay apart in the file."""
SAMPLE_STEPS_TIMED = {False: 20, True: 2}  # real sampler steps timed, by --quick
SPECS = {"co3d": "co3d.yaml", "shapenet": "shapenet.yaml"}


def size_config(size: str, precision: str, device: str, weights: Path, out_dir: str, quick: bool) -> Config:
    """The paper profile's training at ``size`` (:data:`SIZES`) on the procedural data, in ``precision``."""
    return load_config(None, {
        "model.denoiser": "pvcnn2", "model.encoder": "vit_s16", "model.feature_dim": 384,
        "model.encoder_weights": str(weights), "data.image_size": 224, "priors.render_size": 224,
        "diffusion.prediction": "eps", "priors.prior_3d": True, "priors.num_views": 10, "priors.point_size": 0.04,
        "data.train_objects": 8, "data.val_objects": 1, "train.precision": precision, "train.device": device,
        "train.out_dir": out_dir, **SIZES[size],
        **({**QUICK, "data.num_points": SIZES[size]["data.num_points"] // 64} if quick else {}),
    })


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _trainer(cfg: Config) -> Trainer:
    trainer = Trainer(cfg)
    trainer.network.encoder.cache_bytes = 0  # every step pays the frozen ViT, as on a data set larger than the cache
    return trainer


def count_flops(trainer: Trainer) -> dict[str, float]:
    """Counted FLOPs of one training step and one denoiser evaluation (precision-independent); the step
    is taken (it doubles as a warm-up)."""
    batch = trainer.next_batch()
    with FlopCounterMode(display=False) as train:
        trainer.train_step(batch)
    net = trainer.network
    with torch.no_grad():
        call = denoiser_call(net, batch)
        with FlopCounterMode(display=False) as sample:
            call()
    return {"train_step": float(train.get_total_flops()), "sample_step": float(sample.get_total_flops()),
            "batch_size": trainer.cfg.train.batch_size}


def _sampling(trainer: Trainer, quick: bool) -> dict[str, float]:
    """Seconds of one denoiser evaluation and of a batch through 1,000 DDPM steps (extrapolated)."""
    device, cfg = trainer.device, trainer.cfg
    batch = trainer.next_batch()
    net = trainer.network
    step_s = denoiser_eval_s(net, batch, device, 2 if quick else 10)
    k = SAMPLE_STEPS_TIMED[quick]
    # The real sampler loop (encode, k network evaluations and updates); DDIM with k steps costs per step
    # what DDPM does: one network evaluation and an update of x_t.
    timed = cfg.replace(**{"diffusion.sampler": "ddim", "diffusion.sample_steps": k})
    gen = torch.Generator(device=device).manual_seed(0)
    loop_s = device_median_s(lambda: reconstruct(net, trainer.diffusion, batch, timed, gen), device, 1 if quick else 2,
                             warmup=int(not quick))
    net.train()
    return {
        "sample_step_s": step_s,
        "sample_batch_s": loop_s / k * cfg.diffusion.num_steps,
        "sample_steps_timed": k,
        "sample_batch_note": f"extrapolated: {k} timed sampler steps × {cfg.diffusion.num_steps}/{k}",
    }


def _largest_batch(size: str, device: str, weights: Path, out_dir: str, deadline: float) -> dict[str, object]:
    """The largest batch (doubling from the paper's) whose fp16 training step fits in CUDA memory."""
    if torch.device(device).type != "cuda":
        return {"largest_batch": None, "largest_batch_note": "CUDA only"}
    fits, b = None, SIZES[size]["train.batch_size"]
    while time.monotonic() < deadline:
        try:
            cfg = size_config(size, PAPER_PRECISION, device, weights, out_dir, False).replace(**{"train.batch_size": b})
            trainer = _trainer(cfg)
            trainer.train_step(trainer.next_batch())
            _sync(trainer.device)
            fits = b
        except torch.cuda.OutOfMemoryError:
            break
        finally:
            trainer = None
            torch.cuda.empty_cache()
        b *= 2
    note = "out of memory at twice it" if time.monotonic() < deadline else "time budget spent before memory ran out"
    return {"largest_batch": fits, "largest_batch_note": note}


def check(device: str, quick: bool, deadline_s: float) -> dict:
    """Every figure of the module docstring for ``device``; ``quick``: toy sizes (a CPU test)."""
    start = time.monotonic()
    deadline = start + deadline_s
    dev = torch.device(device)
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "CPU"
    figures: dict = {"device": name, "date": time.strftime("%Y-%m-%d"), "denoiser": "pvcnn2", "quick": quick,
                     "torch": torch.__version__, "by_points": {}}
    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "vits16_800ep.pth.tar"
        write_msn_checkpoint(weights)
        flops = {}
        for size in SIZES:
            base = size_config(size, "fp32", device, weights, tmp, quick)
            n = str(base.data.num_points)
            entry = {"size": size, "batch_size": base.train.batch_size, "image_size": base.data.image_size,
                     "by_precision": {}}
            for precision in PRECISIONS:
                if precision == "fp16" and dev.type != "cuda":  # cdm.runtime.resolve_precision: it would train in fp32
                    entry["by_precision"][precision] = {"note": f"{precision} needs CUDA"}
                    continue
                if dev.type == "cuda":
                    torch.cuda.reset_peak_memory_stats(dev)
                trainer = _trainer(base.replace(**{"train.precision": precision}))
                if precision == "fp32":
                    flops[n] = count_flops(trainer)
                batch = trainer.next_batch()
                step_s = device_median_s(partial(trainer.train_step, batch), trainer.device, 2 if quick else 8,
                                         warmup=int(precision != "fp32"))
                peak = peak_flops(name, precision)
                row = {"train_step_s": step_s,
                       "peak_memory_gib": torch.cuda.max_memory_allocated(dev) / 2**30 if dev.type == "cuda" else None,
                       "flop_fraction": flops[n]["train_step"] / step_s / peak if peak else None,
                       **_sampling(trainer, quick)}
                entry["by_precision"][precision] = row
                trainer = None
            entry.update(_largest_batch(size, device, weights, tmp, deadline))
            figures["by_points"][n] = entry
    figures["flops"] = {"counted_with": "torch.utils.flop_counter.FlopCounterMode", "by_points": flops}
    figures["trial_gpu_hours"] = {}
    figures["trial_gpu_hours_note"] = (
        "one trial of each spec's paper profile on its procedural stand-in (no data.root here): 100k steps and "
        "every evaluation of eval.num_objects per category; ShapeNet's at the stand-in's batch 8 (BDM's 16 with "
        "data.root). With data.root, sweeps/run.py --dry-run --profile paper counts the real evaluation split")
    for spec in SPECS.values():
        paper = expand(load_spec(ROOT / "sweeps" / spec), "paper")
        hours, why = paper_trial_gpu_hours(paper, figures)
        figures["trial_gpu_hours"][spec] = hours if hours is not None else why
    figures["seconds"] = time.monotonic() - start
    return figures


TOY_COSTS = ROOT / "benchmarks" / "out" / "gpu_costs.json"
"""Where a check on a CPU or a ``--quick`` one writes (``benchmarks/out/`` is not committed)."""


def device_figures(device: str, quick: bool, count_flops: bool) -> bool:
    """Whether a run measures what the committed table holds: a device (CUDA) at paper scale, or the
    device-independent counted FLOPs at paper scale."""
    return not quick and (count_flops or torch.device(device).type == "cuda")


def _out_path(args: argparse.Namespace) -> Path | None:
    """Where this run's figures go; None (said on stderr) where it would replace the committed table with a toy
    or CPU check's figures."""
    if device_figures(args.device, args.quick, args.count_flops):
        return Path(args.out or GPU_COSTS)
    out = Path(args.out or TOY_COSTS)
    if out.resolve() == GPU_COSTS.resolve():
        what = "--quick" if args.quick else f"--device {args.device}"
        print(f"error: --out {args.out}: a {what} check does not replace the device figures the estimate reads; "
              f"leave --out out (it writes {TOY_COSTS.relative_to(ROOT)}) or name another file", file=sys.stderr)
        return None
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda", help="cuda (default) or cpu")
    p.add_argument("--quick", action="store_true", help="toy sizes: a check that the script runs, not figures")
    p.add_argument("--out", help="where the figures go (default: benchmarks/gpu_costs.json for a device's figures, "
                                 "else benchmarks/out/gpu_costs.json)")
    p.add_argument(
        "--count-flops", action="store_true", help="only count the paper-scale FLOPs into the file's flops section"
    )
    p.add_argument(
        "--budget-s", type=float, default=420.0, help="stop searching the largest batch after this many seconds"
    )
    args = p.parse_args(argv)
    if torch.device(args.device).type == "cuda" and not torch.cuda.is_available():
        print(
            "error: --device cuda: no CUDA device here; pass --device cpu (with --quick for a toy run)", file=sys.stderr
        )
        return 2
    out = _out_path(args)
    if out is None:
        return 2
    if args.count_flops:
        with tempfile.TemporaryDirectory() as tmp:
            weights = Path(tmp) / "vits16_800ep.pth.tar"
            write_msn_checkpoint(weights)
            configs = [size_config(s, "fp32", args.device, weights, tmp, args.quick) for s in SIZES]
            counted = {str(cfg.data.num_points): count_flops(_trainer(cfg)) for cfg in configs}
        figures = json.loads(out.read_text()) if out.is_file() else {}
        figures["flops"] = {
            "counted_with": "torch.utils.flop_counter.FlopCounterMode",
            "date": time.strftime("%Y-%m-%d"),
            "by_points": counted,
        }
    else:
        figures = check(args.device, args.quick, args.budget_s)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(figures, indent=2) + "\n")
    print(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
