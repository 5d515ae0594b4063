"""The quick-config training step, this tree ÷ a reference commit (issue 19: ≤ 0.10 s from 0.195 s).

Both implementations run in child processes (one torch thread each, the same config and batch
recipe), alternated round by round so the machine's drift hits both alike; each round times
``STEPS`` steps on a fixed batch after a warm-up and reports its median CPU seconds per step. The
reference is ``REFERENCE`` (the tree before issue 19's step changes), extracted with ``git archive``;
without git history the row says so instead of a number.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

__all__ = ["REFERENCE", "step_vs_reference"]

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = "1a8e458"
"""main just before issue 19's first change."""
STEPS = 6

_CHILD = """
import json, statistics, sys, time, torch
from pathlib import Path
from cdm.config import load_config
from cdm.train import Trainer
torch.set_num_threads(1)
cfg = load_config(Path(sys.argv[1]), {"train.out_dir": sys.argv[2], "train.threads": 1})
trainer = Trainer(cfg)
batch = trainer.next_batch()
trainer.train_step(batch)
times = []
for _ in range(int(sys.argv[3])):
    start = time.process_time()
    trainer.train_step(batch)
    times.append(time.process_time() - start)
print(json.dumps(statistics.median(times)))
"""


def _time(tree: Path, out_dir: str) -> float:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", _CHILD, str(ROOT / "configs" / "quick.yaml"), out_dir, str(STEPS)],
                          cwd=tree, env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def step_vs_reference(quick: bool, out_dir: str) -> list[dict]:
    with tempfile.TemporaryDirectory() as tmp:
        archive = Path(tmp) / "ref.tar"
        made = subprocess.run(
            ["git", "-C", str(ROOT), "archive", "-o", str(archive), REFERENCE], capture_output=True, text=True
        )
        if made.returncode != 0:
            return [{"benchmark": "quick config step vs reference", "case": f"no git history: {REFERENCE} unavailable",
                     "without_s": float("nan"), "with_s": float("nan"), "ratio": float("nan"), "target": "<= 0.513"}]
        ref = Path(tmp) / "ref"
        with tarfile.open(archive) as tar:
            tar.extractall(ref, filter="data")
        pairs = []
        for i in range(2 if quick else 4):
            order = [(ref, "ref"), (ROOT, "new")] if i % 2 == 0 else [(ROOT, "new"), (ref, "ref")]
            got = {name: _time(tree, f"{out_dir}/step_{name}") for tree, name in order}
            pairs.append((got["ref"], got["new"]))
    ref_s = statistics.median(a for a, _ in pairs)
    new_s = statistics.median(b for _, b in pairs)
    return [
        {
            "benchmark": "quick config step vs reference",
            "case": f"B=8, 1 thread, CPU s per step, {REFERENCE} vs this tree",
            "without_s": ref_s,
            "with_s": new_s,
            "ratio": statistics.median(b / a for a, b in pairs),
            "target": "<= 0.513 (0.10 s / 0.195 s)",
        },
        {
            "benchmark": "quick config step",
            "case": "this tree, B=8, 1 thread, CPU s per step",
            "without_s": new_s,
            "with_s": new_s,
            "ratio": new_s / 0.10,
            "target": "<= 1.0 (step / 0.10 s)",
        },
    ]
