"""Per-sweep work done once, before the trials: the training views and evaluation sets cells share.

Cells of a grid that differ in model or loss settings render the same training samples and build
the same evaluation set, baselines and retrieval bank (:mod:`cdm.shared`). The driver renders them
here once, as one-thread Ray tasks on every CPU, into the sweep folder's ``shared/``; each trial
reads them and computes only what is not there, with the same numbers either way. Only for a local
cluster and a sweep folder on disk: the nodes of a remote cluster do not see the driver's files.
:func:`check_space` refuses, before Ray starts, a store its disk cannot hold.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cdm.io.files import is_uri
from sweeps.plan.trials import SweepPlan
from sweeps.store.files import StoreError

if TYPE_CHECKING:
    from cdm.config import Config
    from cdm.data.views import ObjectDataset

__all__ = ["Precomputed", "check_space", "precompute", "precomputes", "shared_bytes", "shared_root"]


@dataclass(frozen=True)
class Precomputed:
    """What :func:`precompute` left in the store."""

    view_sets: int
    rounds: int
    eval_sets: int
    seconds: float


def shared_root(sweep_dir: str, remote: bool) -> str | None:
    """The store of a sweep in ``sweep_dir``, or None where trials cannot share the driver's files."""
    if remote or is_uri(sweep_dir):
        return None
    return str(Path(sweep_dir) / "shared")


def precomputes(plan: SweepPlan, sweep_dir: str, remote: bool) -> bool:
    """Whether the driver renders ``plan``'s shared work before the trials (:func:`precompute`): a grid's
    cells, in a store the trials share."""
    return shared_root(sweep_dir, remote) is not None and bool(plan.cells)


@dataclass(frozen=True)
class _Job:
    """One distinct piece of shared work: the config that renders it, its data sets, its view rounds."""

    config: Config
    train: ObjectDataset
    val: ObjectDataset
    rounds: int


@dataclass(frozen=True)
class _Work:
    views: dict[str, _Job]
    """Training-view sets by :func:`cdm.shared.views_key`, each with the most rounds a cell visits."""
    evals: dict[str, _Job]
    """Evaluation sets by :func:`cdm.shared.eval_key`."""


def _shared_work(plan: SweepPlan) -> _Work:
    """The distinct training-view sets and evaluation sets of ``plan``'s cells (cells of one data set share them)."""
    from cdm.data import build_dataset
    from cdm.shared import eval_key, rounds_needed, views_key

    world = max(1, plan.profile.resources.workers_per_trial)
    views: dict[str, _Job] = {}
    evals: dict[str, _Job] = {}
    for cell in plan.cells:
        cfg = cell.config
        train, val = build_dataset(cfg, "train"), build_dataset(cfg, "val")
        key = views_key(cfg, train)
        job = _Job(cfg, train, val, rounds_needed(cfg, len(train), world))
        if key not in views or job.rounds > views[key].rounds:
            views[key] = job
        evals.setdefault(eval_key(cfg, val, train), job)
    return _Work(views, evals)


def _tensor_bytes(value: Any) -> int:
    """Bytes of the tensors in ``value`` (a :class:`cdm.data.sample.Sample`, or what it holds), nested included."""
    import torch

    if isinstance(value, torch.Tensor):
        return value.nbytes
    if isinstance(value, (list, tuple)):
        return sum(_tensor_bytes(v) for v in value)
    if isinstance(value, dict):
        return sum(_tensor_bytes(v) for v in value.values())
    if hasattr(value, "__dataclass_fields__"):
        return sum(_tensor_bytes(getattr(value, name)) for name in value.__dataclass_fields__)
    return 0


def shared_bytes(plan: SweepPlan) -> int:
    """Bytes :func:`precompute` writes for ``plan``, at least: one rendered sample's tensors × objects × view
    rounds per training-view set, and × the held-out objects scored per evaluation set (what the files
    hold besides, baselines and pickling, is small beside it)."""
    work = _shared_work(plan)
    total = 0
    for job in work.views.values():
        total += _tensor_bytes(job.train.sample(0, 0)) * len(job.train) * job.rounds
    for job in work.evals.values():
        cfg = job.config
        categories = len({ref.category for ref in job.val.objects})
        scored = len(job.val) if cfg.eval.protocol == "paper" else min(len(job.val), cfg.eval.num_objects * categories)
        total += _tensor_bytes(job.val.sample(0, 0)) * scored
    return total


def _bytes_under(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else 0


def check_space(plan: SweepPlan, sweep_dir: str, remote: bool) -> None:
    """Refuse, before Ray starts, a sweep whose shared store (:func:`shared_bytes`, less what a resumed
    sweep already holds) would not fit in the free space of the disk under ``sweep_dir``.

    Raises:
        StoreError: one line with both sizes and the way out.
    """
    if not precomputes(plan, sweep_dir, remote):
        return
    root = shared_root(sweep_dir, remote)
    try:  # renders one sample per distinct data set: an unreadable input is found here, before Ray
        need = shared_bytes(plan) - _bytes_under(Path(root))
    except ValueError as exc:
        raise StoreError(str(exc)) from None
    except OSError as exc:
        raise StoreError(f"data.root: cannot read an input ({exc})") from None
    probe = Path(sweep_dir)
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if need > free:
        raise StoreError(
            f"--out {sweep_dir}: the views and evaluation sets its cells share ({root}) need "
            f"{_size(need)} but its disk has {_size(free)} free; free space, or give --out on a larger disk"
        )


def _size(n: float) -> str:
    return f"{n / 2**30:.2f} GiB" if n >= 2**30 else f"{n / 2**20:.1f} MiB"


def _render(cfg: Config, root: str, rounds: list[int] | None) -> None:
    """One task's share, on one thread: the training-view ``rounds`` of ``cfg``'s data, or (None) its evaluation set."""
    import torch

    from cdm.data import build_dataset
    from cdm.shared import SharedStore

    torch.set_num_threads(1)
    store, train = SharedStore(root), build_dataset(cfg, "train")
    if rounds is None:
        store.eval_set(cfg, build_dataset(cfg, "val"), train)
    for r in rounds or []:
        store.write_round(cfg, train, r)


def precompute(plan: SweepPlan, root: str, lanes: int) -> Precomputed:
    """Render every distinct training-view set and evaluation set of ``plan``'s cells into ``root``,
    on ``lanes`` parallel tasks (files already there are kept: a resumed sweep pays nothing)."""
    import ray  # deferred, as torch and cdm: the CLI checks its input before importing them

    task = ray.remote(num_cpus=1)(_render)
    start = time.perf_counter()
    work = _shared_work(plan)
    jobs = [(views.config, r) for views in work.views.values() for r in range(views.rounds)]
    tasks = []
    lanes = max(1, lanes)
    for lane in range(lanes):
        mine = jobs[lane::lanes]
        for config in {id(c): c for c, _ in mine}.values():
            tasks.append(task.remote(config, root, [r for c, r in mine if c is config]))
    tasks += [task.remote(evals.config, root, None) for evals in work.evals.values()]
    ray.get(tasks)
    return Precomputed(len(work.views), len(jobs), len(work.evals), time.perf_counter() - start)
