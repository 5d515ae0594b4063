"""The local training step, this tree ÷ the tree at a base revision, side by side (issue 54: ≤ 0.6×).

    python benchmarks/lean_step.py [--base REV] [--rounds N] [--quick]

The step of the sweeps' ``local`` profile as issue 54 measured it: ``configs/quick.yaml`` with point size
0.04, H = 10 views, batch 4, the sparse voxel back-end, one torch thread. The base tree (default
``BASE``, the commit issue 54 profiled) is exported with ``git archive``; each tree runs in its own child
process, and both children stay alive while the parent asks them for one step at a time, alternating
which goes first, so the machine's drift hits both alike. Printed per tree:

- CPU seconds per step (``time.process_time``, the median over rounds) and the median per-round ratio
  new ÷ old;
- top-level ops per step: every op a ``TorchDispatchMode`` sees in one step (forward, backward and
  optimiser; an op called inside another op's kernel is not seen again);
- equality: the loss and every parameter gradient of the first batch at the config's seed, before any
  optimiser step, compared between the trees (largest absolute difference over the largest magnitude).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["BASE", "LOCAL_STEP", "lean_step"]

ROOT = Path(__file__).resolve().parents[1]
BASE = "9fbe9d8"
"""main when issue 54 was filed: the step it profiled."""
LOCAL_STEP = {
    "data.val_objects": 16,
    "model.voxel_backend": "sparse",
    "diffusion.sample_steps": 10,
    "diffusion.timestep_spacing": "trailing",
    "train.batch_size": 4,
    "train.betas": [0.9, 0.99],
    "train.warmup_steps": 150,
    "priors.num_views": 10,
    "priors.point_size": 0.04,
    "train.threads": 1,
}
"""The ``local`` profile's step settings on ``configs/quick.yaml`` as issue 54 measured them (sweeps/profiles.yaml)."""
TOLERANCE = 1e-4
"""Loss and gradients: largest difference ÷ largest magnitude. Float32 sums of the same terms in another
order differ by a few ulps per sum; through ~10 layers and their backward that stays below 1e-5."""

_CHILD = r"""
import collections, json, sys, time, torch
from pathlib import Path
from torch.utils._python_dispatch import TorchDispatchMode
from cdm.config import load_config
from cdm.train import Trainer

class Count(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.ops = collections.Counter()
    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[func.overloadpacket.__name__] += 1
        return func(*args, **(kwargs or {}))

torch.set_num_threads(1)
config, overrides, out_dir, grads_file = sys.argv[1:5]
trainer = Trainer(load_config(Path(config), {**json.loads(overrides), "train.out_dir": out_dir}))
batch = trainer.next_batch()
loss = trainer.losses(batch)[0]
loss.backward()
named = [(n, p.grad) for n, p in trainer.network.named_parameters() if p.grad is not None]
flat = torch.cat([loss.detach().reshape(1)] + [g.reshape(-1) for _, g in named]).double()
flat.numpy().tofile(grads_file)
trainer.network.zero_grad(set_to_none=True)
for _ in range(3):
    trainer.train_step(batch)
with Count() as count:
    trainer.train_step(batch)
print(json.dumps({"names": [n for n, _ in named], "ops": sum(count.ops.values()),
                  "top": count.ops.most_common(8)}), flush=True)
for _ in sys.stdin:
    start = time.process_time()
    trainer.train_step(batch)
    print(json.dumps(time.process_time() - start), flush=True)
"""


class _Tree:
    """A child process holding one tree's trainer; :meth:`step` times one training step in it."""

    def __init__(self, tree: Path, scratch: Path, name: str):
        self.grads_file = scratch / f"{name}.f64"
        env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _CHILD, str(tree / "configs" / "quick.yaml"), json.dumps(LOCAL_STEP),
             str(scratch / f"run_{name}"), str(self.grads_file)],
            cwd=tree, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )
        line = self.proc.stdout.readline()
        if not line:
            self.proc.wait()
            raise RuntimeError(f"the {name} tree's step did not start (exit code {self.proc.returncode})")
        self.info = json.loads(line)

    def step(self) -> float:
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def _export(base: str, into: Path) -> Path | None:
    archive = into / "base.tar"
    made = subprocess.run(["git", "-C", str(ROOT), "archive", "-o", str(archive), base], capture_output=True, text=True)
    if made.returncode != 0:
        return None
    tree = into / "base"
    with tarfile.open(archive) as tar:
        tar.extractall(tree, filter="data")
    return tree


def _equality(old: _Tree, new: _Tree) -> tuple[float, float, float]:
    """Old loss, new loss, and the largest gradient difference over the largest gradient magnitude."""
    if old.info["names"] != new.info["names"]:
        raise RuntimeError("the trees' networks have different parameters: their gradients cannot be compared")
    a, b = np.fromfile(old.grads_file), np.fromfile(new.grads_file)
    return float(a[0]), float(b[0]), float(np.abs(a[1:] - b[1:]).max() / np.abs(a[1:]).max())


def lean_step(quick: bool, out_dir: str, base: str = BASE, rounds: int | None = None) -> list[dict]:
    rounds = rounds or (6 if quick else 30)
    case = f"local step: quick.yaml, B=4, H=10, size 0.04, sparse, 1 thread; {base} vs this tree"
    with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
        scratch = Path(tmp)
        base_tree = _export(base, scratch)
        if base_tree is None:
            nan = float("nan")
            return [{"benchmark": "lean step", "case": f"no git history: {base} unavailable", "without_s": nan,
                     "with_s": nan, "ratio": nan, "target": "<= 0.6"}]
        old, new = _Tree(base_tree, scratch, "old"), _Tree(ROOT, scratch, "new")
        try:
            pairs = []
            for i in range(rounds):
                if i % 2:
                    b = new.step()
                    a = old.step()
                else:
                    a = old.step()
                    b = new.step()
                pairs.append((a, b))
            loss_old, loss_new, grad_diff = _equality(old, new)
        finally:
            old.close()
            new.close()
    old_ops, new_ops = old.info["ops"], new.info["ops"]
    return [
        {"benchmark": "lean step", "case": case + ", CPU s per step",
         "without_s": statistics.median(a for a, _ in pairs), "with_s": statistics.median(b for _, b in pairs),
         "ratio": statistics.median(b / a for a, b in pairs),
         "target": "<= 0.6 (aim 0.5)"},
        {"benchmark": "lean step ops", "case": "top-level ops per step (TorchDispatchMode)", "without_s": old_ops,
         "with_s": new_ops, "ratio": new_ops / old_ops, "target": "report",
         "top_old": old.info["top"], "top_new": new.info["top"]},
        {"benchmark": "lean step equality",
         "case": "loss (a, b); largest gradient difference / largest gradient, over 1e-4 (ratio); first batch",
         "without_s": loss_old, "with_s": loss_new, "ratio": grad_diff / TOLERANCE, "max_grad_diff": grad_diff,
         "target": "<= 1, and loss within 1e-4 relative"},
    ]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", default=BASE, help=f"the old tree's git revision (default {BASE})")
    p.add_argument("--rounds", type=int, default=None, help="timed steps per tree (default 30, --quick 6)")
    p.add_argument("--quick", action="store_true", help="fewer rounds (a check that it runs)")
    args = p.parse_args(argv)
    if args.rounds is not None and args.rounds < 1:
        print(f"error: --rounds must be >= 1, got {args.rounds}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as out:
        rows = lean_step(args.quick, out, args.base, args.rounds)
    for row in rows:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
