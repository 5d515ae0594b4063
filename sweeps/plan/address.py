"""The Ray cluster a command joins (``--address``, else ``RAY_ADDRESS``): its form checked before anything
runs, then its GCS asked for the cluster's id within a bounded time.

``ray.init(address=…)`` on an address where no Ray GCS answers retries for minutes inside Ray's C++ client
(20 tries of a 5 s connect plus a 30 s wait for the cluster id, Ray's ``node.py`` ``_init_gcs_client``),
and no Ctrl-C or SIGTERM reaches Python meanwhile. :func:`reach` asks first, from Python, where a signal
interrupts at once: a TCP connect, then the GCS's own ``GetClusterId`` call (what Ray's client sends first),
each within :data:`REPLY_S`, so a wrong address is one line naming where it came from.
"""

from __future__ import annotations

import os
import re
import socket

__all__ = ["FORMS", "REPLY_S", "AddressError", "check_form", "given_address", "reach"]

FORMS = ("host:port of the cluster's head (its GCS, port 6379 unless `ray start --port` said otherwise, "
         "e.g. 10.0.0.10:6379), or auto (the cluster `ray start` runs on this machine)")
"""What ``--address`` / ``RAY_ADDRESS`` may hold, said in each refusal."""

REPLY_S = 8.0
"""Seconds the TCP connect, then the GCS's reply, may each take: a head across a data centre answers in
milliseconds; two such waits plus Ray's import stay within the 30 s a user is promised a verdict in."""

_HOST_PORT = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):([0-9]{1,5})$")


class AddressError(ValueError):
    """A Ray address refused; the message names ``--address`` or ``RAY_ADDRESS`` and what is allowed."""


def given_address(address: str | None) -> tuple[str, str] | None:
    """(the address to join, the name of where it came from), or None where a local cluster is started."""
    if address is not None:
        return address, "--address"
    env = os.environ.get("RAY_ADDRESS")
    return (env, "RAY_ADDRESS") if env else None


def check_form(address: str, source: str) -> None:
    """Refuse an address that is no Ray GCS address, without asking the network."""
    if address == "auto":
        return
    if address == "local":
        raise AddressError(f"{source} local: leave {source} out for a cluster of this command's own (on 127.0.0.1); "
                           f"to join one give {FORMS}")
    if address.startswith(("http://", "https://")):
        raise AddressError(f"{source} {address}: that is a dashboard's address, for `ray job submit`; give {FORMS}")
    if "://" in address:
        # Ray Client runs the driver's Ray calls through a proxy that lacks the cluster-state calls a sweep sizes
        # itself by; a job submitted to the cluster runs the command on the head instead.
        raise AddressError(f"{source} {address}: Ray Client addresses are not supported (submit the command with "
                           f"`ray job submit`, cluster/README.md); give {FORMS}")
    match = _HOST_PORT.match(address)
    if match is None or not 0 < int(match.group(2)) < 65536:
        raise AddressError(f"{source} {address}: not a Ray address; give {FORMS}")


def reach(address: str, source: str) -> str:
    """Check ``address`` and that a Ray GCS answers there; returns the address Ray joins (``auto`` found,
    a loopback host replaced by this machine's address as Ray does).

    Raises:
        AddressError: a bad form, no cluster found for ``auto``, nothing reachable there, or no Ray GCS
            answering (or one that wants a token this client lacks), within ``2 × REPLY_S``.
    """
    check_form(address, source)
    import grpc
    from ray.core.generated.gcs_service_pb2 import GetClusterIdRequest
    from ray.core.generated.gcs_service_pb2_grpc import NodeInfoGcsServiceStub

    from sweeps.ray_internals import canonical_address, gcs_channel

    try:
        target = canonical_address(address)
    except ConnectionError:  # auto, and no cluster recorded or running on this machine
        raise AddressError(f"{source} auto: no Ray cluster runs on this machine; start one (`ray start --head`) "
                           f"or give {FORMS}") from None
    host, _, port = target.rpartition(":")
    where = f"{source} {address}" + (f" (joined as {target})" if target != address else "")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=REPLY_S).close()
    except TimeoutError:
        raise AddressError(f"{where}: no answer within {REPLY_S:.0f} s; check the head's address and that its "
                           "port is open to this machine") from None
    except OSError as exc:
        raise AddressError(f"{where}: cannot connect ({exc.strerror or exc}); is the cluster running? "
                           f"Give {FORMS}") from None
    channel = gcs_channel(target)
    try:
        NodeInfoGcsServiceStub(channel).GetClusterId.future(GetClusterIdRequest(), timeout=REPLY_S).result()
    except grpc.RpcError as exc:
        if exc.code() == grpc.StatusCode.UNAUTHENTICATED:
            raise AddressError(f"{where}: the cluster asks for its token; run with RAY_AUTH_MODE=token and the "
                               "cluster's token in ~/.ray/auth_token (or RAY_AUTH_TOKEN)") from None
        timed_out = exc.code() == grpc.StatusCode.DEADLINE_EXCEEDED
        said = (f"nothing answered as a Ray GCS within {REPLY_S:.0f} s" if timed_out
                else f"what answers is not a Ray GCS ({exc.code().name})")
        raise AddressError(f"{where}: something listens there but {said}; give {FORMS}") from None
    finally:
        channel.close()
    return target
