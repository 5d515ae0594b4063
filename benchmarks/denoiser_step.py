"""Time one training step of each denoiser on CPU: PC²'s PVCNN2 (``pvcnn2``) against our point-voxel network.

    python benchmarks/denoiser_step.py [--quick]

A step is what training repeats per batch once the image is encoded: project the conditioning map
onto ``x_t`` from the input camera, run the denoiser, MSE against ε, backward, AdamW. The image features
are random tensors of the right shape (the encoder is outside the step). Rows:

- paper scale (B=8, N=4,096, 224², PC²'s 389 conditioning channels): ``pvcnn2`` ÷ ``pointvoxel`` at the
  paper profile's widths (64/128/256, resolutions 32/16/16, sparse on CPU), alternated in one process,
  median of paired ratios; the share of ``pvcnn2``'s step spent in :mod:`cdm.model.pointops` (each call of
  one step replayed alone, forward and backward; goal ≤ 20 %); the peak RSS of each, in its own process.
- local scale (B=4, N=512, 64², 38 channels): ``pvcnn2`` at width multipliers 1, 0.5, 0.25 (and 0.25 with
  voxel resolutions halved) ÷ ``pointvoxel`` at the local profile's widths (32/64/128, 16/8/8, sparse).

One torch thread; figures are per thread. ``--quick`` runs the local rows only.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import torch
import torch.nn as nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import paired  # noqa: E402
from cdm.config import load_config  # noqa: E402
from cdm.model import CDMNetwork, pointops  # noqa: E402
from tests.test_model import tiny_batch  # noqa: E402

__all__ = ["LOCAL", "PAPER", "Scale", "geometry_seconds", "make_step"]


class Scale(NamedTuple):
    """Batch ``B``, points ``N``, image side ``S``, image feature channels, 2D prior channels."""

    batch: int
    points: int
    image: int
    feature_dim: int
    prior_channels: int


PAPER = Scale(8, 4096, 224, 384, 0)  # PC²'s inputs: RGB + ViT-S/16 384 + mask + distance = 389
LOCAL = Scale(4, 512, 64, 32, 1)  # sweeps/profiles.yaml "local", contour prior: 32 + 1 + 5 = 38
POINTVOXEL = {
    PAPER: {"model.widths": [64, 128, 256], "model.voxel_resolutions": [32, 16, 16], "model.voxel_backend": "sparse"},
    LOCAL: {"model.widths": [32, 64, 128], "model.voxel_resolutions": [16, 8, 8], "model.voxel_backend": "sparse"},
}


class _RandomFeatures(nn.Module):
    """Stands in for the image encoder: fixed random ``(B, F, S, S)`` features."""

    def __init__(self, features: torch.Tensor):
        super().__init__()
        self.out_channels = features.shape[1]
        self.features = features

    def forward(self, image: torch.Tensor, mask: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
        return self.features


def make_step(scale: Scale, overrides: dict, seed: int = 0) -> tuple[Callable[[], None], nn.Module]:
    """A closure running one training step of the network ``overrides`` configures, and its denoiser."""
    torch.manual_seed(seed)
    cfg = load_config(None, {"model.feature_dim": scale.feature_dim, **overrides})
    batch = tiny_batch(scale.batch, scale.points, scale.image, scale.prior_channels, seed)
    g = torch.Generator().manual_seed(seed)
    features = torch.randn(scale.batch, scale.feature_dim, scale.image, scale.image, generator=g)
    net = CDMNetwork(cfg.model, scale.prior_channels, device="cpu", encoder=_RandomFeatures(features))
    with torch.no_grad():
        context = net.encode(batch)
    noise = torch.randn(batch.points.shape, generator=g)
    x_t = 0.8 * batch.points + 0.6 * noise
    t = torch.randint(0, 1000, (scale.batch,), generator=g)
    opt = torch.optim.AdamW(net.denoiser.parameters(), lr=1e-4)

    def step() -> None:
        loss = (net(x_t, t, context, batch.camera) - noise).square().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step, net.denoiser


_OPS = ("farthest_point_sample", "ball_query", "group", "gather_points", "three_nn_interpolate",
        "voxelize_coords", "voxelize", "trilinear_devoxelize")


def geometry_seconds(step: Callable[[], None]) -> dict[str, float]:
    """Seconds per :mod:`cdm.model.pointops` operation in one ``step``: every call recorded during a step,
    then replayed alone (forward, and backward into the arguments that needed a gradient in the step)."""
    calls: list[tuple[str, tuple]] = []
    originals = {name: getattr(pointops, name) for name in _OPS}

    def recorder(name: str):
        def record(*args):
            calls.append((name, tuple(a.detach().clone().requires_grad_(a.requires_grad) if isinstance(a, torch.Tensor)
                                      else a for a in args)))
            return originals[name](*args)
        return record

    for name in _OPS:
        setattr(pointops, name, recorder(name))
    try:
        step()
    finally:
        for name, fn in originals.items():
            setattr(pointops, name, fn)
    seconds = dict.fromkeys(_OPS, 0.0)
    for name, args in calls:
        start = time.perf_counter()
        out = originals[name](*args)
        if isinstance(out, torch.Tensor) and out.requires_grad:
            out.backward(torch.ones_like(out))
        seconds[name] += time.perf_counter() - start
    return seconds


_CHILD = """
import json, re, sys, torch
sys.path.insert(0, {root!r})
torch.set_num_threads(1)
from benchmarks.denoiser_step import Scale, make_step
step, _ = make_step(Scale(*{scale!r}), {overrides!r})
for _ in range(2):
    step()
hwm_kb = int(re.search(r"VmHWM:\\s+(\\d+) kB", open("/proc/self/status").read()).group(1))
print(json.dumps({{"peak_rss_mb": hwm_kb / 1024}}))
"""


def peak_rss_mb(scale: Scale, overrides: dict) -> float:
    """Peak RSS of a process that builds the step and runs it twice (``VmHWM``; Linux)."""
    code = _CHILD.format(root=str(Path(__file__).resolve().parents[1]), scale=tuple(scale), overrides=overrides)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=1200)
    return json.loads(done.stdout.strip().splitlines()[-1])["peak_rss_mb"]


def _params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="local-scale rows only")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| scale | pointvoxel (s) | pvcnn2 (s) | pvcnn2 ÷ pointvoxel | params pointvoxel / pvcnn2 |")
    print("|---|---|---|---|---|")
    if not args.quick:
        pv_step, pv = make_step(PAPER, {**POINTVOXEL[PAPER], "model.denoiser": "pointvoxel"})
        p2_step, p2 = make_step(PAPER, {"model.denoiser": "pvcnn2"})
        result = paired(pv_step, p2_step, repeats=2)
        print(f"| paper B=8 N=4096 224², pvcnn2 ×1 vs 64/128/256 32/16/16 sparse | {result.a_s:.2f} | {result.b_s:.2f} "
              f"| {result.ratio:.2f} | {_params(pv):,} / {_params(p2):,} |")
        geometry = geometry_seconds(p2_step)
        total = sum(geometry.values())
        parts = ", ".join(f"{k} {v:.2f}" for k, v in sorted(geometry.items(), key=lambda kv: -kv[1]) if v > 0)
        print(
            f"\npvcnn2 paper step: geometric ops {total:.2f} s of {result.b_s:.2f} s = "
            f"{100 * total / result.b_s:.1f} % ({parts})"
        )
        mem_pv = peak_rss_mb(PAPER, {**POINTVOXEL[PAPER], "model.denoiser": "pointvoxel"})
        mem_p2 = peak_rss_mb(PAPER, {"model.denoiser": "pvcnn2"})
        print(f"peak RSS per process (build + 2 steps): pointvoxel {mem_pv:.0f} MB, pvcnn2 {mem_p2:.0f} MB\n")
    pv_step, pv = make_step(LOCAL, {**POINTVOXEL[LOCAL], "model.denoiser": "pointvoxel"})
    for wm, vm in ((1.0, 1.0), (0.5, 1.0), (0.25, 1.0), (0.25, 0.5)):
        p2_step, p2 = make_step(LOCAL, {"model.denoiser": "pvcnn2", "model.width_multiplier": wm,
                                        "model.voxel_resolution_multiplier": vm})
        result = paired(pv_step, p2_step, repeats=3)
        print(f"| local B=4 N=512 64², pvcnn2 ×{wm} res ×{vm} vs 32/64/128 16/8/8 sparse | {result.a_s:.3f} "
              f"| {result.b_s:.3f} | {result.ratio:.2f} | {_params(pv):,} / {_params(p2):,} |")
    print(f"\ntorch {torch.__version__}, {torch.get_num_threads()} thread; medians of paired steps")


if __name__ == "__main__":
    main()
