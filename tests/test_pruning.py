"""Checkpoint pruning on real files with Tune's own Checkpoint, Trial and Result objects; the clock is a counter."""

from __future__ import annotations

import shutil
from pathlib import Path

import ray.tune
from ray.tune.experiment import Trial

from sweeps.execute.pruning import CheckpointPruner, prune_finished


def _checkpoints(folder: Path, n: int) -> list[ray.tune.Checkpoint]:
    out = []
    for i in range(n):
        d = folder / f"checkpoint_{i:06d}"
        d.mkdir(parents=True)
        (d / "checkpoint.pt").write_bytes(b"weights")
        out.append(ray.tune.Checkpoint.from_directory(d))
    return out


def _present(checkpoints: list[ray.tune.Checkpoint]) -> list[int]:
    return [i for i, c in enumerate(checkpoints) if Path(c.path).exists()]


def test_a_checkpoint_goes_only_once_its_successor_has_been_registered_for_the_lag(tmp_path):
    now = [0.0]
    pruner = CheckpointPruner(keep=2, lag_s=10.0, clock=lambda: now[0])
    a, b = Trial("t", stub=True), Trial("t", stub=True)
    ca, cb = _checkpoints(tmp_path / "a", 4), _checkpoints(tmp_path / "b", 3)
    for i, c in enumerate(ca):  # trial a checkpoints at t = 0, 1, 2, 3
        now[0] = float(i)
        pruner.on_checkpoint(0, [], a, c)
        pruner.on_step_end(0, [])
    for c in cb:  # trial b checkpoints three times at t = 3
        pruner.on_checkpoint(0, [], b, c)
    assert _present(ca) == [0, 1, 2, 3] and _present(cb) == [0, 1, 2]

    now[0] = 10.9  # a's checkpoint 1 (registered at t = 1) is 9.9 s old: checkpoint 0 may still be named
    pruner.on_step_end(0, [])
    assert _present(ca) == [0, 1, 2, 3]
    now[0] = 11.0
    pruner.on_step_end(0, [])
    assert _present(ca) == [1, 2, 3] and _present(cb) == [0, 1, 2]
    now[0] = 100.0  # every successor is old now; each trial keeps its newest two
    pruner.on_step_end(0, [])
    assert _present(ca) == [2, 3] and _present(cb) == [1, 2]


def test_prune_finished_keeps_each_trials_newest_two_and_tolerates_ones_already_gone(tmp_path):
    results = []
    for name, n in (("a", 5), ("b", 1)):
        cs = _checkpoints(tmp_path / name, n)
        results.append(ray.tune.Result(metrics={}, checkpoint=cs[-1], error=None, path=str(tmp_path / name),
                                       best_checkpoints=[(c, {"step": i}) for i, c in enumerate(cs)]))
    shutil.rmtree(tmp_path / "a" / "checkpoint_000001")  # pruned by the driver before a kill
    assert prune_finished(results) == 2
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["checkpoint_000003", "checkpoint_000004"]
    assert [p.name for p in (tmp_path / "b").iterdir()] == ["checkpoint_000000"]
    assert prune_finished(results) == 0
