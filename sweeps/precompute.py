"""Per-sweep work done once, before the trials: the training views and evaluation sets cells share.

Cells of a grid that differ in model or loss settings render the same training samples and build
the same evaluation set, baselines and retrieval bank (:mod:`cdm.shared`). The driver renders them
here once, as one-thread Ray tasks on every CPU, into the sweep folder's ``shared/``; each trial
reads them and computes only what is not there, with the same numbers either way. Only for a local
cluster and a sweep folder on disk: the nodes of a remote cluster do not see the driver's files.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from sweeps.plan import SweepPlan

if TYPE_CHECKING:
    from cdm.config import Config

__all__ = ["Precomputed", "precompute", "shared_root"]


@dataclass(frozen=True)
class Precomputed:
    """What :func:`precompute` left in the store."""

    view_sets: int
    rounds: int
    eval_sets: int
    seconds: float


def shared_root(sweep_dir: str, remote: bool) -> str | None:
    """The store of a sweep in ``sweep_dir``, or None where trials cannot share the driver's files."""
    if remote or "://" in sweep_dir:
        return None
    return str(Path(sweep_dir) / "shared")


def _write_rounds(cfg: Config, root: str, rounds: list[int]) -> None:
    import torch

    from cdm.data import build_dataset
    from cdm.shared import SharedStore

    torch.set_num_threads(1)
    train = build_dataset(cfg, "train")
    store = SharedStore(root)
    for r in rounds:
        store.write_round(cfg, train, r)


def _write_eval(cfg: Config, root: str) -> None:
    import torch

    from cdm.data import build_dataset
    from cdm.shared import SharedStore

    torch.set_num_threads(1)
    SharedStore(root).eval_set(cfg, build_dataset(cfg, "val"), build_dataset(cfg, "train"))


def precompute(plan: SweepPlan, root: str, lanes: int) -> Precomputed:
    """Render every distinct training-view set and evaluation set of ``plan``'s cells into ``root``,
    on ``lanes`` parallel tasks (files already there are kept: a resumed sweep pays nothing)."""
    import ray  # deferred, as torch and cdm: the CLI checks its input before importing them

    from cdm.data import build_dataset
    from cdm.shared import eval_key, rounds_needed, views_key

    rounds_task, eval_task = (ray.remote(num_cpus=1)(f) for f in (_write_rounds, _write_eval))
    start = time.perf_counter()
    world = max(1, plan.profile.resources.workers_per_trial)
    views: dict[str, tuple[Config, int]] = {}
    evals: dict[str, Config] = {}
    for cell in plan.cells:
        cfg = cell.config
        train = build_dataset(cfg, "train")
        key = views_key(cfg, train)
        need = rounds_needed(cfg, len(train), world)
        if need > views.get(key, (cfg, 0))[1]:
            views[key] = (cfg, need)
        evals.setdefault(eval_key(cfg, build_dataset(cfg, "val"), train), cfg)
    jobs = [(config, r) for config, need in views.values() for r in range(need)]
    tasks = []
    lanes = max(1, lanes)
    for lane in range(lanes):
        mine = jobs[lane::lanes]
        for config in {id(c): c for c, _ in mine}.values():
            tasks.append(rounds_task.remote(config, root, [r for c, r in mine if c is config]))
    tasks += [eval_task.remote(config, root) for config in evals.values()]
    ray.get(tasks)
    return Precomputed(len(views), len(jobs), len(evals), time.perf_counter() - start)
