"""Ray resource sizing of a sweep: what one trial reserves and how many trials run at once."""

from __future__ import annotations

from dataclasses import dataclass

from sweeps.plan.profiles import Resources
from sweeps.plan.schema_base import SpecError

__all__ = ["Concurrency", "plan_concurrency"]


@dataclass(frozen=True)
class Concurrency:
    """How trials map onto the cluster: what each trial asks for and how many run at once."""

    trial_resources: dict[str, float]
    """What the Tune trial's own actor reserves (it runs the loop itself in local mode)."""
    cpus_per_trial: float
    gpus_per_trial: float
    max_concurrent: int
    cpus: float
    gpus: float
    """What the cluster has (with ``remote``: could offer) that this sizing is for."""


def plan_concurrency(
    resources: Resources, cpus: float, gpus: float, num_trials: int, remote: bool = False
) -> Concurrency:
    """Size concurrency from the cluster so trials never wait on each other for CPUs (no deadlock).

    In local mode (``workers_per_trial == 0``) the trial's actor trains, so it reserves the worker's
    CPUs/GPUs. With real Train workers the trial actor only waits on ``TorchTrainer.fit``; it
    reserves a token CPU and the workers are counted against the cap instead.

    Args:
        cpus, gpus: what the cluster has; with ``remote``, the most it could offer (its nodes, or
            the bounds its autoscaler publishes: :func:`sweeps.execute.cluster.cluster_capacity`).
        remote: a cluster joined by address, which may autoscale. Only one trial must fit, and
            concurrency is ``resources.max_concurrent_trials`` or every trial at once: waiting
            trials are the demand that makes the autoscaler add nodes (a GPU cluster often starts
            with none), so sizing from the nodes up at start would pin the sweep to them.

    Raises:
        SpecError: one trial needs more than the whole cluster has (could offer, with ``remote``).
    """
    workers = max(1, resources.workers_per_trial)
    per_cpu = workers * resources.cpus_per_worker
    per_gpu = workers * resources.gpus_per_worker
    if resources.workers_per_trial == 0:
        trial = {"cpu": resources.cpus_per_worker, "gpu": resources.gpus_per_worker}
    else:
        trial = {"cpu": 0.01, "gpu": 0.0}
        per_cpu += trial["cpu"]
    if per_cpu > cpus or per_gpu > gpus:
        has = "could offer at most" if remote else "has"
        raise SpecError(
            f"resources: one trial needs {per_cpu:g} CPUs and {per_gpu:g} GPUs "
            f"but the cluster {has} {cpus:g} and {gpus:g}; "
            "lower resources.cpus_per_worker / gpus_per_worker / workers_per_trial"
            + (
                "; or give the cluster a node type that fits one trial (its autoscaler's bounds count, where it "
                "publishes them; otherwise the nodes up now: keep one such node up, e.g. min_workers: 1)"
                if remote
                else ""
            )
        )
    if remote:
        return Concurrency(
            trial, per_cpu, per_gpu, min(resources.max_concurrent_trials or num_trials, num_trials), cpus, gpus
        )
    # The small epsilon keeps 2 CPUs / 0.4 at 5, not 4.999… → 4 (Ray itself counts in 1e-4 units).
    fit = int(cpus / per_cpu + 1e-6)
    if per_gpu > 0:
        fit = min(fit, int(gpus / per_gpu + 1e-6))
    cap = resources.max_concurrent_trials or fit
    return Concurrency(trial, per_cpu, per_gpu, max(1, min(fit, cap, num_trials)), cpus, gpus)
