"""What it takes to re-run a training exactly: code version, config hash, data fingerprint, versions, device, seeds
and the machine.

:func:`fit` hands :func:`run_record` to its callbacks once, before the first step; the sweep runner
stores it on each MLflow child run and ``cdm-lab rerun`` checks it before running the cell
again. All values are strings so they fit tracking tags.

The machine matters on CPU: MKL and oneDNN pick their kernels per CPU at run time, so the same code,
config and packages gave other numbers on an Intel Xeon (AVX512, AMX) than on an AMD EPYC
(docs/local-results.md). :func:`machine_record` names what picks them.
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sysconfig
from importlib.metadata import PackageNotFoundError, distributions, version
from pathlib import Path

import torch

from cdm.config import Config
from cdm.data.views import ObjectDataset
from cdm.digest import json_digest

__all__ = ["KERNEL_PINS", "MACHINE_KEYS", "PACKAGES", "code_version", "config_hash", "installed_packages",
           "machine_record", "run_record"]

PACKAGES = ("torch", "numpy", "ray", "optuna", "mlflow")
"""Packages whose versions are recorded (those that can change a result or how it was produced)."""


MACHINE_KEYS = ("cpu_model", "cpu_isa", "cpu_capability", "math_libraries", "kernel_pins", "packages_digest")
"""Keys of :func:`machine_record`: what picks the kernels a run's float sums go through, and every package."""

KERNEL_PINS = ("MKL_CBWR", "MKL_ENABLE_INSTRUCTIONS", "ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY")
"""Environment variables that pin MKL's code path, oneDNN's ISA and ATen's kernels (read when the process starts)."""

ISA_FLAGS = ("avx2", "avx_vnni", "avx512f", "avx512_vnni", "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16")
"""CPU flags (``/proc/cpuinfo``) that change which kernels MKL and oneDNN run: a virtual machine's model name
(``Intel(R) Xeon(R) Processor``) may not say which generation it is."""


def _cpu() -> tuple[str, str]:
    """(model name, the :data:`ISA_FLAGS` it has); Linux reads ``/proc/cpuinfo``, elsewhere the ISA is unknown."""
    try:
        info = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return platform.processor() or platform.machine() or "unknown", "unknown"
    model = re.search(r"^model name\s*:\s*(.+)$", info, re.MULTILINE)
    flags = re.search(r"^(?:flags|Features)\s*:\s*(.*)$", info, re.MULTILINE)
    have = set(flags.group(1).split()) if flags else set()
    return (model.group(1).strip() if model else platform.machine() or "unknown",
            " ".join(f for f in ISA_FLAGS if f in have) or "none of " + " ".join(ISA_FLAGS[:3]))


def math_libraries() -> str:
    """torch's BLAS and oneDNN builds in one short line, e.g. ``BLAS mkl, MKL 2024.2 build 20240605, oneDNN 3.12.0
    (80afa71)`` (from ``torch.__config__.show()``)."""
    shown = torch.__config__.show()
    blas = re.search(r"BLAS_INFO=(\w+)", shown)
    parts = [f"BLAS {blas.group(1) if blas else 'unknown'}"]
    if mkl := re.search(r"Math Kernel Library Version ([\d.]+)\D*?Build (\d+)", shown):
        parts.append(f"MKL {mkl.group(1)} build {mkl.group(2)}")
    if dnn := re.search(r"MKL-DNN v([\d.]+) \(Git Hash (\w{7})", shown):
        parts.append(f"oneDNN {dnn.group(1)} ({dnn.group(2)})")
    return ", ".join(parts)


def _site_dirs() -> list[str]:
    """The environment's site-packages folders (pure and platform), where ``pip install`` puts packages."""
    return list(dict.fromkeys(sysconfig.get_paths()[k] for k in ("purelib", "platlib")))


def installed_packages(paths: list[str] | None = None) -> list[str]:
    """Every distribution installed in ``paths`` (default: the environment's site-packages) as ``name==version``
    (names normalised, PEP 503), sorted; of one name, the first found, as ``import`` would.

    Only the site-packages, not ``sys.path``: importing Ray puts its private copies of packages
    (``ray/thirdparty_files``) on the path, which would make the list depend on what the process imported.
    """
    found: dict[str, str] = {}
    for dist in distributions(path=_site_dirs() if paths is None else paths):
        name = re.sub(r"[-_.]+", "-", dist.metadata["Name"] or "").lower()
        if name:
            found.setdefault(name, dist.version)
    return [f"{name}=={v}" for name, v in sorted(found.items())]


def machine_record() -> dict[str, str]:
    """What picks the kernels on this machine (keys :data:`MACHINE_KEYS`): CPU model and ISA flags, ATen's CPU
    capability, the BLAS/oneDNN build, the :data:`KERNEL_PINS` set, and a digest of :func:`installed_packages`."""
    model, isa = _cpu()
    return {
        "cpu_model": model,
        "cpu_isa": isa,
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "math_libraries": math_libraries(),
        "kernel_pins": " ".join(f"{k}={os.environ[k]}" for k in KERNEL_PINS if k in os.environ) or "none",
        "packages_digest": json_digest(installed_packages()),
    }


def config_hash(config: Config) -> str:
    """Hash of the resolved config, leaving out ``train.out_dir`` (where files go changes no result)."""
    tree = config.to_dict()
    tree["train"] = {k: v for k, v in tree["train"].items() if k != "out_dir"}
    return json_digest(tree)


def code_version(root: Path | None = None) -> dict[str, str]:
    """``git_commit`` and ``git_dirty`` (``true``/``false``) of the checkout at ``root`` (default: this package's).

    ``unknown`` for both outside a git checkout (an installed wheel, a ``ray job`` working-dir copy).
    """
    root = root or Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, check=True
        )
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        return {"git_commit": "unknown", "git_dirty": "unknown"}
    return {"git_commit": commit.stdout.strip(), "git_dirty": str(bool(status.stdout.strip())).lower()}


def _version(package: str) -> str:
    try:
        return version(package)
    except PackageNotFoundError:
        return "not installed"


def run_record(config: Config, train: ObjectDataset, val: ObjectDataset, device: torch.device) -> dict[str, str]:
    """The reproducibility record of one training run (keys are stable; values strings)."""
    record = {
        "config_hash": config_hash(config),
        "data_kind": config.data.kind,
        "data_fingerprint": f"train {train.fingerprint()} val {val.fingerprint()}",
        "device": str(device) if device.type != "cuda" else f"cuda ({torch.cuda.get_device_name(device)})",
        "torch_threads": str(torch.get_num_threads()),
        "seed_train": str(config.train.seed),
        "seed_data": str(config.data.seed),
        "seed_eval": str(config.eval.seed),
    }
    record.update({f"version_{p}": _version(p) for p in PACKAGES})
    record.update(machine_record())
    return record
