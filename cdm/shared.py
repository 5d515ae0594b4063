"""Work computed once and read by many runs: the training views and the evaluation set of a data set.

A sweep's cells usually differ in model or loss settings, not in their data: every cell then renders
the same training samples and builds the same evaluation set (held-out views, baselines, retrieval
bank). A :class:`SharedStore` is a folder where that work lies once, in files named by a hash of
everything that decides their content; a run given the store reads what is there and computes, as
it always did, what is not. Each file is a safetensors file (:mod:`cdm.io.safetensors`): its tensors,
and the rest of what it holds as JSON in its metadata (``cdm.tree``, :func:`cdm.io.safetensors.encode_tree`).
Files are written whole (temporary name, then rename), so a reader sees
a complete file or none; what it reads are the same float32 tensors it would have computed, so
results stay bit-identical with or without the store.

Which samples a run sees: its batches are a pure function of the step (:func:`cdm.data.order.batch_indices`),
and ``steps`` steps of ``B`` samples on ``world`` data-parallel ranks visit view rounds
``0 … ⌈steps·B·world / objects⌉ − 1`` of every object, whatever ``train.seed`` (the seed only orders
them), so one set of round files serves every seed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from torch import Tensor

from cdm.cameras import Cameras
from cdm.config import Config
from cdm.data.sample import Batch, ConditionViews, Sample, collate
from cdm.data.views import ObjectDataset
from cdm.digest import json_digest
from cdm.evaluate import EvalSet, build_eval_set
from cdm.io.json import parse_json
from cdm.io.safetensors import decode_tree, encode_tree, read_safetensors, write_safetensors
from cdm.io.write import make_folder

__all__ = ["SharedStore", "SharedViews", "eval_key", "rounds_needed", "views_key"]

_FORMAT = 3
"""Bumped whenever the files' layout changes, so stale files are never read."""


def _hash(identity: object) -> str:
    return json_digest([_FORMAT, identity])


_LOSS_ONLY = {"lambda_3d", "point_size", "render_kind", "render_size", "target", "depth_layer"}
"""``priors`` fields only the loss reads (:mod:`cdm.objective`): samples do not depend on them."""


def views_key(cfg: Config, train: ObjectDataset) -> str:
    """Name of the training samples of ``train`` under ``cfg``: the objects (the split's fingerprint,
    which covers the ``data`` group), the number of prior-view cameras and every ``priors`` field a
    sample depends on (2D prior, depth source). Files a data set reads (generated images, depth maps)
    are named by their folders, not hashed: a store lives in one sweep's folder, over which they do not change."""
    priors = {k: v for k, v in cfg.priors.model_dump(mode="json").items() if k not in _LOSS_ONLY}
    return _hash({"train": train.fingerprint(), "priors": priors, "num_views": train.num_views})


def eval_key(cfg: Config, val: ObjectDataset, train: ObjectDataset) -> str:
    """Name of the evaluation set of ``cfg``: both splits' objects, what a sample holds, the ``eval``
    group and the batch size (the set is stored in training-size batches)."""
    return _hash({"views": views_key(cfg, train), "val": val.fingerprint(), "eval": cfg.eval.model_dump(mode="json"),
                  "batch_size": cfg.train.batch_size})


def rounds_needed(cfg: Config, num_objects: int, world: int = 1) -> int:
    """View rounds a run of ``cfg`` visits (module docstring)."""
    return math.ceil(cfg.train.steps * cfg.train.batch_size * world / num_objects)


def _cameras_dict(c: Cameras) -> dict[str, Tensor]:
    return {"R": c.R, "T": c.T, "focal": c.focal, "principal": c.principal}


def _batch_dict(b: Batch) -> dict[str, object]:
    c = b.conditions
    return {
        "image": b.image, "mask": b.mask, "depth": b.depth, "prior_2d": b.prior_2d, "points": b.points,
        "camera": _cameras_dict(b.camera), "view_cameras": _cameras_dict(b.view_cameras),
        "category": list(b.category), "object_id": list(b.object_id),
        "conditions": None if c is None else {"image": c.image, "mask": c.mask, "prior_2d": c.prior_2d,
                                              "camera": _cameras_dict(c.camera), "valid": c.valid},
    }


def _conditions(d: dict | None) -> ConditionViews | None:
    if d is None:
        return None
    return ConditionViews(d["image"], d["mask"], d["prior_2d"], Cameras(**d["camera"]), d["valid"])


def _batch(d: dict) -> Batch:
    return Batch(
        image=d["image"],
        mask=d["mask"],
        depth=d["depth"],
        prior_2d=d["prior_2d"],
        camera=Cameras(**d["camera"]),
        view_cameras=Cameras(**d["view_cameras"]),
        points=d["points"],
        category=tuple(d["category"]),
        object_id=tuple(d["object_id"]),
        conditions=_conditions(d["conditions"]),
    )


_TREE = "cdm.tree"
"""Metadata key of a shared file's JSON: what it holds besides its tensors."""


def _save(obj: object, path: Path) -> None:
    # Atomic (cdm.io.write): the runs reading it see the whole file or none.
    tree, tensors = encode_tree(obj)
    write_safetensors(make_folder(path.parent, "shared cache") / path.name, tensors, {_TREE: json.dumps(tree)},
                      "shared cache")


def _load(path: Path, mapped: bool) -> Any:
    """What :func:`_save` wrote to ``path``; ``mapped``: tensors are views of the mapped file (shared pages)."""
    tensors, metadata = read_safetensors(path, "shared cache", mapped=mapped)
    if _TREE not in metadata:
        raise ValueError(f"shared cache: {path} lacks its {_TREE!r} metadata; delete it and it is computed again")
    return decode_tree(parse_json(metadata[_TREE].encode(), "shared cache", path), tensors, f"shared cache: {path}")


class SharedStore:
    """A folder of shared work (module docstring). ``root`` need not exist yet."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def _round_path(self, key: str, view_round: int) -> Path:
        return self.root / "views" / key / f"round_{view_round:05d}.safetensors"

    def _eval_path(self, key: str) -> Path:
        return self.root / "eval" / f"{key}.safetensors"

    def write_round(self, cfg: Config, train: ObjectDataset, view_round: int) -> Path:
        """Render every object of ``train`` in ``view_round`` into one file (kept if already there)."""
        path = self._round_path(views_key(cfg, train), view_round)
        if not path.exists():
            _save(_batch_dict(collate([train.sample(i, view_round) for i in range(len(train))])), path)
        return path

    def read_round(self, key: str, view_round: int) -> Batch | None:
        """The samples of ``view_round`` as one ``Batch`` over all objects (memory-mapped), or None."""
        path = self._round_path(key, view_round)
        if not path.exists():
            return None
        return _batch(_load(path, mapped=True))

    def eval_set(self, cfg: Config, val: ObjectDataset, train: ObjectDataset) -> EvalSet:
        """The evaluation set of ``cfg`` (:func:`cdm.evaluate.build_eval_set`), read when stored, else built and
        stored."""
        path = self._eval_path(eval_key(cfg, val, train))
        if path.exists():
            d = _load(path, mapped=False)
            return EvalSet([_batch(b) for b in d["batches"]], d["fingerprint"], d["baseline_metrics"],
                           d["baseline_rows"], d.get("baseline_clouds", {}))
        built = build_eval_set(cfg, val, train, cfg.eval.seed)
        _save({"batches": [_batch_dict(b) for b in built.batches], "fingerprint": built.fingerprint,
               "baseline_metrics": built.baseline_metrics,
               "baseline_rows": built.baseline_rows, "baseline_clouds": built.baseline_clouds}, path)
        return built


class SharedViews:
    """``sample(index, view_round)`` of a training set, read from a store's round files where they
    exist and rendered by the data set where not (the same tensors either way)."""

    def __init__(self, store: SharedStore, cfg: Config, train: ObjectDataset):
        self.store, self.train = store, train
        self.key = views_key(cfg, train)
        self._rounds: dict[int, Batch | None] = {}

    def __len__(self) -> int:
        return len(self.train)

    def sample(self, index: int, view_round: int = 0) -> Sample:
        if view_round not in self._rounds:
            self._rounds[view_round] = self.store.read_round(self.key, view_round)
        stored = self._rounds[view_round]
        if stored is None:
            return self.train.sample(index, view_round)
        return Sample(image=stored.image[index], mask=stored.mask[index],
                      depth=None if stored.depth is None else stored.depth[index], prior_2d=stored.prior_2d[index],
                      camera=stored.camera[index], view_cameras=stored.view_cameras[index],
                      points=stored.points[index], category=stored.category[index],
                      object_id=stored.object_id[index], conditions=_row(stored.conditions, index))


def _row(c: ConditionViews | None, index: int) -> ConditionViews | None:
    if c is None:
        return None
    return ConditionViews(c.image[index], c.mask[index], c.prior_2d[index], c.camera[index], c.valid[index])
