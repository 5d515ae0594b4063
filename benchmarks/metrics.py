"""Chamfer/F1: ``cdm.metrics.chamfer_f1`` vs a scipy cKDTree implementation of the same definition.

Sizes 4,096² and 16,384², batch 8 (issue 8): the ratio is scipy's time ÷ ours (target ≥ 1.0 on CPU),
and the largest absolute CD difference between the two (they must agree).
"""

from __future__ import annotations

from functools import partial

import numpy as np
import torch
from scipy.spatial import cKDTree

from benchmarks.common import paired
from cdm.metrics import chamfer_f1

__all__ = ["metrics_vs_scipy"]


def scipy_chamfer(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    out = []
    for p, g in zip(pred, gt):
        p, g = p - p.mean(0), g - g.mean(0)
        d_p = cKDTree(g).query(p)[0] ** 2
        d_g = cKDTree(p).query(g)[0] ** 2
        out.append(1000.0 * (d_p.mean() + d_g.mean()))
    return np.array(out)


def metrics_vs_scipy(quick: bool) -> list[dict]:
    rows = []
    for n in (4096,) if quick else (4096, 16384):
        gen = torch.Generator().manual_seed(n)
        pred, gt = torch.rand(8, n, 3, generator=gen), torch.rand(8, n, 3, generator=gen)
        pn, gn = pred.double().numpy(), gt.double().numpy()
        ref = scipy_chamfer(pn, gn)
        for search in ("kdtree", "brute"):
            ours = chamfer_f1(pred, gt, search=search).cd.numpy()
            timing = paired(
                partial(chamfer_f1, pred, gt, search=search), partial(scipy_chamfer, pn, gn), repeats=2 if quick else 3
            )
            rows.append(
                {
                    "benchmark": f"chamfer_f1 ({search}) vs scipy cKDTree",
                    "case": f"B=8, {n}x{n}",
                    "without_s": timing.a_s,
                    "with_s": timing.b_s,
                    "ratio": timing.ratio,
                    "target": ">= 1.0 (scipy/ours)" if search == "kdtree" else "report (the GPU path, timed on CPU)",
                    "max_abs_cd_diff": float(np.abs(ours - ref).max()),
                }
            )
    return rows
