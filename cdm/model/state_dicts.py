"""A state dict read from a file, checked before a network takes it: every name a string, every weight a
tensor, every floating-point weight finite; then loaded, a misfit named in one line.

A file read as data may hold anything a pickle can: an integer key, a list where a tensor belongs, or a
NaN. Left in, those fail far from the file (``'int' object has no attribute 'startswith'``), or worse,
compute: one NaN weight turns every point NaN, and the voxel grid then indexes at −2⁶³. So each reader
of weights (PC²'s and PVD's files, MSN's ViT, CDM's checkpoints) checks them here first and names the
file and the first bad entry, in the file's order.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor, nn

__all__ = ["checked_state_dict", "load_into"]


def checked_state_dict(state: Mapping[Any, Any], label: str) -> dict[str, Tensor]:
    """``state`` as a state dict, unchanged, once every entry is a named, finite tensor.

    Args:
        state: what the file holds where its weights belong.
        label: how a refusal starts, the file and the field that named it if any, e.g.
            ``"checkpoint: /runs/a/model.safetensors"``; ``holds …`` follows.
    Raises:
        ValueError: naming ``label`` and the first key that is not a string, the first value that is not
            a tensor, or the first floating-point tensor holding NaN or ±inf.
    """
    for name, value in state.items():
        if not isinstance(name, str):
            raise ValueError(f"{label} holds a weight under the key {name!r} ({type(name).__name__}); a weight's name "
                             "is a string")
        if not isinstance(value, Tensor):
            raise ValueError(f"{label} holds weight {name!r} as a Python {type(value).__name__}, not a tensor")
        if (value.is_floating_point() or value.is_complex()) and not bool(torch.isfinite(value).all()):
            bad = "NaN" if bool(torch.isnan(value).any()) else "inf"
            raise ValueError(f"{label} holds {bad} in weight {name!r}; a network computes nothing with it")
    return dict(state)


def load_into(module: nn.Module, state: Mapping[str, Tensor], label: str) -> None:
    """``module.load_state_dict(state)``, strictly.

    Raises:
        ValueError: ``label`` (the file), then the first of torch's complaints: missing or unexpected
            keys, or a weight of another shape than the network its config builds.
    """
    try:
        module.load_state_dict(state)
    except RuntimeError as exc:  # torch lists every complaint on its own line, after a heading
        first = [*str(exc).splitlines(), ""][1].strip() or str(exc)
        raise ValueError(f"{label} holds weights its config's network cannot take: {first}") from None
