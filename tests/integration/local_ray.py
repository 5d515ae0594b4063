"""The local Ray cluster the integration tests share a module's sweeps on."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NamedTuple

import pytest
import ray


@contextmanager
def local_ray() -> Iterator[str]:
    """A 2-CPU Ray cluster of our own on 127.0.0.1 (``address="local"``: never another ``ray start``
    cluster of this machine); yields its GCS address and shuts it down on exit."""
    ray.init(
        address="local", _node_ip_address="127.0.0.1", include_dashboard=False, num_cpus=2, logging_level="WARNING"
    )
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


class TwoNodes(NamedTuple):
    address: str  # the head's GCS address, for a driver in another process
    nodes: list[str]  # node ids, head first
    temp_dir: str  # both nodes' Ray temporary folder: what is node-local on a real cluster


@contextmanager
def two_node_cluster() -> Iterator[TwoNodes]:
    """A head and a worker node on 127.0.0.1 (``ray.cluster_utils.Cluster``), 1 CPU each, this process
    connected as the driver. A driver in another process joins with ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``
    in its environment (below: why)."""
    from ray.cluster_utils import Cluster

    # Own temp dir (short: Ray's socket paths must fit ~107 characters): Cluster records its address
    # there, so `address="auto"` elsewhere on this machine never finds this cluster.
    temp_dir = tempfile.mkdtemp(prefix="cdm2n", dir="/tmp")
    common = {"num_cpus": 1, "node_ip_address": "127.0.0.1", "temp_dir": temp_dir}
    # Given node_ip_address 127.0.0.1 the GCS listens on loopback only, but ray.init(address=...)
    # rewrites a loopback host to the machine's outward address (services.resolve_ip_for_localhost,
    # ray#59110) and then cannot reach it. Ray keeps loopback where it thinks clusters are
    # unsupported; say so, in this process only, for as long as the cluster lives.
    patch = pytest.MonkeyPatch()
    patch.setattr(ray._private.ray_constants, "ENABLE_RAY_CLUSTER", False)
    cluster = Cluster(initialize_head=True, head_node_args={**common, "include_dashboard": False})
    try:
        cluster.add_node(**common)
        cluster.wait_for_nodes()
        ray.init(address=cluster.address, logging_level="WARNING")
        nodes = [n["NodeID"] for n in ray.nodes() if n["Alive"]]
        assert len(nodes) == 2 and ray.cluster_resources()["CPU"] == 2
        yield TwoNodes(cluster.address, nodes, temp_dir)
    finally:
        ray.shutdown()
        cluster.shutdown()  # stops exactly the processes of these two nodes
        patch.undo()
        shutil.rmtree(temp_dir, ignore_errors=True)
