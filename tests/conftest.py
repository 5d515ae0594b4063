"""Shared fixtures: the real configs shrunk to test size (lightning-hydra-template's habit)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml

from cdm.config import Config, apply_overrides, load_config

PROFILES = Path(__file__).resolve().parents[1] / "sweeps" / "profiles.yaml"

# What the tests change in the `smoke` profile, and why. The numbers the tests assert on were set
# with these values, so they stay.
TEST_CHANGES = {
    "data.categories": ["chair", "mug"],  # mug: the category-prior tests train one
    "data.train_objects": 6,
    "data.val_objects": 2,  # two held-out objects per category: per-object rows to pair
    "model.voxel_resolutions": [8, 4],  # two different resolutions exercise both grids
    "priors.num_views": 2,  # H > 1 at the least cost
    "train.threads": 1,
    "train.steps": 40,
    "train.eval_every": 20,
    "train.warmup_steps": 5,
    "train.log_every": 10,
    "train.lr": 3e-3,  # learns within 40 steps
    "eval.save_clouds": 1,
}


def _smoke_tree() -> dict:
    """The `smoke` profile of sweeps/profiles.yaml (its overrides and budget) as a nested config tree."""
    smoke = yaml.safe_load(PROFILES.read_text())["smoke"]
    budget = {f"train.{k}": v for k, v in smoke["budget"].items()}
    return apply_overrides({}, {**smoke["overrides"], **budget, **TEST_CHANGES})


TINY = _smoke_tree()
"""The tests' config tree: the `smoke` profile shrunk further where a test needs it (``TEST_CHANGES``)."""


def tiny_config(tmp_path, **overrides) -> Config:
    """The default config shrunk to seconds of CPU time, writing under ``tmp_path``."""
    return load_config(TINY, {"train.out_dir": str(tmp_path / "run"), **overrides})


@pytest.fixture
def tiny(tmp_path) -> Config:
    return tiny_config(tmp_path)


@pytest.fixture(autouse=True)
def _one_thread():
    """Tiny tensors gain nothing from intra-op threads, and on a shared, busy CPU OpenMP's waiting
    made tests ~50x slower with two threads; restore the setting afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def script_help(monkeypatch, capsys):
    """``script_help(path, *args)``: what the file ``path`` run as ``__main__`` prints for ``*args --help``,
    the way a user who types ``python path ... --help`` sees it (exit 0 asserted)."""

    def run(path: Path, *args: str) -> str:
        import runpy
        import sys

        monkeypatch.setattr(sys, "argv", [str(path), *args, "--help"])
        monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1]))
        with pytest.raises(SystemExit) as exit_:
            runpy.run_path(str(path), run_name="__main__")
        assert exit_.value.code == 0
        return capsys.readouterr().out

    return run
