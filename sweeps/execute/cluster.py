"""The Ray cluster a sweep runs on: joining it (or starting a loopback one) and what it can offer.

:func:`cluster_capacity` is the input of :func:`sweeps.plan.resources.plan_concurrency`;
:func:`cluster_machines` decides whether a SQLite MLflow store can serve every trial.
"""

from __future__ import annotations

import ray

from sweeps.plan.address import AddressError, given_address, reach
from sweeps.ray_internals import autoscaler_max_resources, autoscaler_node_groups

__all__ = ["cluster_capacity", "cluster_machines", "connect"]


def connect(address: str | None) -> bool:
    """Join the Ray cluster at ``address``/``RAY_ADDRESS``, or start a local one bound to loopback.

    Returns:
        True when this call connected (the caller disconnects with ``ray.shutdown()``); False when
        the process was already connected (a test session, a notebook).

    Raises:
        AddressError: the address is refused, or no Ray GCS answers there (:func:`sweeps.plan.address.reach`).
    """
    if ray.is_initialized():
        return False
    given = given_address(address)
    if given is not None:
        text, source = given
        target = reach(text, source)  # asked right before joining: ray.init alone would retry for minutes
        try:
            ray.init(address=target, logging_level="WARNING")
        except (ConnectionError, RuntimeError) as exc:  # the GCS answered, the join did not (RuntimeError: another
            # Ray version, Ray's utils.py check_version_info)
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise AddressError(f"{source} {text}: Ray could not join {target}: {first}") from None
    else:
        from sweeps.execute import local_cluster

        local_cluster.start()
    return True


def cluster_capacity(remote: bool) -> dict[str, float]:
    """CPUs and GPUs for :func:`sweeps.plan.resources.plan_concurrency`: the nodes up now, or, on a ``remote``
    cluster, the most it could offer — the larger of its nodes and the node-group bounds an
    autoscaler publishes in the GCS (none on a fixed cluster: then its nodes).
    """
    present = ray.cluster_resources()
    bounds = autoscaler_max_resources() if remote else {}  # no public API reads it (sweeps/ray_internals.py)
    return {k: max(float(present.get(k, 0.0)), float(bounds.get(k, 0))) for k in ("CPU", "GPU")}


def cluster_machines(remote: bool) -> int:
    """Machines the cluster spans (distinct node addresses: nodes of one host share its files), or on a
    ``remote`` cluster whose autoscaler publishes its bounds, the most it could grow to (unbounded: 2).
    """
    hosts = {n["NodeManagerAddress"] for n in ray.nodes() if n["Alive"]}
    groups = autoscaler_node_groups() if remote else []
    bound = sum(2 if most == -1 else most for _, most in groups)
    return max(len(hosts), bound)
