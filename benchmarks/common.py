"""Shared helpers for benchmarks: paired timing (ratios measured side by side) and fixtures.

These machines are shared and noisy: absolute times drift ±10 % between blocks, so every comparison
alternates its variants in one process and reports the median of paired ratios.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

__all__ = ["Paired", "median_s", "paired", "timed"]


@dataclass
class Paired:
    """Median seconds of each variant and the median of per-pair ratios ``b / a``."""

    a_s: float
    b_s: float
    ratio: float


def timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def median_s(fn: Callable[[], object], repeats: int, warmup: int = 1, sync: Callable[[], object] | None = None,
             clock: Callable[[], float] = time.perf_counter) -> float:
    """Median seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones, by ``clock``
    (wall time; ``time.process_time`` for this process's CPU time).

    ``sync`` (e.g. ``torch.cuda.synchronize``) runs before and after each timed call, so queued
    device work is counted in the call that queued it.
    """
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if sync is not None:
            sync()
        start = clock()
        fn()
        if sync is not None:
            sync()
        times.append(clock() - start)
    return statistics.median(times)


def device_median_s(fn: Callable[[], object], device: torch.device, repeats: int, warmup: int = 1) -> float:
    """:func:`median_s` of work on ``device``: on CUDA, queued kernels are waited for around each call."""
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else None
    return median_s(fn, repeats, warmup, sync)


def denoiser_call(net, batch) -> Callable[[], object]:
    """One denoiser evaluation (a sampler step's network call) on ``batch``, ready to run: its image
    features encoded once, x_t Gaussian noise at t = 500. Build and call it under ``torch.no_grad()``."""
    context = net.encode(batch)
    x = torch.randn_like(batch.points)
    t = torch.full((len(batch),), 500, device=batch.points.device)
    return lambda: net(x, t, context, batch.camera)


@torch.no_grad()
def denoiser_eval_s(net, batch, device: torch.device, repeats: int) -> float:
    """Median seconds of :func:`denoiser_call` on ``batch``."""
    return device_median_s(denoiser_call(net, batch), device, repeats)


def paired(a: Callable[[], object], b: Callable[[], object], repeats: int, warmup: int = 1) -> Paired:
    """Alternate ``a`` and ``b`` ``repeats`` times after ``warmup`` untimed rounds."""
    for _ in range(warmup):
        a()
        b()
    times_a, times_b = [], []
    for i in range(repeats):
        # Alternate which variant goes first so drift does not favour one.
        if i % 2:
            times_b.append(timed(b))
            times_a.append(timed(a))
        else:
            times_a.append(timed(a))
            times_b.append(timed(b))
    ratios = [tb / ta for ta, tb in zip(times_a, times_b)]
    return Paired(statistics.median(times_a), statistics.median(times_b), statistics.median(ratios))
