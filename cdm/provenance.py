"""What it takes to re-run a training exactly: code version, config hash, data fingerprint, versions, device, seeds.

:func:`fit` hands :func:`run_record` to its callbacks once, before the first step; the sweep runner
stores it on each MLflow child run and ``sweeps/run.py --rerun`` checks it before running the cell
again. All values are strings so they fit tracking tags.
"""

from __future__ import annotations

import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import torch

from cdm.config import Config
from cdm.data.views import ObjectDataset
from cdm.digest import json_digest

__all__ = ["PACKAGES", "code_version", "config_hash", "run_record"]

PACKAGES = ("torch", "numpy", "ray", "optuna", "mlflow")
"""Packages whose versions are recorded (those that can change a result or how it was produced)."""


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
    return record
