"""Where and how a run computes: the device, torch's CPU threads and the global seed, set once."""

from __future__ import annotations

import torch

from cdm.config import TrainConfig

__all__ = ["resolve_device", "start_run"]


def resolve_device(name: str) -> torch.device:
    """``train.device`` as a torch device: ``auto`` takes CUDA when present."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("train.device: cuda requested but no CUDA device is available; use auto or cpu")
    return torch.device(name)


def start_run(cfg: TrainConfig) -> torch.device:
    """Set ``train.threads`` and seed torch's global RNG with ``train.seed`` (weight initialisation);
    returns the resolved ``train.device``."""
    device = resolve_device(cfg.device)
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    return device
