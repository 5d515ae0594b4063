"""Core leases (sweeps/execute/cores.py): at most ``cores`` trials compute at once, a handed-on lease goes to a
waiting trial, and leases are only used where more one-thread trials than cores share a machine."""

from __future__ import annotations

import threading
import time

from sweeps.execute.cores import CoreLease, lease_cores


def test_leases_are_used_only_for_packed_local_trials():
    assert lease_cores(2.0, 0.4, 0, remote=False) == 2
    assert lease_cores(2.0, 1.0, 0, remote=False) == 0  # Ray's reservations already give a core each
    assert lease_cores(2.0, 0.4, 0, remote=True) == 0
    assert lease_cores(8.0, 0.5, 1, remote=False) == 0  # Train workers: not one-thread local trials


def test_at_most_cores_leases_are_held_and_a_release_frees_one(tmp_path):
    trials = [CoreLease(tmp_path, cores=2) for _ in range(3)]
    trials[0].acquire()
    trials[1].acquire()
    got = threading.Event()

    def third():
        trials[2].acquire()
        got.set()

    waiter = threading.Thread(target=third, daemon=True)
    waiter.start()
    time.sleep(0.2)
    assert not got.is_set()  # both cores leased: the third trial waits
    trials[0].release()
    assert got.wait(5.0) and trials[2].held
    for t in trials:
        t.release()


def test_a_handoff_lets_the_waiting_trial_compute_first(tmp_path):
    running, waiting = CoreLease(tmp_path, cores=1), CoreLease(tmp_path, cores=1)
    running.on_start({})
    order = []

    def wait_then_take():
        waiting.acquire()
        order.append("waiting")
        time.sleep(0.1)
        waiting.release()

    thread = threading.Thread(target=wait_then_take, daemon=True)
    thread.start()
    time.sleep(0.05)
    running.on_step(100, {})  # hands the lease on, then takes it back once free
    order.append("running")
    thread.join(5.0)
    assert order == ["waiting", "running"]
    running.release()


def test_waiting_trials_are_served_first_come_first_served(tmp_path):
    holder = CoreLease(tmp_path, cores=1)
    holder.acquire()
    order = []
    waiters = [CoreLease(tmp_path, cores=1) for _ in range(3)]

    def wait(i):
        waiters[i].acquire()
        order.append(i)
        time.sleep(0.05)
        waiters[i].release()

    threads = []
    for i in range(3):
        threads.append(threading.Thread(target=wait, args=(i,), daemon=True))
        threads[-1].start()
        time.sleep(0.05)  # queued in the order 0, 1, 2
    holder.on_step(100, {})  # hands on, queues behind all three
    order.append("holder")
    for t in threads:
        t.join(5.0)
    assert order == [0, 1, 2, "holder"]
    holder.release()


def test_a_dead_trials_ticket_does_not_block_the_queue(tmp_path):
    (tmp_path / "queue").mkdir()
    (tmp_path / "queue" / "00000000000000000001_999_1").touch()  # unlocked: its process is gone
    lease = CoreLease(tmp_path, cores=1)
    done = threading.Event()
    threading.Thread(target=lambda: (lease.acquire(), done.set()), daemon=True).start()
    assert done.wait(5.0) and lease.held
    assert not (tmp_path / "queue" / "00000000000000000001_999_1").exists()
    lease.release()
