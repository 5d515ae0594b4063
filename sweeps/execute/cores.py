"""Core leases: however many trials a sweep packs onto one machine, at most one computes per core.

Packing more one-thread trials than cores (local mode with ``resources.cpus_per_worker`` < 1: on 2
CPUs, all 5 cells of point_size.yaml at 0.4 CPU each) lets every cell start and show progress at
once, but five threads time-sliced on two cores pay for it in CPU per step (caches refilled at
every switch; issue 19 measured 1.85× the isolated step's CPU per step with the other waste of that
sweep). Waves of one trial per core avoid that but leave cores idle once fewer trials than cores
are left (5 trials on 2 cores: a third of the last wave's time). With leases, a trial computes only
while it holds one of ``cores`` lease files (an exclusive ``flock``, released by the kernel if the
process dies); it hands the lease on every ``train.log_every`` steps and queues for the next one,
first come, first served.
The trials take turns in slices of seconds, no core runs two of them and none idles while two are
left. A trial's numbers do not depend on when it computes.
"""

from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path

from cdm.train import Callback

__all__ = ["CoreLease", "lease_cores"]

POLL_S = 0.01
"""How often a waiting trial looks for a free lease."""


def lease_cores(cpus: float, cpus_per_worker: float, workers_per_trial: int, remote: bool) -> int:
    """How many leases a local sweep packs its trials under: one per core when more one-thread trials
    than cores share the machine, else 0 (no leases: Ray's reservations already keep one trial per core)."""
    if remote or workers_per_trial != 0 or cpus_per_worker >= 1.0:
        return 0
    return max(1, int(cpus + 1e-6))


def _try_lock(path: Path) -> int | None:
    """An exclusive ``flock`` on ``path`` (created if need be) without waiting: the descriptor, or None."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


class CoreLease(Callback):
    """Holds one of ``cores`` lease files in ``folder`` while its trial computes (module docstring).

    Waiting trials queue first come, first served: each holds a ticket file (named by the time it
    started waiting, locked while it waits) in ``folder/queue``, and only the oldest live ticket may
    take a free lease. A trial handing its lease on queues behind those already waiting, so the
    trials advance at the same pace and finish together. A ticket whose process died is unlocked:
    the next waiter removes it.
    """

    def __init__(self, folder: str | Path, cores: int):
        self.paths = [Path(folder) / f"core_{i}.lock" for i in range(cores)]
        self.queue = Path(folder) / "queue"
        self.queue.mkdir(parents=True, exist_ok=True)
        self._fd: int | None = None

    def _first_in_queue(self, mine: str) -> bool:
        for name in sorted(os.listdir(self.queue)):
            if name == mine:
                return True
            stale = _try_lock(self.queue / name)
            if stale is None:
                return False  # a live trial waits ahead of this one
            (self.queue / name).unlink(missing_ok=True)
            os.close(stale)
        return True

    def acquire(self) -> None:
        if self._fd is not None:
            return
        mine = f"{time.time_ns():020d}_{os.getpid()}_{id(self)}"
        ticket = _try_lock(self.queue / mine)
        try:
            while True:
                if self._first_in_queue(mine):
                    for path in self.paths:
                        self._fd = _try_lock(path)
                        if self._fd is not None:
                            return
                time.sleep(POLL_S)
        finally:
            (self.queue / mine).unlink(missing_ok=True)
            if ticket is not None:
                os.close(ticket)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops its flock
            self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def on_start(self, record: dict[str, str]) -> None:
        self.acquire()

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        self.release()
        self.acquire()  # behind every trial already waiting
