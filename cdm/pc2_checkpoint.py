"""PC²'s own checkpoint file, scored or fine-tuned as it is: recognised, its ``cfg`` read as data, and
the config that rebuilds its network.

PC²'s ``experiments/main.py`` saves ``checkpoint-latest.pth`` as ``{"model", "optimizer", "scheduler",
"epoch", "step", "best_val", "model_ema", "cfg"}``: ``model`` is the state dict of its whole diffusion
model (PVCNN2 under ``point_cloud_model.model.``, the frozen ViT-S/16 under ``feature_model.model.``
with timm's names) and ``cfg`` its Hydra/OmegaConf config, pickled. The file is read with
:func:`cdm.io.torch.load_inert`: ``cfg`` stays a tree of inert records that :func:`config_data`
turns into plain data, and a file whose pickle would run anything else is refused.

What the network is follows from PC²'s code, and ``cfg`` settles what it may change
(``experiments/config/structured.py``; its defaults stand in where a file has no ``cfg``):
PVCNN2 at both multipliers 1 (``point_cloud_model.py``), the ViT-S/16 with MSN weights, projection
conditioning on ``[2·RGB − 1, ViT features, mask, distance]`` (``projection_model.py``), ε-prediction
on a linear β schedule over 1,000 steps, sampled by DDPM over all of them with x̂₀ unclipped
(``model.py``: ``clip_sample=False``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

from cdm.config import Config, ConfigError, load_config
from cdm.io.torch import Pickled, load_inert, pickle_bytes
from cdm.model.state_dicts import checked_state_dict
from cdm.paths import input_path

__all__ = ["PC2_DEFAULTS", "PC2File", "config_data", "is_pc2_checkpoint", "read_pc2_checkpoint"]

PC2_DEFAULTS: dict[str, Any] = {
    "dataset.image_size": 224,
    "dataset.max_points": 16_384,
    "dataset.scale_factor": 1.0,
    "model.image_feature_model": "vit_small_patch16_224_msn",
    "model.use_local_colors": True,
    "model.use_local_features": True,
    "model.use_global_features": False,
    "model.use_mask": True,
    "model.use_distance_transform": True,
    "model.predict_color": False,
    "model.beta_start": 1e-5,
    "model.beta_end": 8e-3,
    "model.beta_schedule": "linear",
    "model.point_cloud_model": "pvcnn",
    "model.point_cloud_model_embed_dim": 64,
    "run.diffusion_scheduler": "ddpm",
    "run.num_inference_steps": 1000,
    "dataset.mask_images": True,
}
"""PC²'s settings that shape the network and the sampler, as ``experiments/config/structured.py`` sets them."""

# What the network must be for PC²'s weights to mean what they meant there.
_REQUIRED = {k: PC2_DEFAULTS[k] for k in (
    "model.image_feature_model", "model.use_local_colors", "model.use_local_features", "model.use_global_features",
    "model.predict_color", "model.beta_schedule", "model.point_cloud_model", "dataset.scale_factor")}
_MARKER = b"point_cloud_model.model.sa_layers.0.0.point_features.layers.0.weight"
_INTERPOLATION = re.compile(r"^\$\{([A-Za-z0-9_.]+)\}$")


def is_pc2_checkpoint(path: str | Path) -> bool:
    """Whether ``path`` is a torch file whose pickle names PC²'s first PVCNN2 weight under PC²'s model
    prefix; read from the pickle's bytes (the zip archive's ``data.pkl``, or a pre-zip file's start),
    nothing unpickled."""
    path = input_path(path)
    if not path.is_file():
        return False
    return _MARKER in pickle_bytes(path, str(path))  # a file torch's readers would refuse is refused here too


def config_data(node: Any) -> Any:
    """An OmegaConf config read by :func:`cdm.io.torch.load_inert` as plain dicts, lists and values.

    OmegaConf pickles a ``DictConfig`` / ``ListConfig`` with its children in ``_content`` and a value
    node with its value in ``_val``; anything else keeps its class name.
    """
    if isinstance(node, Pickled):
        state = node.state if isinstance(node.state, Mapping) else {}
        if "_val" in state:
            return config_data(state["_val"])
        if "_content" in state:
            return config_data(state["_content"])
        return f"<{node.name}>"
    if isinstance(node, Mapping):
        return {k: config_data(v) for k, v in node.items()}
    if isinstance(node, list | tuple):
        return [config_data(v) for v in node]
    return node


def _lookup(tree: Any, dotted: str, depth: int = 0) -> Any:
    value: Any = tree
    for part in dotted.split("."):
        if not isinstance(value, Mapping) or part not in value:
            return PC2_DEFAULTS.get(dotted)
        value = value[part]
    match = _INTERPOLATION.match(value) if isinstance(value, str) else None
    # PC² writes e.g. model.image_size: ${dataset.image_size}; a chain longer than a few links is not a config's.
    return _lookup(tree, match.group(1), depth + 1) if match and depth < 8 else value


class PC2File(NamedTuple):
    """What a PC² checkpoint says: the config fields that rebuild its network and sampler, and in words."""

    overrides: dict[str, Any]
    """Dotted :class:`cdm.config.Config` fields; ``--set`` goes on top."""
    co3d: dict[str, Any]
    """PC²'s Co3D loading (``experiments/dataset/__init__.py``), for a run that reads ``data.kind: co3d``."""
    step: int | None
    source: str
    """Where the settings came from: the file's ``cfg`` or PC²'s defaults."""
    trained_on: str

    def config(self, sets: Mapping[str, Any], source: str | Path | None = None) -> Config:
        """The run's config: PC²'s settings, then ``source`` (a YAML file) and ``sets`` on top; on Co3D
        also PC²'s way of loading it, as the network saw its inputs in training."""
        cfg = load_config(source, {**self.overrides, **sets})
        return load_config(source, {**self.overrides, **self.co3d, **sets}) if cfg.data.kind == "co3d" else cfg

    def describe(self, cfg: Config, sets: Mapping[str, Any]) -> list[str]:
        """The reference settings this run took, and each one ``--set`` changed."""
        o = self.overrides
        sampler = o["diffusion.sampler"]
        steps = (
            o.get("diffusion.sample_steps")
            if sampler == "ddim"
            else o.get("diffusion.ddpm_steps") or o["diffusion.num_steps"]
        )
        lines = [
            f"PC² checkpoint {cfg.model.init_from} (step {self.step}), trained on {self.trained_on}: PVCNN2 and its "
            "frozen ViT-S/16 from the same file, weights only",
            f"reference settings ({self.source}): PC²'s {sampler.upper()} sampler over {steps} steps, linear β "
            f"{o['diffusion.beta_start']:g} → {o['diffusion.beta_end']:g}, ε-prediction, x̂₀ unclipped, "
            f"{o['data.image_size']}² images, {o['data.num_points']} points, mask channels "
            f"{'on' if o['model.mask_channels'] else 'off'}"
            + (
                ", Co3D loaded as PC² (" + ", ".join(f"{k}={v}" for k, v in self.co3d.items()) + ")"
                if cfg.data.kind == "co3d"
                else ""
            ),
        ]
        changed = [f"{k}={v}" + (f" (PC²: {'null' if o[k] is None else o[k]})" if k in o else "")
                   for k, v in sets.items() if o.get(k, v) != v or k not in o]
        lines.append("changed by --set: " + ", ".join(changed) if changed else "changed by --set: nothing")
        return lines


def _checked_values(tree: Mapping, label: str) -> dict[str, object]:
    """The values of :data:`PC2_DEFAULTS`' keys in the file's ``cfg`` (PC²'s default where it is silent),
    checked: numbers are numbers, and the network they ask for is one this code builds.

    Raises:
        ValueError: naming ``label``, the field and what it holds.
    """
    value = {key: _lookup(tree, key) for key in PC2_DEFAULTS}
    numbers = (
        "dataset.image_size",
        "dataset.max_points",
        "model.point_cloud_model_embed_dim",
        "run.num_inference_steps",
    )
    for key in (*numbers, "model.beta_start", "model.beta_end"):
        kind = int if key in numbers else float
        # Finite first: int() of inf overflows and of NaN raises, neither naming the file.
        if (
            isinstance(value[key], bool)
            or not isinstance(value[key], int | float)
            or isinstance(value[key], float) and not math.isfinite(value[key])
            or kind is int
            and value[key] != int(value[key])
        ):
            raise ValueError(f"{label}: its cfg's {key} is {value[key]!r}, not "
                             f"{'an integer' if kind is int else 'a finite number'}")
    wrong = [f"{k}={value[k]!r}" for k, want in _REQUIRED.items() if value[k] != want]
    if value["model.use_mask"] != value["model.use_distance_transform"]:
        wrong.append("model.use_mask differs from model.use_distance_transform")
    if value["run.diffusion_scheduler"] not in ("ddpm", "ddim"):
        wrong.append(f"run.diffusion_scheduler={value['run.diffusion_scheduler']!r}")
    if wrong:
        raise ValueError(f"{label}: its cfg asks for what this network cannot be: {', '.join(wrong)} (PC²'s "
                         "defaults in its experiments/config/structured.py are what is read)")
    return value


def _network_fields(value: dict, path: str | Path) -> dict:
    """The config fields (dotted path → value) of the network and sampler that PC²'s checked cfg ``value``
    (:func:`_checked_values`) describes, for the checkpoint at ``path``."""
    ddim = value["run.diffusion_scheduler"] == "ddim"
    steps = min(int(value["run.num_inference_steps"]), 1000)
    points = int(value["dataset.max_points"])
    return {
        "model.denoiser": "pvcnn2",
        "model.encoder": "vit_s16",
        "model.encoder_weights": None,
        "model.init_from": str(path),
        "model.feature_dim": 384,
        "model.width_multiplier": 1.0,
        "model.voxel_resolution_multiplier": 1.0,
        "model.time_embed_dim": int(value["model.point_cloud_model_embed_dim"]),
        "model.mask_channels": bool(value["model.use_mask"]),
        "model.raster_radius": 0.0075,
        "model.global_feature": "none",
        "priors.prior_2d": "none",
        "priors.prior_3d": False,
        "diffusion.num_steps": 1000,
        "diffusion.beta_start": float(value["model.beta_start"]),
        "diffusion.beta_end": float(value["model.beta_end"]),
        "diffusion.prediction": "eps",
        "diffusion.sampler": "ddim" if ddim else "ddpm",
        "diffusion.clip_x0": None,
        "diffusion.sample_steps" if ddim else "diffusion.ddpm_steps": None if steps >= 1000 and not ddim else steps,
        "data.image_size": int(value["dataset.image_size"]),
        "data.num_points": points,
        "eval.num_points": points,
    }


def read_pc2_checkpoint(path: str | Path, flag: str = "--checkpoint") -> PC2File:
    """The config fields that rebuild ``path``'s network and PC²'s sampler (:class:`PC2File`).

    Raises:
        ValueError: the file could run code while loading, holds no PC² model, its ``model`` is no state dict
            of finite tensors (:func:`cdm.model.state_dicts.checked_state_dict`), or its ``cfg`` holds a
            value that is no finite number where one belongs, or asks for a network this one cannot be
            (another image model, global features, colour, a scale factor) or a value the config refuses;
            the message starts with ``flag`` (the option that named the file) and the path.
    """
    file = input_path(path)
    label = f"{flag}: {file}"
    raw = load_inert(file, label, "PC² checkpoint")
    if not isinstance(raw, Mapping) or not isinstance(raw.get("model", raw), Mapping):
        raise ValueError(f"{label} holds no model state dict")
    checked_state_dict(raw.get("model", raw), label)  # refused here in the option's name, not in the network's
    tree = config_data(raw.get("cfg")) or {}
    if not isinstance(tree, Mapping):
        raise ValueError(
            f"{label}: its cfg is a {type(tree).__name__}, not a config of groups (run, dataset, model, …)"
        )
    value = _checked_values(tree, label)
    overrides = _network_fields(value, path)
    dataset = tree.get("dataset") if isinstance(tree.get("dataset"), Mapping) else {}
    trained_on = (
        " ".join(str(dataset[k]) for k in ("type", "category") if k in dataset) or "a data set its file does not name"
    )
    step = raw.get("step", raw.get("steps"))
    co3d = {"data.mask_rgb": bool(value["dataset.mask_images"]), "data.exclude_sequences": True,
            "data.frames_per_sequence": 1, "data.drop_outliers": False}
    try:  # what the file asks for must make a config by itself: --set comes later, and names no file
        load_config(None, overrides)
    except ConfigError as exc:
        raise ValueError(f"{label}: its cfg asks for a value this code refuses ({exc})") from None
    return PC2File(overrides, co3d, step if isinstance(step, int) else None,
                   "the file's cfg" if tree else "PC²'s defaults: the file has no cfg", trained_on)
