"""The local Ray cluster the integration tests share a module's sweeps on."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import ray


@contextmanager
def local_ray() -> Iterator[str]:
    """A 2-CPU Ray cluster of our own on 127.0.0.1 (``address="local"``: never another ``ray start``
    cluster of this machine); yields its GCS address and shuts it down on exit."""
    ray.init(address="local", _node_ip_address="127.0.0.1", include_dashboard=False, num_cpus=2, logging_level="WARNING")
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()
