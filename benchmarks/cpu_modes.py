"""Pinned CPU kernels against the default: the cost per training step and whether the numbers change.

    python benchmarks/cpu_modes.py [--steps 40] [--rounds 3] [--cell point_size=0.04]

On CPU the same code, config and packages gave other numbers on an Intel Xeon (AVX512, AMX) than on an AMD
EPYC (docs/local-results.md, "What varies"): MKL and oneDNN choose their kernels per CPU when the process
starts, and ATen dispatches by the CPU's capability. Each can be pinned by an environment variable read at
start-up: ``MKL_CBWR`` (MKL's code branch; Intel's oneMKL guide: ``AVX2`` holds on Intel CPUs only, other
CPUs fall back to ``AUTO``, so ``COMPATIBLE`` is the branch for both vendors), ``ONEDNN_MAX_CPU_ISA`` (the
newest ISA oneDNN's JIT may use) and ``ATEN_CPU_CAPABILITY``. Each mode of :data:`MODES` trains the main
job's cell (``sweeps/point_size.yaml``, profile local) from the same seed for ``--steps`` steps in a fresh
process on one thread, the modes alternating over ``--rounds`` rounds; per mode it prints the median step,
the median of per-round ratios to the default's, and a digest of the weights after the steps (the same
digest: bit-identical training). Also ``python benchmarks/run.py --only cpu_modes``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script, as the README does

from cdm.provenance import KERNEL_PINS, machine_record  # noqa: E402

__all__ = ["MODES", "cpu_modes"]

MODES = {
    "default": {},
    "avx2": {"MKL_CBWR": "AVX2", "ONEDNN_MAX_CPU_ISA": "AVX2", "ATEN_CPU_CAPABILITY": "avx2"},
    "portable": {"MKL_CBWR": "COMPATIBLE", "ONEDNN_MAX_CPU_ISA": "AVX2", "ATEN_CPU_CAPABILITY": "avx2"},
}
"""Kernel pins per mode: none; AVX2 everywhere (MKL's AVX2 branch holds on Intel CPUs only); AVX2 for oneDNN and
ATen with MKL's vendor-neutral COMPATIBLE branch."""

WARMUP = 3
"""Steps run before timing (first-call allocations, oneDNN's JIT)."""


def _train(cell: str, steps: int) -> dict:
    """In this process: ``steps`` training steps of the main job's ``cell``; step seconds and the weights' digest."""
    import torch

    from cdm.train import Trainer
    from sweeps.plan.spec import load_spec
    from sweeps.plan.trials import expand

    torch.set_num_threads(1)
    config = next(c.config for c in expand(load_spec("sweeps/point_size.yaml"), "local").cells if c.name == cell)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(config.replace(**{"train.out_dir": tmp, "train.threads": 1}))
        times = []
        for _ in range(WARMUP + steps):
            batch = trainer.next_batch()
            start = time.perf_counter()
            trainer.train_step(batch)
            times.append(time.perf_counter() - start)
    weights = hashlib.sha256()
    for tensor in trainer.network.state_dict().values():
        weights.update(tensor.detach().contiguous().numpy().tobytes())
    return {"step_s": statistics.median(times[WARMUP:]), "weights": weights.hexdigest()[:16],
            "capability": torch.backends.cpu.get_cpu_capability()}


def cpu_modes(cell: str = "point_size=0.04", steps: int = 40, rounds: int = 3) -> list[dict]:
    """A row per pinned mode (``benchmarks/run.py``'s format): the default's median step and the mode's, the
    median per-round ratio, and in ``case`` the pins, ATen's capability and whether the weights matched the
    default's after the steps."""
    base = {k: v for k, v in os.environ.items() if k not in KERNEL_PINS}
    seen: dict[str, list[dict]] = {mode: [] for mode in MODES}
    for _ in range(rounds):
        for mode, pins in MODES.items():
            out = subprocess.run([sys.executable, __file__, "--child", "--cell", cell, "--steps", str(steps)],
                                 env={**base, **pins}, capture_output=True, text=True, check=True)
            seen[mode].append(json.loads(out.stdout.splitlines()[-1]))
    default = seen["default"]
    digests = {mode: sorted({r["weights"] for r in runs}) for mode, runs in seen.items()}
    rows = []
    for mode, runs in seen.items():
        if mode == "default":
            continue
        pins = " ".join(f"{k}={v}" for k, v in MODES[mode].items())
        same = "the same as" if digests[mode] == digests["default"] else "other than"
        rows.append({
            "benchmark": "pinned CPU kernels",
            "case": f"{mode} ({pins}; ATen {runs[0]['capability']} against {default[0]['capability']}): {cell}, "
                    f"{steps} steps, weights {', '.join(digests[mode])}, {same} the default's "
                    f"{', '.join(digests['default'])}",
            "without_s": statistics.median(r["step_s"] for r in default),
            "with_s": statistics.median(r["step_s"] for r in runs),
            "ratio": statistics.median(r["step_s"] / d["step_s"] for r, d in zip(runs, default)),
            "target": "<= 1.2 (issue 53)",
        })
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cell", default="point_size=0.04", help="cell of sweeps/point_size.yaml to train")
    parser.add_argument("--steps", type=int, default=40, help="timed steps per run")
    parser.add_argument("--rounds", type=int, default=3, help="runs per mode, the modes alternating")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(_train(args.cell, args.steps)))
        return 0
    machine = machine_record()
    print(f"{machine['cpu_model']} ({machine['cpu_isa']}); {machine['math_libraries']}; one thread")
    for row in cpu_modes(args.cell, args.steps, args.rounds):
        print(f"| {row['benchmark']} | {row['case']} | {row['without_s']:.4f} | {row['with_s']:.4f} "
              f"| {row['ratio']:.3f} | {row['target']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
