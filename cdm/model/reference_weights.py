"""Load PC²'s and PVD's (BDM's category prior) point-cloud model weights into :class:`PVCNN2Denoiser`.

Both references save the same PVCNN2 (BDM copies PVD's modules; PVD's and PC²'s ``pvcnn_utils`` are
identical), under different containers and prefixes:

- PC² (lukemelas/projection-conditioned-point-cloud-diffusion, ``experiments/main.py``): a dict whose
  ``"model"`` is the whole diffusion model's state dict; the denoiser's keys start with
  ``point_cloud_model.model.`` (``module.`` before it when saved from a ``DistributedDataParallel``).
  Its input channels are ``3 + S`` with ``S`` = RGB 3 + ViT-S/16 384 + mask 1 + distance 1 = 389 by
  default (``experiments/model/projection_model.py``).
- PVD (alexzhou907/PVD, ``train_generation.py``; BDM's ``experiments/pvd/__init__.py`` loads the same):
  ``"model_state"`` (BDM also accepts ``"prior_model"``) with keys ``model.module.`` + PVCNN2's, an
  unconditional network on xyz alone (``extra_feature_channels=0``).

Our module names equal PVCNN2's (``tests/test_pvcnn2.py`` holds PC²'s list), so mapping a key is
stripping its prefix. Anything else — a missing or unexpected key, a different shape — is refused with
an error naming the first offending key in the network's order.

Files are read with :func:`cdm.io.torch.load_inert`: PC²'s checkpoints also pickle their OmegaConf
``cfg``, which is kept as inert data (never constructed), and a file whose pickle would call anything
else is refused.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from torch import Tensor

from cdm.io.torch import load_inert
from cdm.model.pvcnn2 import PVCNN2Denoiser
from cdm.model.state_dicts import checked_state_dict

__all__ = [
    "Reference",
    "denoiser_from_reference",
    "load_reference_checkpoint",
    "load_reference_weights",
    "reference_in_channels",
    "reference_state_dict",
]

Reference = Literal["pc2", "pvd"]

# Where each reference keeps the network in a saved checkpoint, and the key prefixes it may carry
# (longest first; "" is a bare PVCNN2 state dict).
_CONTAINERS: dict[str, tuple[str, ...]] = {"pc2": ("model",), "pvd": ("model_state", "prior_model")}
_PREFIXES: dict[str, tuple[str, ...]] = {
    "pc2": ("module.point_cloud_model.model.", "point_cloud_model.model.", ""),
    "pvd": ("model.module.", "module.", "model.", ""),
}
_FIRST_LAYER = "sa_layers.0.0.point_features.layers.0.weight"  # (32, 3 + S, 1): present in every PVCNN2


def reference_state_dict(
    checkpoint: Mapping[str, Any], reference: Reference, label: str = "the checkpoint"
) -> dict[str, Tensor]:
    """The PVCNN2 weights of a loaded reference checkpoint, under our (= PVCNN2's) key names.

    Args:
        checkpoint: what the reference saved (the whole dict), its model state dict, or a bare PVCNN2
            state dict.
        reference: ``pc2`` or ``pvd`` (PVD's unconditional PVCNN2, also BDM's category prior).
        label: the file, as a refusal names it.
    Raises:
        ValueError: no PVCNN2 weights under any of the reference's prefixes, or where they are, a key that
            is not a string, a value that is not a tensor or a weight that is not finite
            (:func:`cdm.model.state_dicts.checked_state_dict`).
    """
    if reference not in _CONTAINERS:
        raise ValueError(f"reference must be 'pc2' or 'pvd', got {reference!r}")
    state: Mapping[Any, Any] = checkpoint
    for container in _CONTAINERS[reference]:
        if isinstance(checkpoint.get(container), Mapping):
            state = checkpoint[container]
            break
    for prefix in _PREFIXES[reference]:
        if prefix + _FIRST_LAYER in state:
            # Checked before the prefix is cut, so a refusal names the key as the file spells it; a key that
            # is no string has no prefix to test and is refused.
            kept = {k: v for k, v in state.items() if not isinstance(k, str) or k.startswith(prefix)}
            weights = checked_state_dict(kept, label)
            return {k[len(prefix) :]: v for k, v in weights.items() if k.startswith(prefix)}
    raise ValueError(
        f"no {reference} PVCNN2 weights found: expected a key '<prefix>{_FIRST_LAYER}' with a prefix in "
        f"{list(_PREFIXES[reference])} inside {list(_CONTAINERS[reference])} or at the top level"
    )


def reference_in_channels(state: Mapping[str, Tensor]) -> int:
    """Per-point conditioning channels ``S`` of a PVCNN2 state dict (its first layer sees ``3 + S``)."""
    return int(state[_FIRST_LAYER].shape[1]) - 3


def load_reference_weights(model: PVCNN2Denoiser, state: Mapping[str, Tensor]) -> None:
    """Copy a PVCNN2 state dict (our key names, :func:`reference_state_dict`) into ``model``.

    Raises:
        ValueError: naming the first key, in the network's order, that is missing or has another
            shape, else the first unexpected key. Nothing is copied then.
    """
    expected = model.state_dict()
    for name, tensor in expected.items():
        if name not in state:
            raise ValueError(
                f"reference weights lack {name!r} (shape {tuple(tensor.shape)}) that the pvcnn2 denoiser has"
            )
        if tuple(state[name].shape) != tuple(tensor.shape):
            raise ValueError(
                f"reference weight {name!r} has shape {tuple(state[name].shape)}, the pvcnn2 denoiser's is "
                f"{tuple(tensor.shape)}: build it with the reference's input channels and multipliers"
            )
    unexpected = [k for k in state if k not in expected]
    if unexpected:
        raise ValueError(f"reference weights hold {unexpected[0]!r}, which the pvcnn2 denoiser does not have")
    model.load_state_dict(state)


def load_reference_checkpoint(path: str | Path, reference: Reference) -> dict[str, Tensor]:
    """Read a reference checkpoint file on CPU and return its PVCNN2 weights under our names.

    Raises:
        ValueError: the file's pickle would call something other than what tensors and a config need
            (:func:`cdm.io.torch.load_inert`), torch cannot read it, or it holds no PVCNN2 weights.
    """
    checkpoint = load_inert(Path(path), str(path), "torch file")
    if not isinstance(checkpoint, Mapping):
        raise ValueError(f"{path} holds a {type(checkpoint).__name__}, not a checkpoint dict or state dict")
    return reference_state_dict(checkpoint, reference, str(path))


def denoiser_from_reference(path: str | Path, reference: Reference) -> PVCNN2Denoiser:
    """A :class:`PVCNN2Denoiser` holding a reference checkpoint's weights, input channels read from it.

    The references trained with both multipliers 1 (PC²'s ``point_cloud_model.py``, PVD's defaults).
    """
    state = load_reference_checkpoint(path, reference)
    model = PVCNN2Denoiser(reference_in_channels(state))
    load_reference_weights(model, state)
    return model
