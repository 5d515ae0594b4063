"""``python -m cdm prepare``: convert a published data set once into a prepared root of shards.

The format is :mod:`cdm.data.cache`'s; this module reads both splits through the data set's own
reader (:meth:`CapturedDataset.export`) and writes one shard per object, resumably: :func:`prepare` in
this process, or :func:`start` once and :func:`write_object` per object wherever the objects are sent
(``python sweeps/inputs.py prepare --ray``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from cdm.config import Config, load_config
from cdm.data.cache import (
    ESTIMATED_DEPTHS,
    FORMAT,
    MANIFEST,
    SCRATCH,
    SHARD_SUFFIX,
    ObjectRecord,
    ViewImages,
    is_prepared,
    write_shard,
)
from cdm.data.captured import CapturedDataset
from cdm.data.depth_maps import DepthMaps
from cdm.io.json import read_json
from cdm.io.write import TEMP_NAME, make_folder, write_atomic

__all__ = [
    "PrepareReport", "Preparation", "check_out", "prepare", "prepare_config", "shard_path", "start", "write_object"
]


class PrepareReport(NamedTuple):
    """What :func:`prepare` did: shards written now, shards found complete from an earlier run."""

    out: Path
    written: int
    skipped: int


def prepare_config(sets: dict, root: str | Path) -> tuple[type[CapturedDataset], Config]:
    """What ``prepare`` reads: the data set class ``--set data.kind=`` names (a captured kind) and the config
    over the published data set at ``root`` (``--set`` overrides, ``data.image_size`` the crops' side)."""
    from cdm.data import DATASETS

    preparable = [k for k, cls in DATASETS.items() if issubclass(cls, CapturedDataset)]
    kind = sets.get("data.kind")
    if kind not in preparable:
        said = "give --set data.kind=KIND" if kind is None else f"{kind!r} cannot be prepared"
        raise ValueError(f"data.kind: {said}; choose one of {', '.join(preparable)}")
    return DATASETS[kind], load_config(None, {**sets, "data.root": str(root)})


def _object_arrays(record: ObjectRecord, views: list[ViewImages]) -> dict[str, np.ndarray]:
    seq = record.sequence
    arrays = {
        "cloud": record.cloud.numpy().astype(np.float32),
        "seq_R": seq.R.numpy(),
        "seq_T": seq.T.numpy(),
        "seq_focal": seq.focal.numpy(),
        "seq_principal": seq.principal.numpy(),
        "views": record.views.numpy().astype(np.int64),
        "images": np.stack([v.image for v in views]),
        "masks": np.stack([v.mask for v in views]),
        "depth_scale": np.array([v.depth_scale for v in views], dtype=np.float32),
    }
    if views[0].depth is not None:
        arrays["depths"] = np.stack([v.depth for v in views])
    for key in ("R", "T", "focal", "principal"):
        arrays[f"cam_{key}"] = torch.stack([getattr(v.camera, key) for v in views]).numpy()
    return arrays


_PROJECT = Path(__file__).resolve().parents[2]


def check_out(out: Path) -> None:
    """Refuse an ``--out`` that ``prepare`` may not fill: the file system's root, the home folder, this
    project's folder, a file, or a folder holding anything but a root ``prepare`` made (its manifest).
    Filling a folder of other files would mix them into a data root."""
    where = out.resolve()
    for forbidden, what in ((Path(where.anchor), "the file system's root"), (Path.home().resolve(), "the home folder"),
                            (_PROJECT, "this project's folder")):
        if where == forbidden:
            raise ValueError(f"--out: {out} is {what}; prepare into a new folder")
    if not where.exists():
        return
    if not where.is_dir():
        raise ValueError(f"--out: {out} is a file, not a folder; give a new or empty folder")
    try:
        with os.scandir(where) as entries:
            occupied = next(entries, None) is not None
    except OSError as exc:
        raise ValueError(f"--out: cannot read the folder {out}: {exc.strerror}") from None
    if occupied and not is_prepared(where):
        raise ValueError(f"--out: {out} holds files and no {MANIFEST} (not a root `prepare` made); "
                         "give a new or empty folder, or the --out of an earlier prepare to resume it")


def _clear_scratch(out: Path) -> Path:
    """``out``'s scratch folder (:data:`cdm.data.cache.SCRATCH`), emptied of the temporary files a killed
    run left: they were never renamed, so never complete. Nothing else is removed, and nothing is
    followed: the folder is opened without following a link, and only names it made are unlinked."""
    scratch = make_folder(out / SCRATCH, "--out")
    try:
        fd = os.open(scratch, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        raise ValueError(f"--out: {scratch} is not the folder prepare keeps temporary files in "
                         f"({exc.strerror}); remove it") from None
    try:
        for entry in os.scandir(fd):
            if TEMP_NAME.fullmatch(entry.name) and not entry.is_dir(follow_symlinks=False):
                os.unlink(entry.name, dir_fd=fd)
    finally:
        os.close(fd)
    return scratch


class Preparation(NamedTuple):
    """A checked preparation (:func:`start`): both splits indexed, the manifest written into ``out``.

    It pickles (the splits are plain indexes), so a Ray task can write some of its objects
    (:func:`write_object`) on another machine that sees the same ``out``.
    """

    out: Path
    splits: list[CapturedDataset]
    maps: DepthMaps | None
    image_size: int
    scratch: Path


def start(dataset: type[CapturedDataset], cfg: Config, out: Path, depth_maps: Path | None = None) -> Preparation:
    """Index and check the raw data set ``cfg.data`` (kind ``dataset``) and write ``out``'s manifest.

    With ``depth_maps`` (a folder in :mod:`cdm.data.depth_maps`' layout; disparity with
    ``priors.depth_maps_disparity``) each shard also stores the estimated depth of its input views,
    which ``priors.depth_source: maps`` reads when ``priors.depth_maps`` is not set.

    Reads the training split and ``data.eval_split`` of ``data.categories`` at ``data.image_size``.
    Both splits are indexed (and every path checked) before anything is written. ``out`` must be new,
    empty or a root ``prepare`` made (:func:`check_out`). Shards already in it from an interrupted run
    of the same command are kept; the temporary files it left in its scratch folder are removed.

    Raises:
        ValueError: bad root, annotation, category or image (named), ``out`` refused by :func:`check_out`,
            prepared differently, or not writable.
    """
    out = out.expanduser()
    check_out(out)
    root = Path(cfg.data.root).expanduser() if cfg.data.root is not None else None
    if root is not None and is_prepared(root):
        raise ValueError(f"--root: {root} is already a prepared root; point --root at the published data set")
    splits = [dataset(cfg, "train"), dataset(cfg, "val")]
    manifest = {
        "format": FORMAT, "kind": dataset.kind, "image_size": cfg.data.image_size, "source": str(root),
        "categories": list(dataset.categories(cfg)),
        "protocol": dataset.protocol(cfg),
        "splits": {ds.published: [list(ref) for ref in ds.objects] for ds in splits},
    }
    maps = None
    if depth_maps is not None:
        maps = DepthMaps(depth_maps, cfg.priors.depth_maps_disparity)
        maps.require(ref.object_id for ds in splits for ref in ds.objects)
        manifest[ESTIMATED_DEPTHS] = str(maps.folder)
    if is_prepared(out):
        earlier = read_json(out / MANIFEST, "--out")
        if earlier != manifest:
            said = earlier if isinstance(earlier, dict) else {}
            raise ValueError(
                f"--out: {out} holds a different preparation (kind {said.get('kind')}, image size "
                f"{said.get('image_size')}, {said.get('categories')}); choose another --out"
            )
    make_folder(out, "--out")
    write_atomic(out / MANIFEST, json.dumps(manifest, indent=1), "--out")
    return Preparation(out, splits, maps, cfg.data.image_size, _clear_scratch(out))


def shard_path(prep: Preparation, split: int, index: int) -> Path:
    """Where object ``index`` of ``prep.splits[split]`` is stored: below ``prep.out``, whatever the id says
    (ValueError otherwise). The data sets check every name they read; this is the last check, on the
    resolved path, before a write."""
    ds = prep.splits[split]
    object_id = ds.objects[index].object_id
    path = prep.out / ds.published / f"{object_id}{SHARD_SUFFIX}"
    if not path.resolve().is_relative_to(prep.out.resolve()):
        raise ValueError(f"--out: object {object_id[:200]!r} would be written to {path.resolve()}, outside {prep.out}; "
                         "refused (its name comes from the data set's annotations)")
    return path


def write_object(prep: Preparation, split: int, index: int) -> bool:
    """Write the shard of object ``index`` of ``prep.splits[split]`` unless it is complete already;
    True when written now. The write is atomic: a killed run leaves no shard under its final name."""
    path = shard_path(prep, split, index)
    if path.is_file():
        return False
    ds, ref = prep.splits[split], prep.splits[split].objects[index]
    make_folder(path.parent, "--out")
    record, views = ds.export(index)
    arrays = _object_arrays(record, views)
    if prep.maps is not None:
        arrays[ESTIMATED_DEPTHS] = np.stack(
            [prep.maps.read(ref.object_id, p, prep.image_size)[0].numpy() for p in record.views.tolist()])
    write_shard(path, arrays, {"object_id": ref.object_id, "category": ref.category, "scale": record.scale,
                               "image_size": prep.image_size}, prep.scratch)
    return True


def prepare(dataset: type[CapturedDataset], cfg: Config, out: Path, progress: bool = True,
            depth_maps: Path | None = None) -> PrepareReport:
    """Write the prepared form of the raw data set ``cfg.data`` (kind ``dataset``) into ``out``, one
    object after another in this process (:func:`start`, then :func:`write_object` for each object).

    Raises:
        ValueError: as :func:`start`.
    """
    prep = start(dataset, cfg, out, depth_maps)
    from tqdm import tqdm

    written = skipped = 0
    for split, ds in enumerate(prep.splits):
        # The context closes the bar on errors too, so an error message starts on its own line.
        with tqdm(total=len(ds), desc=f"{dataset.kind} {ds.published}", unit="object", disable=not progress) as bar:
            for index in range(len(ds)):
                if write_object(prep, split, index):
                    written += 1
                else:
                    skipped += 1
                bar.update(1)
    return PrepareReport(prep.out, written, skipped)
