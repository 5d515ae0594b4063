"""Loading a training checkpoint: 0.1.0's ``checkpoint.pt`` (one ``torch.save``, read by the inert pickle
reader, ``cdm/io/torch``) against the safetensors folder (``cdm/checkpoint.py``), time and peak memory.

The checkpoint is the local profile's network (``configs/quick.yaml`` with ``sweeps/profiles.yaml``'s local
overrides) with EMA weights and AdamW's two moments per weight (one optimiser step of random gradients),
the RNG states and the schedule: what ``train --resume-from`` and a sweep's ``--resume`` read. Time: the two
loads alternate in one process (:func:`benchmarks.common.paired`), the files in the page cache for both;
the ratio is the median of per-pair ratios old / new. Memory: each load runs in a fresh process, alternating
old and new, and reports the growth of its peak RSS (``VmHWM`` after the load minus ``VmRSS`` before it,
``/proc/self/status``), the loaded checkpoint included. Issue 59: loading must not cost more than before.

    python benchmarks/checkpoint_load.py [--repeats 21] [--processes 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from dataclasses import fields
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # `python benchmarks/checkpoint_load.py` puts benchmarks/ first, not the root
    sys.path.insert(0, str(ROOT))

from benchmarks.common import paired  # noqa: E402
from cdm.checkpoint import LEGACY_FILE, Checkpoint, load_checkpoint, save_checkpoint  # noqa: E402
from cdm.io.torch import load_tensors  # noqa: E402
from cdm.model.state_dicts import checked_state_dict  # noqa: E402

LOCAL = {"data.val_objects": 16, "model.voxel_backend": "sparse", "diffusion.sample_steps": 10,
         "diffusion.timestep_spacing": "trailing", "train.batch_size": 4, "train.betas": [0.9, 0.99],
         "train.warmup_steps": 150, "eval.num_objects": 16, "train.ema_decay": 0.999}
"""The local profile's overrides of configs/quick.yaml (sweeps/profiles.yaml), with EMA kept."""

_CHILD = """
import re, sys, json
sys.path.insert(0, {root!r})
from benchmarks.checkpoint_load import load_old, load_new
def status(key):
    return int(re.search(key + r":\\s+(\\d+) kB", open("/proc/self/status").read()).group(1)) / 1024
before = status("VmRSS")
loaded = {fn}({path!r})
print(json.dumps({{"growth_mb": status("VmHWM") - before, "step": loaded.step}}))
"""


def load_old(file: str) -> Checkpoint:
    """0.1.0's ``load_checkpoint``: the inert pickle reader, then the weights checked."""
    state = load_tensors(Path(file), f"checkpoint: {file}", "CDM checkpoint", "")
    for name in ("model", "ema"):
        state[name] = checked_state_dict(state[name], name)
    return Checkpoint(**{f.name: state[f.name] for f in fields(Checkpoint) if f.name in state})


def load_new(folder: str) -> Checkpoint:
    return load_checkpoint(folder)


def _checkpoint() -> Checkpoint:
    """The local profile's training state after one AdamW step of random gradients (module docstring)."""
    from cdm.config import load_config
    from cdm.train import Trainer

    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(load_config(ROOT / "configs" / "quick.yaml", {**LOCAL, "train.out_dir": out}))
    torch.manual_seed(0)
    for p in trainer.network.parameters():
        p.grad = torch.randn_like(p)
    trainer.optimiser.optimizer.step()
    return trainer.state()


def _growth(fn: str, path: Path) -> float:
    code = _CHILD.format(root=str(ROOT), fn=fn, path=str(path))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=600)
    return json.loads(done.stdout.strip().splitlines()[-1])["growth_mb"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=21, help="timed pairs (default 21)")
    parser.add_argument("--processes", type=int, default=5, help="processes per variant for peak memory (default 5)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    state = _checkpoint()
    with tempfile.TemporaryDirectory() as scratch:
        old, new = Path(scratch) / "old", Path(scratch) / "new"
        old.mkdir()
        torch.save({f.name: getattr(state, f.name) for f in fields(state)}, old / LEGACY_FILE)
        save_checkpoint(state, new)
        sizes = {"old": (old / LEGACY_FILE).stat().st_size, "new": sum(p.stat().st_size for p in new.iterdir())}
        timing = paired(lambda: load_new(str(new)), lambda: load_old(str(old / LEGACY_FILE)), args.repeats)
        growth = {"old": [], "new": []}
        for _ in range(args.processes):
            growth["old"].append(_growth("load_old", old / LEGACY_FILE))
            growth["new"].append(_growth("load_new", new))
    weights = sum(t.numel() for t in state.model.values())
    mem = {k: statistics.median(v) for k, v in growth.items()}
    print(f"checkpoint: {weights:,} weights, EMA and AdamW moments; files {sizes['old'] / 2**20:.1f} MiB (old) "
          f"vs {sizes['new'] / 2**20:.1f} MiB (new)")
    print("| load | old: torch.save + inert reader | new: safetensors + JSON | old / new |")
    print("|---|---|---|---|")
    print(f"| time, median of {args.repeats} pairs | {timing.b_s * 1e3:.1f} ms | {timing.a_s * 1e3:.1f} ms | "
          f"{timing.ratio:.2f}× |")
    print(f"| peak RSS growth, median of {args.processes} processes | {mem['old']:.1f} MiB | {mem['new']:.1f} MiB | "
          f"{mem['old'] / mem['new']:.2f}× |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
