"""PC²'s ``checkpoint-latest.pth`` written as its ``experiments/main.py`` saves it, with random weights.

The ``cfg`` is pickled as OmegaConf pickles a ``DictConfig``: classes named ``omegaconf.dictconfig.DictConfig``,
``omegaconf.nodes.IntegerNode``, ``omegaconf.base.Metadata`` …, created bare and given their ``__dict__``,
children under ``_content``, values under ``_val``, each node pointing back at its ``_parent``, the metadata
holding ``typing.Any`` and a ``defaultdict`` resolver cache. omegaconf need not be installed: stand-in
classes under those names exist in ``sys.modules`` only while the file is written.
"""

from __future__ import annotations

import sys
import types
import typing
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch

from cdm.model import PVCNN2Denoiser, ViTS16

PC2_CFG: dict[str, dict[str, Any]] = {  # PC²'s experiments/config/structured.py, the groups a checkpoint's cfg holds
    "run": {
        "name": "hydrant",
        "job": "train",
        "mixed_precision": "fp16",
        "seed": 42,
        "max_steps": 100_000,
        "num_inference_steps": 1000,
        "diffusion_scheduler": "ddpm",
        "sample_from_ema": False,
        "limit_train_batches": None,
    },
    "dataset": {
        "type": "co3dv2",
        "root": "/data/co3d",
        "category": "hydrant",
        "subset_name": "fewview_dev",
        "eval_split": "val",
        "max_points": 16_384,
        "image_size": 224,
        "scale_factor": 1.0,
        "mask_images": "${model.use_mask}",
    },
    "model": {
        "image_size": "${dataset.image_size}",
        "image_feature_model": "vit_small_patch16_224_msn",
        "use_local_colors": True,
        "use_local_features": True,
        "use_global_features": False,
        "use_mask": True,
        "use_distance_transform": True,
        "scale_factor": "${dataset.scale_factor}",
        "colors_mean": 0.5,
        "colors_std": 0.5,
        "color_channels": 3,
        "predict_shape": True,
        "predict_color": False,
        "beta_start": 1e-5,
        "beta_end": 8e-3,
        "beta_schedule": "linear",
        "point_cloud_model": "pvcnn",
        "point_cloud_model_embed_dim": 64,
    },
    "optimizer": {
        "type": "torch",
        "name": "AdamW",
        "lr": 1e-3,
        "weight_decay": 1e-6,
        "kwargs": {"betas": [0.95, 0.999]},
    },
}


def _class(module: types.ModuleType, name: str) -> type:
    cls = type(name, (), {})
    cls.__module__, cls.__qualname__ = module.__name__, name
    setattr(module, name, cls)
    return cls


@contextmanager
def fake_omegaconf():
    """``omegaconf``'s modules with stand-in classes, in ``sys.modules`` for the duration."""
    names = ("omegaconf", "omegaconf.dictconfig", "omegaconf.listconfig", "omegaconf.nodes", "omegaconf.base")
    saved = {n: sys.modules.get(n) for n in names}
    modules = {n: types.ModuleType(n) for n in names}
    sys.modules.update(modules)
    try:
        yield modules
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def _node(modules: dict, value: Any, key: Any, parent: Any) -> Any:
    def make(module: str, name: str, **state: Any) -> Any:
        cls = getattr(modules[module], name, None) or _class(modules[module], name)
        obj = cls.__new__(cls)
        meta_cls = "ContainerMetadata" if name in ("DictConfig", "ListConfig") else "Metadata"
        meta_type = getattr(modules["omegaconf.base"], meta_cls, None) or _class(modules["omegaconf.base"], meta_cls)
        meta = meta_type.__new__(meta_type)
        meta.__dict__.update(ref_type=typing.Any, object_type=dict if name == "DictConfig" else None, optional=True,
                             key=key, flags={}, flags_root=False, resolver_cache=defaultdict(dict))
        obj.__dict__.update(_metadata=meta, _parent=parent, **state)
        return obj

    if isinstance(value, dict):
        node = make("omegaconf.dictconfig", "DictConfig", _content={})
        node._content.update({k: _node(modules, v, k, node) for k, v in value.items()})
        return node
    if isinstance(value, list):
        node = make("omegaconf.listconfig", "ListConfig", _content=[])
        node._content.extend(_node(modules, v, i, node) for i, v in enumerate(value))
        return node
    kind = {bool: "BooleanNode", int: "IntegerNode", float: "FloatNode", str: "StringNode"}.get(type(value), "AnyNode")
    if isinstance(value, str) and value.startswith("${"):
        kind = "AnyNode"
    return make("omegaconf.nodes", kind, _val=value)


def write_pc2_checkpoint(path: Path, *, width: float = 1.0, cfg: dict | None = None, payload: Any = None,
                         seed: int = 0, legacy: bool = False) -> dict[str, torch.Tensor]:
    """PC²'s checkpoint dict with random weights: PVCNN2 at ``width`` (both multipliers) under
    ``point_cloud_model.model.``, the ViT-S/16 under ``feature_model.model.``; ``payload`` replaces the
    ``cfg`` when given; ``legacy`` writes torch < 1.6's pre-zip format. Returns the model state dict written."""
    g = torch.Generator().manual_seed(seed)
    pvcnn2 = PVCNN2Denoiser(389, width, width)  # S = RGB 3 + ViT 384 + mask 1 + distance 1
    model = {
        f"point_cloud_model.model.{k}": torch.randn(v.shape, generator=g) * 0.05 for k, v in pvcnn2.state_dict().items()
    }
    for k, v in ViTS16().state_dict().items():
        weight = torch.randn(v.shape, generator=g) * 0.05
        model[f"feature_model.model.{k}"] = (
            weight + 1.0 if k.endswith(("norm1.weight", "norm2.weight", "norm.weight")) else weight
        )
    checkpoint = {"model": model, "optimizer": {"state": {}, "param_groups": [{"lr": 1e-3, "params": [0, 1]}]},
                  "scheduler": {"last_epoch": 100_000, "_last_lr": [0.0]}, "epoch": 12, "step": 100_000,
                  "best_val": None, "model_ema": {}}
    with fake_omegaconf() as modules:
        checkpoint["cfg"] = payload if payload is not None else _node(modules, cfg or PC2_CFG, None, None)
        torch.save(checkpoint, path, _use_new_zipfile_serialization=not legacy)
    return model
