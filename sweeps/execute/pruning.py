"""Which of a sweep's Tune checkpoints to delete, and when, so a killed driver can always resume.

Tune's own ``CheckpointConfig(num_to_keep=k)`` deletes a trial's oldest checkpoint the moment the
(k+1)-th is registered, but uploads the experiment state that names each trial's latest checkpoint
only afterwards, in the background (``ray/tune/execution/experiment_state.py``: the forced sync
after ``num_to_keep`` checkpoints runs after the deletion). A driver killed in between leaves a
state in storage that points at a deleted checkpoint, and ``--resume`` fails that trial with
"Could not recover from checkpoint as it does not exist on storage anymore" (seen in CI with the
smoke profile, whose checkpoints come every half second).

So Tune keeps every checkpoint (``num_to_keep=None``) and :class:`CheckpointPruner` deletes a
trial's old ones itself, lagging: a checkpoint goes only once the one after it has been registered
for :data:`SYNC_LAG_S`, long after the state naming that newer one was uploaded (snapshots go out
every second, ``sweeps.execute.tuner.run_sweep``), and :func:`prune_finished` trims every trial after
``Tuner.fit`` returns, when Tune has uploaded its final state and waited for it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable

import ray.tune

__all__ = ["KEEP", "SYNC_LAG_S", "CheckpointPruner", "prune_finished"]

KEEP = 2
"""Checkpoints kept per trial: the newest, and the one before it."""

SYNC_LAG_S = 120.0
"""Seconds a checkpoint's successor must have been registered before the checkpoint is deleted:
four times the 30 s after which Tune warns that an experiment-state upload is slow."""


def _delete(checkpoint: ray.tune.Checkpoint) -> bool:
    """True if it was there; a driver killed before a resume may have deleted it already."""
    try:
        checkpoint.filesystem.delete_dir(checkpoint.path)
    except FileNotFoundError:
        return False
    return True


class CheckpointPruner(ray.tune.Callback):
    """Driver side: deletes each trial's checkpoints beyond the newest :data:`KEEP`, lagging by ``lag_s``.

    ``clock`` is injectable for tests (monotonic seconds).
    """

    def __init__(self, keep: int = KEEP, lag_s: float = SYNC_LAG_S, clock: Callable[[], float] = time.monotonic):
        self.keep, self.lag_s, self.clock = keep, lag_s, clock
        self._registered: dict[str, list[tuple[float, ray.tune.Checkpoint]]] = {}

    def on_checkpoint(self, iteration, trials, trial, checkpoint, **info) -> None:
        self._registered.setdefault(trial.trial_id, []).append((self.clock(), checkpoint))

    def on_step_end(self, iteration, trials, **info) -> None:
        self.prune()

    def prune(self) -> None:
        now = self.clock()
        for registered in self._registered.values():
            # registered[1] is the oldest checkpoint's successor: once the state naming it (or a
            # newer one) has surely been uploaded, nothing in storage points at registered[0].
            while len(registered) > self.keep and now - registered[1][0] >= self.lag_s:
                _delete(registered.pop(0)[1])


def prune_finished(results: Iterable[ray.tune.Result], keep: int = KEEP) -> int:
    """Delete every trial's checkpoints but the newest ``keep``; call once ``Tuner.fit`` returned.

    Returns how many checkpoints it deleted.
    """
    # Without a score attribute Tune lists a trial's checkpoints oldest first.
    return sum(_delete(c) for r in results for c, _ in (r.best_checkpoints or [])[:-keep])
