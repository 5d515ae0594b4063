"""Ops dispatched per pvcnn2 training step, and per point operation, counted with ``torch.profiler`` on CPU.

    python benchmarks/step_ops.py [--quick]

On a GPU every dispatched op is at least one kernel launch, and sequential launches are what a small
kernel costs, so the count is a device-independent proxy for launch overhead. Rows:

- one whole training step (:class:`cdm.train.Trainer`, PC²'s PVCNN2 with the frozen ViT-S/16 and the 3D prior,
  ``benchmarks/gpu_check.py``'s sizes) at batch 2 (CPU time; the count depends on the batch only through
  the chunking of the neighbour searches, given per operation below): top-level ``aten`` ops, forward and
  backward together;
- each point operation at the paper's shapes (Co3D: B=8, N=16,384; SA1: 1,024 centres, r 0.1, 32
  neighbours; the last feature propagation: 16,384 points from 1,024 centres): top-level ops per call,
  farthest-point sampling also per picked centre, and the largest single allocation of the call
  (``profile_memory``) against the full ``B×M×N`` float32 distance matrix.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from functools import partial
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.gpu_check import _trainer, size_config  # noqa: E402
from cdm.model import pointops  # noqa: E402
from tests.test_encoder import write_msn_checkpoint  # noqa: E402

__all__ = ["count_ops", "main"]


def count_ops(fn) -> tuple[int, int]:
    """Top-level ``aten`` ops ``fn()`` dispatches (an op called inside another is not counted again) and
    the largest allocation one op made, in bytes."""
    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        fn()
    events = prof.events()

    def nested(e) -> bool:
        parent = e.cpu_parent
        while parent is not None:
            if parent.name.startswith("aten::"):
                return True
            parent = parent.cpu_parent
        return False

    aten = [e for e in events if e.name.startswith("aten::")]
    top = [e for e in aten if not nested(e)]
    biggest = max((e.cpu_memory_usage for e in aten), default=0)
    return len(top), int(biggest)


def _pointops_rows(b: int, n: int, m: int, k: int) -> list[dict]:
    g = torch.Generator().manual_seed(0)
    points = torch.rand(b, 3, n, generator=g) * 2 - 1
    centres = pointops.gather_points(points, pointops.farthest_point_sample(points, m))
    full = b * m * n * 4
    rows = []
    ops, biggest = count_ops(lambda: pointops.farthest_point_sample(points, m))
    rows.append({"op": "farthest_point_sample", "shape": f"B={b}, N={n} → M={m}", "ops": ops,
                 "ops_per_centre": round(ops / (m - 1), 2), "largest_bytes": biggest, "full_matrix_bytes": b * n * 4})
    ops, biggest = count_ops(lambda: pointops.ball_query(centres, points, 0.1, k))
    rows.append({"op": "ball_query", "shape": f"B={b}, M={m} centres, N={n}, K={k}", "ops": ops,
                 "largest_bytes": biggest, "full_matrix_bytes": full})
    ops, biggest = count_ops(lambda: pointops.three_nn(points, centres))
    rows.append({"op": "three_nn", "shape": f"B={b}, N={n} points, M={m} centres", "ops": ops,
                 "largest_bytes": biggest, "full_matrix_bytes": full})
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="toy sizes (a check that it runs)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "vits16_800ep.pth.tar"
        write_msn_checkpoint(weights)
        for size in ("shapenet", "co3d"):
            cfg = size_config(size, "fp32", "cpu", weights, tmp, args.quick).replace(**{"train.batch_size": 2})
            trainer = _trainer(cfg)
            batch = trainer.next_batch()
            trainer.train_step(batch)  # warm-up
            ops, biggest = count_ops(partial(trainer.train_step, batch))
            rows.append(
                {
                    "op": "training step",
                    "shape": f"{size}: B=2, N={cfg.data.num_points}, {cfg.data.image_size}²",
                    "ops": ops,
                    "largest_bytes": biggest,
                }
            )
    b, n = (2, 1024) if args.quick else (8, 16384)
    rows += _pointops_rows(b, n, 1024 if not args.quick else 128, 32)
    print(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
