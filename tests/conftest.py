"""Shared fixtures: the real configs shrunk to test size (lightning-hydra-template's habit)."""

from __future__ import annotations

import pytest
import torch

from cdm.config import Config, load_config

TINY = {
    "data": {"image_size": 32, "num_points": 128, "train_objects": 6, "val_objects": 2, "categories": ["chair", "mug"]},
    "model": {"feature_dim": 8, "widths": [16, 16], "voxel_resolutions": [8, 4], "time_embed_dim": 16},
    "diffusion": {"prediction": "x0", "sample_steps": 5},
    "priors": {"num_views": 2, "render_size": 32},
    "train": {"threads": 1, "steps": 40, "batch_size": 4, "warmup_steps": 5, "eval_every": 20, "log_every": 10, "lr": 3e-3},
    "eval": {"num_objects": 1, "num_points": 128, "save_clouds": 1},
}


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
