"""Rendering cost: the hard rasterizer (projection conditioning) and soft splatting (the 3D prior).

Points ∈ {1k, 4k, 16k}, 224² images, H ∈ {1, 4, 10} cameras per cloud, one thread. Each row: ``a`` =
seconds per image of the rasterizer, ``b`` = seconds per image of the splatter (planar kind, point
size 0.04), ``ratio`` = b / a. One row per renderer reports the exponent of a log-log fit of time
against points at H=10: at most linear growth (≤ 1) is the target — neither renderer compares point
pairs, and per-image costs (the z-buffer, the blur) keep the slope below 1 at these sizes.
"""

from __future__ import annotations

from functools import partial

import numpy as np
import torch

from benchmarks.common import median_s
from cdm.cameras import orbit_cameras
from cdm.render import rasterize_points, splat_points

__all__ = ["growth_exponent", "rendering"]

SIZE = 224


def growth_exponent(points: list[int], seconds: list[float]) -> float:
    """Slope of log(seconds) against log(points), least squares."""
    return float(np.polyfit(np.log(points), np.log(seconds), 1)[0])


def _per_image(fn, images: int, repeats: int) -> float:
    return median_s(fn, repeats) / images


def rendering(quick: bool, out_dir: str) -> list[dict]:
    rows, hard, soft = [], {}, {}
    counts = (1024, 4096, 16384)
    for h in (1, 10) if quick else (1, 4, 10):
        cams = orbit_cameras(
            torch.tensor([20.0]), torch.tensor([0.0]), torch.tensor([2.5]), h, focal=torch.tensor([2.0])
        )[0]
        for n in counts:
            pts = torch.rand(h, n, 3, generator=torch.Generator().manual_seed(n)) - 0.5
            repeats = 2 if quick else 5
            a = _per_image(partial(rasterize_points, pts, cams, SIZE, 0.0075), h, repeats)
            b = _per_image(partial(splat_points, pts, cams, SIZE, 0.04, "planar"), h, repeats)
            rows.append({"benchmark": "render: rasterize vs splat", "case": f"N={n}, 224², H={h} (s per image)",
                         "without_s": a, "with_s": b, "ratio": b / a, "target": "report"})
            if h == 10:
                hard[n], soft[n] = a, b
    for name, times in (("rasterize", hard), ("splat", soft)):
        exponent = growth_exponent(list(times), list(times.values()))
        rows.append({"benchmark": f"render: {name} growth", "case": "log-log slope of time vs points, H=10",
                     "without_s": times[counts[0]], "with_s": times[counts[-1]], "ratio": exponent,
                     "target": "<= 1 (at most linear)"})
    return rows
