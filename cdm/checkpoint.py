"""Checkpoints: one folder of safetensors weights and a JSON record, written atomically, read back typed and safely.

A checkpoint holds everything needed to use or continue a run without anything else (nanoGPT's
habit): the resolved config, the step, the voxel back-end the weights were trained with (the
back-ends compute different functions) and the weights; a CDM run adds its EMA weights, optimiser,
schedule and RNG states, a BDM category prior its ``kind`` and ``category``. A folder holds

- ``model.safetensors``: the network's ``state_dict`` (``safetensors.torch.load_file`` reads it);
- ``ema.safetensors``: the EMA weights, where the run kept them;
- ``training.safetensors``: the optimiser's moments and the RNG states, in a training checkpoint only;
- ``checkpoint.json``: everything else (config, step, back-end, precision, encoder record, loss scale,
  the optimiser's groups and the schedule), the tensors named by their key in ``training.safetensors``
  (:func:`cdm.io.safetensors.encode_tree`). Written last: a folder without it holds no checkpoint.

No file holds code, and every one is read through :mod:`cdm.io` (:func:`cdm.io.safetensors.read_safetensors`,
:func:`cdm.io.json.read_json`). A ``checkpoint.pt`` of cdm 0.1.0 (one ``torch.save``) is not read here:
:func:`convert_legacy` (``cdm-lab convert``) rewrites it, reading it inertly (:func:`cdm.io.torch.load_tensors`).
"""

from __future__ import annotations

import json
import math
import re
import shutil
import stat
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor

from cdm.config import Config, load_config
from cdm.data.priors2d import PRIOR_2D_CHANNELS
from cdm.diffusion import GaussianDiffusion
from cdm.io.json import read_json
from cdm.io.safetensors import decode_tree, encode_tree, read_safetensors, write_safetensors
from cdm.io.torch import load_tensors
from cdm.io.write import make_folder, write_atomic
from cdm.model import CDMNetwork, check_encoder_record
from cdm.model.state_dicts import checked_state_dict, load_into
from cdm.runtime import AUTOCAST_DTYPES, resolve_device, resolve_precision

__all__ = [
    "CHECKPOINT_FILE",
    "Checkpoint",
    "LoadedNetwork",
    "LEGACY_FILE",
    "checkpoint_file",
    "convert_legacy",
    "load_checkpoint",
    "load_network",
    "network_config",
    "save_checkpoint",
    "save_step",
]

CHECKPOINT_FILE = "checkpoint.json"
"""The record that marks a checkpoint folder (module docstring)."""
LEGACY_FILE = "checkpoint.pt"
"""What cdm 0.1.0 wrote instead: one ``torch.save`` of the same fields (:func:`convert_legacy`)."""
FORMAT = "cdm-checkpoint/2"
"""``checkpoint.json``'s ``format``: 2, the safetensors folder (1 was 0.1.0's ``checkpoint.pt``)."""
WEIGHTS = ("model", "ema")
"""Fields kept in a safetensors file of their own, ``<field>.safetensors``."""
TRAINING_FILE = "training.safetensors"
_OUT_DIR = "train.out_dir"
_STEP = re.compile(r"step_[0-9]{7}")
_REQUIRED = ("config", "step", "voxel_backend", "model")


@dataclass(frozen=True)
class Checkpoint:
    """The contents of one checkpoint folder."""

    config: dict[str, Any]
    """The resolved config as saved (:meth:`Config.to_dict`)."""
    step: int
    """Optimiser steps taken."""
    voxel_backend: str
    """The voxel back-end the weights were trained with (``dense`` or ``sparse``)."""
    model: dict[str, Tensor]
    """The network's ``state_dict``."""
    ema: dict[str, Tensor] | None = None
    """EMA weights (``train.ema_decay``), or None."""
    optimizer: dict[str, Any] | None = None
    scheduler: dict[str, Any] | None = None
    generator: Tensor | None = None
    """State of the training noise generator."""
    torch_rng: Tensor | None = None
    """State of torch's global CPU RNG."""
    kind: str | None = None
    """``category_prior`` for a BDM prior (:mod:`cdm.prior_model`); None for a CDM run."""
    category: str | None = None
    """The one category a prior models."""
    precision: str | None = None
    """The ``train.precision`` the run computed in, as resolved on its device (``fp16`` asked on a CPU
    trains in ``fp32``); None in checkpoints written before it was recorded (fp32)."""
    loss_scale: dict[str, Any] | None = None
    """fp16's dynamic loss scale (``torch.amp.GradScaler.state_dict()``: plain numbers), else None."""
    compute_s: float = 0.0
    """Seconds of compute training had spent when this step was saved (:data:`cdm.metric_names.COMPUTE_METRIC`'s
    unit): a run resumed under ``train.compute_budget_s`` goes on counting from it. 0 in checkpoints written before
    it was recorded."""
    encoder: dict[str, Any] | None = None
    """The image encoder's record (``CDMNetwork.encoder.record``): ``{"encoder": "cnn"}``, or
    ``{"encoder": "vit_s16", "weights_sha256": ...}`` for the frozen ViT, whose weights are not in
    ``model``; None in checkpoints written before it was recorded (read as the CNN)."""

    @property
    def weights(self) -> dict[str, Tensor]:
        """The weights to evaluate with: EMA when the run kept them, else the trained ones."""
        return self.ema or self.model

    def for_inference(self) -> Checkpoint:
        """What evaluating and reconstructing read (config, step, back-end, weights, EMA, precision, encoder),
        without the state that only continues training (optimiser, schedule, RNGs, loss scale; AdamW keeps two
        moments per weight) and without ``train.out_dir``: the folder the training wrote to is no part of the
        model (:func:`cdm.provenance.config_hash` leaves it out too); reading it back gives the default."""
        train = {k: v for k, v in self.config.get("train", {}).items() if k != "out_dir"}
        return replace(self, config={**self.config, "train": train}, optimizer=None, scheduler=None, generator=None,
                       torch_rng=None, loss_scale=None)


def save_checkpoint(checkpoint: Checkpoint, folder: str | Path) -> Path:
    """Write the checkpoint's files into ``folder`` (module docstring), each through a temporary file renamed
    when complete and ``checkpoint.json`` last, so a reader sees a whole checkpoint; files of an earlier
    checkpoint there that this one lacks (``ema``, ``training``) are removed. Returns ``checkpoint.json``."""
    folder = make_folder(Path(folder), _OUT_DIR)
    record = {"format": FORMAT}
    for name in WEIGHTS:
        weights = getattr(checkpoint, name)
        record[name] = None if weights is None else f"{name}.safetensors"
        if weights is not None:
            write_safetensors(folder / record[name], dict(weights), {"format": "pt"}, _OUT_DIR)
    rest, tensors = encode_tree({f.name: getattr(checkpoint, f.name) for f in fields(checkpoint)
                                 if f.name not in WEIGHTS})
    record["training"] = TRAINING_FILE if tensors else None
    if tensors:
        write_safetensors(folder / TRAINING_FILE, tensors, {}, _OUT_DIR)
    file = folder / CHECKPOINT_FILE
    write_atomic(file, json.dumps({**record, **rest}, indent=1) + "\n", _OUT_DIR)
    for stale in [f"{name}.safetensors" for name in WEIGHTS if record[name] is None] + [TRAINING_FILE] * (not tensors):
        (folder / stale).unlink(missing_ok=True)  # unlink removes a link, never its target
    return file


def save_step(checkpoint: Checkpoint, out_dir: Path, keep: int = 2) -> Path:
    """Write ``out_dir/checkpoints/step_<step>`` (7 digits) as ``.tmp_step_<step>`` renamed when complete, then
    remove all but the newest ``keep`` of the earlier steps; returns the step's folder.

    ``out_dir`` may be shared, so nothing is written, renamed or removed through a link planted in it:
    ``checkpoints`` must lie below ``out_dir`` (checked before it is made); a link or a file where a step's
    folder goes is refused, not followed; old steps are this run's own: real folders named ``step_<7
    digits>`` up to this step (a link, or a planted later step, is neither removed nor counted).

    Raises:
        ValueError: one of those links or files; the message starts with ``train.out_dir:``.
    """
    root = make_folder(out_dir / "checkpoints", _OUT_DIR, within=out_dir)
    final = root / f"step_{checkpoint.step:07d}"
    tmp = root / f".tmp_{final.name}"
    _remove_folder(tmp)  # a killed run's leftover
    tmp.mkdir()  # a link planted since is not followed: mkdir fails on any existing name
    save_checkpoint(checkpoint, tmp)
    _remove_folder(final)
    tmp.rename(final)  # a checkpoint directory is either complete or absent
    steps = sorted(p for p in root.iterdir() if _STEP.fullmatch(p.name) and int(p.name[5:]) <= checkpoint.step
                   and stat.S_ISDIR(p.lstat().st_mode))
    for old in steps[:-keep]:
        shutil.rmtree(old)
    return final


def _remove_folder(path: Path) -> None:
    """Remove the folder ``path`` if it exists (``shutil.rmtree`` removes the links inside, not their
    targets); refuse a link or a file there."""
    try:
        mode = path.lstat().st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISDIR(mode):
        kind = "a symbolic link" if stat.S_ISLNK(mode) else "not a folder"
        raise ValueError(f"{_OUT_DIR}: {path} is {kind} where train keeps its checkpoints; remove it (train never "
                         "writes or removes through one)")
    shutil.rmtree(path)


def checkpoint_file(path: str | Path) -> Path:
    """The ``checkpoint.json`` a user means by ``path``: the file itself, or the one in that folder."""
    path = Path(path)
    return path / CHECKPOINT_FILE if path.is_dir() else path


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read a checkpoint folder (or its ``checkpoint.json``) through :mod:`cdm.io`: JSON and safetensors only.

    Raises:
        ValueError: a missing or unreadable file, a 0.1.0 ``checkpoint.pt`` (convert it: :func:`convert_legacy`),
            not a CDM checkpoint, or weights (``model``, ``ema``) that are not finite tensors; the message
            starts with ``checkpoint:`` and names the file.
    """
    file = checkpoint_file(path)
    legacy = file if file.suffix in (".pt", ".pth") else file.parent / LEGACY_FILE
    if legacy == file or (not file.exists() and legacy.exists()):
        raise ValueError(f"checkpoint: {legacy} was written by cdm 0.1.0 (torch.save); convert it once with "
                         f"`cdm-lab convert {legacy} NEW_FOLDER` and pass NEW_FOLDER")
    if not file.exists():
        raise ValueError(f"checkpoint: {file} does not exist; pass a checkpoint folder or its {CHECKPOINT_FILE}")
    where = f"checkpoint: {file}"
    record = read_json(file, "checkpoint")
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise ValueError(f"{where} is not a CDM checkpoint (its format is not {FORMAT!r})")
    missing = set(_REQUIRED) - set(record)
    if missing:
        raise ValueError(f"{where} is not a CDM checkpoint (missing {', '.join(sorted(missing))})")
    state = decode_tree({f.name: record[f.name] for f in fields(Checkpoint) if f.name in record
                         and f.name not in WEIGHTS}, _training(record, file), where)
    for name in WEIGHTS:
        if record.get(name) is not None:
            if record[name] != f"{name}.safetensors":
                raise ValueError(f"{where}: its {name!r} is {str(record[name])[:80]!r}; expected {name}.safetensors")
            weights, _ = read_safetensors(file.parent / record[name], "checkpoint")
            state[name] = checked_state_dict(weights, f"checkpoint: {file.parent / record[name]}")
    if type(state["step"]) is not int or not isinstance(state["voxel_backend"], str):
        raise ValueError(f"{where}: its step must be a whole number and its voxel_backend a name")
    if type(state.get("compute_s", 0.0)) not in (int, float) or not 0 <= state.get("compute_s", 0.0) < math.inf:
        raise ValueError(f"{where}: its compute_s must be a finite number of seconds, at least 0")
    return Checkpoint(**state)


def _training(record: dict[str, Any], file: Path) -> dict[str, Tensor]:
    """The tensors of ``training.safetensors`` where ``record`` names it."""
    if record.get("training") is None:
        return {}
    if record["training"] != TRAINING_FILE:
        raise ValueError(f"checkpoint: {file}: its 'training' is {str(record['training'])[:80]!r}; expected "
                         f"{TRAINING_FILE}")
    return read_safetensors(file.parent / TRAINING_FILE, "checkpoint")[0]


def convert_legacy(old: str | Path, new: str | Path) -> Path:
    """Rewrite a cdm 0.1.0 checkpoint (its folder or ``checkpoint.pt``, read inertly: tensors and plain data,
    nothing executed) as a checkpoint folder ``new``; returns ``new``'s ``checkpoint.json``.

    Raises:
        ValueError: ``old`` is no 0.1.0 checkpoint; the message starts with ``checkpoint:`` and names the file.
    """
    file = Path(old) / LEGACY_FILE if Path(old).is_dir() else Path(old)
    state = load_tensors(file, f"checkpoint: {file}", "cdm 0.1.0 checkpoint", "Convert only checkpoints of cdm")
    missing = set(_REQUIRED) - set(state if isinstance(state, dict) else ())
    if missing:
        raise ValueError(f"checkpoint: {file} is not a cdm 0.1.0 checkpoint (missing {', '.join(sorted(missing))})")
    for name in WEIGHTS:
        if state.get(name) is not None:
            if not isinstance(state[name], dict):
                raise ValueError(f"checkpoint: {file} holds a {type(state[name]).__name__} as {name!r}, not a "
                                 "state dict")
            state[name] = checked_state_dict(state[name], f"checkpoint: {file} ({name!r})")
    return save_checkpoint(Checkpoint(**{f.name: state[f.name] for f in fields(Checkpoint) if f.name in state}), new)


def network_config(checkpoint: Checkpoint, overrides: dict[str, Any] | None = None) -> Config:
    """The checkpoint's config with dotted ``overrides``, its voxel back-end fixed to the trained one."""
    return load_config(checkpoint.config, {**(overrides or {}), "model.voxel_backend": checkpoint.voxel_backend})


class LoadedNetwork(NamedTuple):
    """A CDM checkpoint ready to sample: config, network (eval mode, on ``device``), schedule, device."""

    config: Config
    network: CDMNetwork
    diffusion: GaussianDiffusion
    device: torch.device


def load_network(path: str | Path | None, overrides: dict[str, Any] | None = None) -> LoadedNetwork:
    """The network of a CDM checkpoint (EMA weights when present) on ``train.device``, sampling in
    ``train.precision`` (as the run trained, unless overridden).

    Args:
        path: a checkpoint folder or its ``checkpoint.json``; None builds the network the default config
            with ``overrides`` names, with the weights of its ``model.init_from`` (PC²'s checkpoint).
        overrides: dotted config fields applied to the saved config (e.g. ``eval.num_objects``,
            ``train.device``); the voxel back-end stays the trained one.
    Raises:
        ValueError: unreadable file, a category prior instead of a CDM checkpoint, a bad override, or
            frozen encoder weights other than those it was trained with (``model.encoder_weights``).
    """
    checkpoint = None
    if path is None:
        cfg = load_config(None, overrides)
        if cfg.model.init_from is None:
            raise ValueError("model.init_from: a network without a checkpoint needs PC²'s weights to start from")
    else:
        checkpoint = load_checkpoint(path)
        if checkpoint.kind is not None:
            raise ValueError(f"checkpoint: {path} holds a {checkpoint.kind} ({checkpoint.category}), not a CDM network")
        cfg = network_config(checkpoint, overrides)  # its voxel back-end pinned: the device picks none
    device = resolve_device(cfg.train.device)
    autocast = AUTOCAST_DTYPES[resolve_precision(cfg.train.precision, device)]
    network = CDMNetwork(cfg.model, PRIOR_2D_CHANNELS[cfg.priors.prior_2d], device=device, autocast=autocast)
    if checkpoint is not None:
        check_encoder_record(checkpoint.encoder, network.encoder.record)
        load_into(network, checkpoint.weights, f"checkpoint: {path}")
    return LoadedNetwork(cfg, network.to(device).eval(), GaussianDiffusion.from_config(cfg.diffusion), device)
