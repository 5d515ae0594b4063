"""Run the benchmarks and print one Markdown table; write the rows as JSON.

    python benchmarks/run.py [--quick] [--only NAME ...] [--device cpu|cuda] [--out DIR]

Every row compares two variants measured side by side in this process (see benchmarks/common.py):
``a`` and ``b`` are median seconds, ``ratio`` the median of per-pair ratios ``b / a`` (the quality rows
hold CD×1000 values instead: ``a`` the baseline's, ``b`` the model's; the memory rows peak RSS in MB).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.blend import blend_overhead  # noqa: E402
from benchmarks.cpu_modes import cpu_modes  # noqa: E402
from benchmarks.kornia_ops import kornia_ops  # noqa: E402
from benchmarks.lean_step import lean_step  # noqa: E402
from benchmarks.loader import loader_speed  # noqa: E402
from benchmarks.memory import peak_rss  # noqa: E402
from benchmarks.metrics import metrics_vs_scipy  # noqa: E402
from benchmarks.model_logging import model_logging  # noqa: E402
from benchmarks.quality import quick_config_quality  # noqa: E402
from benchmarks.render import rendering  # noqa: E402
from benchmarks.scaling import paper_scaling  # noqa: E402
from benchmarks.step_reference import step_vs_reference  # noqa: E402
from benchmarks.sweep_efficiency import sweep_efficiency  # noqa: E402
from benchmarks.throughput import throughput  # noqa: E402
from benchmarks.training_step import prior_overhead, voxel_backends  # noqa: E402

BENCHMARKS = {
    "metrics": lambda quick, out: metrics_vs_scipy(quick),
    "prior_overhead": prior_overhead,
    "voxel_backends": voxel_backends,
    "step_reference": step_vs_reference,
    "lean_step": lean_step,
    "memory": peak_rss,
    "render": rendering,
    "sweep_efficiency": sweep_efficiency,
    "paper_scaling": paper_scaling,
    "blend": blend_overhead,
    "loader": loader_speed,
    "kornia_ops": kornia_ops,
    "model_logging": model_logging,
}
# Minutes-long training runs: only with --only.
SLOW = {"quality": quick_config_quality, "cpu_modes": lambda quick, out: cpu_modes(steps=10 if quick else 40)}
# Run on --device (the others measure CPU costs per thread).
ON_DEVICE = {"throughput": throughput}


def to_markdown(rows: list[dict]) -> str:
    lines = ["| benchmark | case | a (s) | b (s) | ratio | target |", "|---|---|---|---|---|---|"]
    for r in rows:
        if r["benchmark"] != "paper scaling":
            lines.append(
                f"| {r['benchmark']} | {r['case']} | {r['without_s']:.4f} | {r['with_s']:.4f} | {r['ratio']:.3f} "
                f"| {r['target']} |"
            )
    scaling = [r for r in rows if r["benchmark"] == "paper scaling"]
    if scaling:
        lines += [
            "",
            f"Paper profile, GPU figures: {scaling[0]['device']} (benchmarks/scaling.py states the assumptions):",
            "",
            "| spec | trials | GPU-h per trial | wall h, 1 GPU | wall h, 8 GPUs | wall h, 64 GPUs |",
            "|---|---|---|---|---|---|",
        ]

        def hours(value: float | None, digits: int) -> str:
            return "not measured" if value is None else f"{value:.{digits}f}"

        lines += [
            f"| {r['spec']} | {r['trials']} | {hours(r['trial_gpu_hours'], 2)} | {hours(r['wall_h_1_gpus'], 1)} | "
            f"{hours(r['wall_h_8_gpus'], 1)} | {hours(r['wall_h_64_gpus'], 1)} |"
            for r in scaling
        ]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer sizes and repeats (about a minute)")
    parser.add_argument("--only", nargs="*", choices=sorted({**BENCHMARKS, **SLOW, **ON_DEVICE}),
                        help="run only these (quality: only this way)")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="device of the throughput benchmark")
    parser.add_argument("--out", default="benchmarks/out", help="folder for results.json (and gpu_costs.json on cuda)")
    args = parser.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        print("error: --device cuda: no CUDA device is available", file=sys.stderr)
        return 2
    torch.set_num_threads(1)  # figures are per CPU thread, comparable across machines
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for name in args.only or [*BENCHMARKS, *ON_DEVICE]:
            print(f"running {name} ...", flush=True)
            if name in ON_DEVICE:
                rows += ON_DEVICE[name](args.quick, str(out), args.device)
            else:
                rows += {**BENCHMARKS, **SLOW}[name](args.quick, scratch)
    (out / "results.json").write_text(json.dumps(rows, indent=2))
    print(to_markdown(rows))
    print(f"\nrows written to {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
