"""The local Ray cluster of a sweep run without ``--address``: every listener on 127.0.0.1.

``ray.init(_node_ip_address="127.0.0.1")`` alone does not keep Ray on loopback: Ray 2.x resolves a
loopback node address to the machine's routable one (``ray._private.services.resolve_ip_for_localhost``),
so the GCS, raylet, object manager, driver and workers listen on every interface, the autoscaler
monitor's and dashboard's Prometheus endpoints on 0.0.0.0, and the dashboard and runtime-env agents on
the routable address. Ray keeps the node on loopback only while ``ray_constants.ENABLE_RAY_CLUSTER`` is
false (its default on macOS/Windows, set by ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``): then the node
address is 127.0.0.1, each gRPC server binds it, and the metrics servers bind loopback because the
node's address is loopback (``monitor.py``/``dashboard/head.py``: ``addr=get_localhost_ip()`` when
``is_localhost``). :func:`start` sets both, for this process and for the Ray processes it spawns.

A SIGKILLed driver cannot shut its cluster down: the GCS and raylet notice, but the dashboard and
runtime-env agents and idle workers may keep listening for up to a minute. Each start records its
session folder under ``<tmp>/cdm-ray-sessions/<pid>.json``; the next start ends (by process id)
the processes still holding files in the session folder of a driver that is gone.
"""

from __future__ import annotations

import atexit
import json
import os
import signal
import tempfile
from pathlib import Path

__all__ = ["LOOPBACK_ENV", "SESSION_RECORDS", "reap_stale_sessions", "session_pids", "start"]

LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
"""Ray's switch that, set to ``0``, keeps a node's address (and so its listeners) on loopback."""

SESSION_RECORDS = Path(tempfile.gettempdir()) / "cdm-ray-sessions"
"""One ``<driver pid>.json`` per running local sweep: its session folder, for the next start's clean-up."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def session_pids(session_dir: str) -> set[int]:
    """Processes of this user holding an open file under ``session_dir`` (every Ray process of a
    session writes its logs there; agents' command lines are renamed, their open logs are not)."""
    found = set()
    prefix = session_dir.rstrip("/") + "/"
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            for fd in (entry / "fd").iterdir():
                if os.readlink(fd).startswith(prefix):
                    found.add(int(entry.name))
                    break
        except OSError:  # gone meanwhile, or another user's
            continue
    return found - {os.getpid()}


def reap_stale_sessions() -> list[int]:
    """End the leftover processes of local sessions whose driver died; returns their ids."""
    if not SESSION_RECORDS.is_dir():
        return []
    ended = []
    for record in SESSION_RECORDS.glob("*.json"):
        try:
            info = json.loads(record.read_text())
            driver, session_dir = int(info["pid"]), str(info["session_dir"])
        except (OSError, ValueError, KeyError, TypeError):
            record.unlink(missing_ok=True)
            continue
        if not Path(session_dir).name.startswith("session_"):  # only ever a Ray session folder, never "/"
            record.unlink(missing_ok=True)
            continue
        if _alive(driver):
            continue
        for pid in sorted(session_pids(session_dir)):
            try:
                os.kill(pid, signal.SIGKILL)
                ended.append(pid)
            except ProcessLookupError:
                pass
        record.unlink(missing_ok=True)
    return ended


def _record(session_dir: str) -> None:
    SESSION_RECORDS.mkdir(parents=True, exist_ok=True)
    record = SESSION_RECORDS / f"{os.getpid()}.json"
    record.write_text(json.dumps({"pid": os.getpid(), "session_dir": session_dir}))
    atexit.register(record.unlink, missing_ok=True)


def start(**init_kwargs) -> None:
    """Start a new local Ray cluster of this process, bound to 127.0.0.1, after reaping stale sessions."""
    import ray
    import ray._private.ray_constants as constants

    ended = reap_stale_sessions()
    if ended:
        print(f"ended {len(ended)} leftover Ray processes of an earlier sweep whose driver was killed", flush=True)
    # The environment reaches the GCS, raylet, agents and workers started now; the constant is read
    # at call time by ray._private.services.get_node_ip_address in this process, which may have
    # imported ray before the variable was set. Both are put back once the node exists (its address
    # is fixed then), so a later cluster joined by address in this process is not pinned to loopback.
    saved_env, saved_flag = os.environ.get(LOOPBACK_ENV), constants.ENABLE_RAY_CLUSTER
    os.environ[LOOPBACK_ENV], constants.ENABLE_RAY_CLUSTER = "0", False
    try:
        # address="local": always a new cluster of our own; plain ray.init() would join any cluster
        # another process left running on this machine.
        ray.init(address="local", _node_ip_address="127.0.0.1", include_dashboard=False, logging_level="WARNING",
                 **init_kwargs)
    finally:
        constants.ENABLE_RAY_CLUSTER = saved_flag
        if saved_env is None:
            os.environ.pop(LOOPBACK_ENV)
        else:
            os.environ[LOOPBACK_ENV] = saved_env
    _record(ray._private.worker._global_node.get_session_dir_path())
