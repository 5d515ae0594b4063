"""Where and how a run computes: the device, its arithmetic precision, torch's CPU threads and the
global seed, set once."""

from __future__ import annotations

import logging

import torch

from cdm.config import TrainConfig

__all__ = ["AUTOCAST_DTYPES", "resolve_device", "resolve_precision", "start_run"]

log = logging.getLogger(__name__)

AUTOCAST_DTYPES: dict[str, torch.dtype | None] = {"fp32": None, "fp16": torch.float16, "bf16": torch.bfloat16}
"""``train.precision`` → the dtype the image encoder and the denoiser autocast to (None: no autocast)."""


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


def resolve_precision(precision: str, device: torch.device) -> str:
    """``train.precision`` as the run on ``device`` computes it: ``fp16`` needs CUDA (PC²'s fp16 is a
    CUDA recipe; CPU half-precision kernels are slow or missing), so elsewhere the run says so once on
    stderr and trains in ``fp32``; ``fp32`` and ``bf16`` as given."""
    if precision == "fp16" and device.type != "cuda":
        log.warning("train.precision=fp16 needs CUDA; on device %s this run trains and samples in fp32 "
                    "(use bf16 for mixed precision on this device)", device)
        return "fp32"
    return precision
