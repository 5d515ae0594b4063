"""Ray tasks that make a data set's external inputs over a cluster: prepared shards and depth maps.

Work is cut into chunks of objects (or views), one Ray task each. A task does its items one by one and
returns the ones that failed with their error, so a bad object fails alone, named, and the others
finish. Every file is written atomically under its final name (:func:`cdm.io.write.write_atomic`,
:mod:`cdm.tools.estimate_depth`) and an item whose file exists is skipped, so a killed run, rerun,
writes only what is missing. Tasks write to ``out`` as every node sees it: on several machines, a
shared file system. Used by ``sweeps/inputs.py``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import ray
from tqdm import tqdm

from cdm.data.prepare import Preparation, shard_path, write_object
from cdm.tools.estimate_depth import View, load_estimator, write_maps

__all__ = ["Failure", "chunks_of", "estimate_depth", "prepare_shards"]

TASKS_PER_CPU = 4
"""Chunks per CPU of the cluster: enough for the progress bar to move and for a slow node to be
balanced, few enough that a task's start-up (a depth model loaded) stays small beside its work."""


class Failure(NamedTuple):
    """An item that could not be made: its name and the one-line reason."""

    item: str
    error: str


def chunks_of(count: int, cpus: float, most: int = 64) -> list[range]:
    """``range(count)`` cut into chunks of equal size, about :data:`TASKS_PER_CPU` per CPU, at most ``most`` each."""
    size = max(1, min(most, math.ceil(count / max(1.0, TASKS_PER_CPU * cpus))))
    return [range(i, min(i + size, count)) for i in range(0, count, size)]


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _run(refs: dict, names: Callable[[object], list[str]], desc: str, unit: str) -> list[Failure]:
    """Wait for ``refs`` (Ray refs → their chunk), advancing one bar with a rate and an ETA as each ends."""
    failures: list[Failure] = []
    with tqdm(total=sum(len(names(c)) for c in refs.values()), desc=desc, unit=unit) as bar:
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            chunk = refs[done[0]]
            try:
                failures += ray.get(done[0])
            except ray.exceptions.RayError as exc:  # the worker died or the task could not run: its items failed
                failures += [Failure(n, _one_line(exc)) for n in names(chunk)]
            bar.update(len(names(chunk)))
    return sorted(failures)


@ray.remote
def _prepare_task(prep: Preparation, split: int, indices: list[int]) -> list[Failure]:
    failed = []
    for index in indices:
        try:
            write_object(prep, split, index)
        except (ValueError, OSError) as exc:  # the data checks' and the file system's errors: this object alone
            failed.append(Failure(prep.splits[split].objects[index].object_id, _one_line(exc)))
    return failed


def prepare_shards(prep: Preparation, cpus: float) -> tuple[int, int, list[Failure]]:
    """Write every shard of ``prep`` missing from ``prep.out`` as Ray tasks of one CPU each.

    Returns:
        (shards written now, shards complete before, failures).
    """
    todo = {split: [i for i in range(len(ds)) if not shard_path(prep, split, i).is_file()]
            for split, ds in enumerate(prep.splits)}
    before = sum(len(ds) for ds in prep.splits) - sum(len(t) for t in todo.values())
    shared = ray.put(prep)
    refs = {}
    for split, indices in todo.items():
        for part in chunks_of(len(indices), cpus):
            chunk = indices[part.start:part.stop]
            refs[_prepare_task.remote(shared, split, chunk)] = (split, chunk)
    failures = _run(refs, lambda c: [prep.splits[c[0]].objects[i].object_id for i in c[1]], "shards", "object")
    return sum(len(t) for t in todo.values()) - len(failures), before, failures


def _view_name(view: View) -> str:
    return f"{view.object_id}/{view.position}"


@ray.remote
def _depth_task(model: str, output: str | None, views: list[View], out: Path, batch_size: int) -> list[Failure]:
    import torch

    try:
        estimator = load_estimator(model, "cuda" if torch.cuda.is_available() else "cpu", output)
    except ValueError as exc:
        return [Failure(_view_name(v), _one_line(exc)) for v in views]
    try:
        write_maps(estimator, views, out, batch_size, progress=False)
    except (ValueError, OSError):  # one bad crop fails its batch: find it, view by view
        return _depth_one_by_one(estimator, views, out)
    return []


def _depth_one_by_one(estimator, views: list[View], out: Path) -> list[Failure]:
    """After a failed batch: each view alone, so only the bad ones fail."""
    failed = []
    for view in views:
        try:
            write_maps(estimator, [view], out, 1, progress=False)
        except (ValueError, OSError) as exc:
            failed.append(Failure(_view_name(view), _one_line(exc)))
    return failed


def estimate_depth(model: str, output: str | None, views: Sequence[View], out: Path, batch_size: int, cpus: float,
                   gpus: float) -> tuple[int, int, list[Failure]]:
    """Write every depth map of ``views`` missing from ``out`` as Ray tasks of one GPU each where the
    cluster has GPUs, else one CPU each; a task loads the model once and runs its views in batches.

    Returns:
        (maps written now, maps there before, failures).
    """
    todo = [v for v in views if not (out / v.object_id / f"{v.position}.npy").is_file()]
    options = {"num_gpus": 1, "num_cpus": 1} if gpus >= 1 else {"num_cpus": 1}
    workers = gpus if gpus >= 1 else cpus
    refs = {}
    for part in chunks_of(len(todo), workers, most=1024):
        chunk = todo[part.start:part.stop]
        refs[_depth_task.options(**options).remote(model, output, chunk, out, batch_size)] = chunk
    failures = _run(refs, lambda c: [_view_name(v) for v in c], "depth maps", "view")
    return len(todo) - len(failures), len(views) - len(todo), failures
