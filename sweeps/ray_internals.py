"""Every use of Ray's private API (``ray._private``), in one place: what no public call of Ray 2.60 does.

Ray may change any of these in a minor release without notice. ``tests/test_ray_internals.py`` imports each
name listed in :data:`PRIVATE_NAMES` and fails on a Ray whose minor version is not :data:`TESTED_RAY`, saying
what to re-check; on an upgrade, re-read each function's source file named below, then raise the bound in
``pyproject.toml`` and :data:`TESTED_RAY` together.

What the public API covers is used directly elsewhere: ``ray.cluster_resources()`` and ``ray.nodes()`` size a
sweep, ``ray.get_runtime_context()`` names the session folder (``get_temp_dir()/get_session_name()``).
"""

from __future__ import annotations

__all__ = ["PRIVATE_NAMES", "TESTED_RAY", "TOKEN_NOTE_LOGGER", "autoscaler_max_resources", "autoscaler_node_groups",
           "canonical_address", "gcs_channel", "loopback_flag", "set_log_dedup", "set_loopback_flag"]

TESTED_RAY = "2.60"
"""The Ray minor version these calls were read against (``pyproject.toml`` bounds ray below the next one)."""

TOKEN_NOTE_LOGGER = "ray._private.authentication.authentication_token_setup"
"""The logger of Ray's note that a new local cluster turned token authentication on (its module's ``logger``)."""

PRIVATE_NAMES = (
    ("ray._private.services", "canonicalize_bootstrap_address"),
    ("ray._private.grpc_utils", "init_grpc_channel"),
    ("ray._private.state", "state"),
    ("ray._private.ray_logging", "RAY_DEDUP_LOGS"),
    ("ray._private.ray_constants", "ENABLE_RAY_CLUSTER"),
    (TOKEN_NOTE_LOGGER, "logger"),
)
"""(module, name) of every private name used here, imported by the upgrade test."""


def canonical_address(address: str) -> str:
    """``address`` as Ray's own ``ray.init`` joins it: ``auto`` looked up in the cluster ``ray start`` recorded
    on this machine, a loopback host replaced by the machine's address (``_private/services.py``,
    ``canonicalize_bootstrap_address``; no public equivalent, and a copy would drift from what ray.init does).

    Raises:
        ConnectionError: ``auto`` and no cluster recorded or running on this machine.
    """
    from ray._private.services import canonicalize_bootstrap_address

    return canonicalize_bootstrap_address(address)


def gcs_channel(target: str):
    """A gRPC channel to the GCS at ``target`` (``host:port``) as Ray's clients open it: TLS when
    ``RAY_USE_TLS`` says so, the token interceptor when token authentication is on (``_private/grpc_utils.py``,
    ``init_grpc_channel``; the public API only joins, and ``ray.init`` cannot be bounded in time)."""
    from ray._private.grpc_utils import init_grpc_channel

    return init_grpc_channel(target)


def _state():
    import ray._private.state

    return ray._private.state.state


def autoscaler_max_resources() -> dict[str, float]:
    """The most of each resource an autoscaler's node groups could add up to (``{}`` where none is published):
    the record Ray Data sizes itself by (``_private/state.py``, ``get_max_resources_from_cluster_config``)."""
    return dict(_state().get_max_resources_from_cluster_config() or {})


def autoscaler_node_groups() -> list[tuple[str, int]]:
    """(name, most nodes; -1: unbounded) of each node group an autoscaler publishes in the GCS (``[]`` where
    none is: a fixed cluster); ``_private/state.py``, ``get_cluster_config``."""
    config = _state().get_cluster_config()
    return [(g.name, int(g.max_count)) for g in config.node_group_configs] if config else []


def set_log_dedup(on: bool) -> None:
    """Switch the driver's de-duplication of worker log lines. Ray reads ``RAY_DEDUP_LOGS`` once, at import
    (``_private/ray_logging/__init__.py``); a process that imported Ray before the variable was set (a notebook,
    the test suite) is switched through the module's constant, which its de-duplicator reads per line."""
    import ray._private.ray_logging as ray_logging

    ray_logging.RAY_DEDUP_LOGS = on


def loopback_flag() -> bool:
    """``ray_constants.ENABLE_RAY_CLUSTER`` now (:func:`set_loopback_flag`)."""
    import ray._private.ray_constants as constants

    return constants.ENABLE_RAY_CLUSTER


def set_loopback_flag(enable_cluster: bool) -> None:
    """Set ``ray_constants.ENABLE_RAY_CLUSTER``: false keeps a node's address on loopback
    (``_private/services.py``, ``get_node_ip_address`` reads it at call time; the environment variable
    ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER`` reaches only processes that import Ray after it is set)."""
    import ray._private.ray_constants as constants

    constants.ENABLE_RAY_CLUSTER = enable_cluster
