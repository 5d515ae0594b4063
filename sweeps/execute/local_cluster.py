"""The local Ray cluster of a sweep run without ``--address``: every listener on 127.0.0.1.

``ray.init(_node_ip_address="127.0.0.1")`` alone does not keep Ray on loopback: Ray 2.x resolves a
loopback node address to the machine's routable one (Ray's ``services.resolve_ip_for_localhost``),
so the GCS, raylet, object manager, driver and workers listen on every interface, the autoscaler
monitor's and dashboard's Prometheus endpoints on 0.0.0.0, and the dashboard and runtime-env agents on
the routable address. Ray keeps the node on loopback only while ``ray_constants.ENABLE_RAY_CLUSTER`` is
false (its default on macOS/Windows, set by ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``): then the node
address is 127.0.0.1, each gRPC server binds it, and the metrics servers bind loopback because the
node's address is loopback (``monitor.py``/``dashboard/head.py``: ``addr=get_localhost_ip()`` when
``is_localhost``). :func:`start` sets both, for this process and for the Ray processes it spawns.

A SIGKILLed driver cannot shut its cluster down: the GCS and raylet notice, but the dashboard and
runtime-env agents and idle workers may keep listening for up to a minute. Each start records its
session folder under ``<tmp>/cdm-ray-sessions-<uid>/<pid>.json``; the next start ends (by process id)
the processes still holding files in the session folder of a driver that is gone.

Ending a process is trusted only as far as the record is: records are read only from this user's
own folder of mode 0700 (:func:`sweeps.store.files.private_folder`; anyone may write the shared
temporary folder, and a planted record would name someone else's folder), and a process is ended
only if it is this user's, holds a file in the recorded session folder, and its command line is a
Ray process's of that session (:func:`is_session_process`).
"""

from __future__ import annotations

import atexit
import json
import logging
import os
import signal
import stat
import sys
import tempfile
import threading
from pathlib import Path

from cdm.interrupt import INTERRUPTED
from cdm.io.json import read_json
from sweeps.ray_internals import TOKEN_NOTE_LOGGER, loopback_flag, set_loopback_flag
from sweeps.store.files import StoreError, private_folder, write_private

__all__ = [
    "LOOPBACK_ENV",
    "DeliberateTokenNote",
    "TOKEN_NOTE_LOGGER",
    "SESSION_RECORDS",
    "descendants",
    "is_session_process",
    "private_token",
    "reap_stale_sessions",
    "session_pids",
    "start",
]

LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
"""Ray's switch that, set to ``0``, keeps a node's address (and so its listeners) on loopback."""

SESSION_RECORDS = Path(tempfile.gettempdir()) / f"cdm-ray-sessions-{os.getuid()}"
"""One ``<driver pid>.json`` per running local sweep: its session folder, for the next start's clean-up."""

RAY_TITLES = ("ray::", "ray-dashboard-")
"""How Ray renames its workers and agents (``ray_constants.AGENT_PROCESS_TYPE_*``, ``WORKER_PROCESS_TYPE_*``,
``dashboard/subprocesses/module.py``); the GCS, raylet and monitors keep a command line naming the session."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        pass
    return True


def _pids() -> list[int]:
    """Every process id now (``/proc``)."""
    return [int(entry.name) for entry in Path("/proc").iterdir() if entry.name.isdigit()]


def _cmdline(pid: int) -> str | None:
    """``pid``'s command line, arguments joined by spaces; None when it is gone."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return None


def session_pids(session_dir: str) -> set[int]:
    """Processes of this user holding an open file under ``session_dir`` (every Ray process of a
    session writes its logs there; agents' command lines are renamed, their open logs are not)."""
    found = set()
    prefix = session_dir.rstrip("/") + "/"
    for pid in _pids():
        try:
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                if os.readlink(fd).startswith(prefix):
                    found.add(pid)
                    break
        except OSError:  # gone meanwhile, or another user's
            continue
    return found - {os.getpid()}


def is_session_process(pid: int, session_dir: str) -> bool:
    """``pid`` is this user's and its command line is one of Ray's for the session in ``session_dir``
    (a renamed worker or agent, or one whose arguments name the session)."""
    try:
        if Path(f"/proc/{pid}").stat().st_uid != os.getuid():
            return False
    except OSError:  # gone meanwhile
        return False
    cmdline = _cmdline(pid) or ""
    return cmdline.startswith(RAY_TITLES) or Path(session_dir).name in cmdline


def reap_stale_sessions() -> list[int]:
    """End the leftover processes of local sessions whose driver died; returns their ids.

    Raises:
        StoreError: the records' folder is not this user's private one (nothing is ended).
    """
    if not os.path.lexists(SESSION_RECORDS):
        return []
    private_folder(SESSION_RECORDS)
    ended = []
    for record in SESSION_RECORDS.glob("*.json"):
        try:
            info = read_json(record, "Ray session record")
            driver, session_dir = int(info["pid"]), str(info["session_dir"])
        except (OSError, ValueError, KeyError, TypeError):
            record.unlink(missing_ok=True)
            continue
        if not Path(session_dir).name.startswith("session_"):  # only ever a Ray session folder, never "/"
            record.unlink(missing_ok=True)
            continue
        if _alive(driver):
            continue
        for pid in sorted(p for p in session_pids(session_dir) if is_session_process(p, session_dir)):
            try:
                os.kill(pid, signal.SIGKILL)
                ended.append(pid)
            except ProcessLookupError:
                pass
        record.unlink(missing_ok=True)
    return ended


def _record(session_dir: str) -> None:
    record = private_folder(SESSION_RECORDS) / f"{os.getpid()}.json"
    write_private(record, json.dumps({"pid": os.getpid(), "session_dir": session_dir}))
    atexit.register(record.unlink, missing_ok=True)


def private_token() -> None:
    """Make Ray's token file (``~/.ray/auth_token``, written with the default umask: mode 644) readable by
    this user alone: with it any local user's client is admitted to this user's clusters."""
    token = Path.home() / ".ray" / "auth_token"
    try:
        info = token.lstat()
    except FileNotFoundError:
        return
    if stat.S_ISREG(info.st_mode) and info.st_uid == os.getuid() and info.st_mode & 0o077:
        token.chmod(0o600)


class DeliberateTokenNote(logging.Filter):
    """Drops Ray's 245-character warning that a new local cluster turned token authentication on: it is
    on by our choice (docs/security.md). Its warning that authentication is off still shows."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("Token authentication is enabled for this Ray cluster")


def _abandon_start() -> None:
    """A signal came while ``ray.init`` was starting the cluster: end what it started, now, and end the
    process as soon as the caller's clean-up has run.

    Left to themselves, the processes die with this one, but only at its end, and that end took 4.1–8.2 s
    (docs/security.md): Ray's exit hook imports its compiled-graph modules (~1.5 s on 2 loaded cores) to
    shut down a cluster that never came up, then the interpreter waits seconds in Ray's C++ teardown. So
    this process's Ray children and everything below them are killed here (their command lines are Ray's
    programs', :func:`_ray_children`), and an exit hook registered last, so run first, ends the process
    with :data:`cdm.interrupt.INTERRUPTED` once every ``finally`` on the way out has run, skipping the rest.
    """
    for pid in _ray_children():
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    atexit.register(_exit_interrupted)


def _exit_interrupted() -> None:
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(INTERRUPTED)


def descendants(pid: int) -> set[int]:
    """Every process below ``pid`` now (``/proc/<pid>/stat``'s parent field)."""
    children: dict[int, list[int]] = {}
    for child in _pids():
        try:
            parent = int(Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split()[1])
        except OSError:  # gone meanwhile
            continue
        children.setdefault(parent, []).append(child)
    found, stack = set(), [pid]
    while stack:
        for child in children.get(stack.pop(), []):
            found.add(child)
            stack.append(child)
    return found


def _ray_children() -> list[int]:
    """The processes below this one that run Ray's programs (GCS, raylet, reaper, monitors, workers)."""
    lines = {pid: _cmdline(pid) or "" for pid in descendants(os.getpid())}
    return sorted(pid for pid, line in lines.items() if "/ray/" in line or line.startswith(RAY_TITLES))


def start(**init_kwargs) -> None:
    """Start a new local Ray cluster of this process, bound to 127.0.0.1, after reaping stale sessions."""
    import ray

    private = True
    try:
        ended = reap_stale_sessions()
    except StoreError as exc:  # someone else's records folder: neither read nor written
        print(f"not ending leftover Ray processes, nor recording this session: {exc}", flush=True)
        private, ended = False, []
    if ended:
        print(f"ended {len(ended)} leftover Ray processes of an earlier sweep whose driver was killed", flush=True)
    # The environment reaches the GCS, raylet, agents and workers started now; the constant is read
    # at call time by Ray's services.get_node_ip_address in this process, which may have
    # imported ray before the variable was set. Both are put back once the node exists (its address
    # is fixed then), so a later cluster joined by address in this process is not pinned to loopback.
    note = logging.getLogger(TOKEN_NOTE_LOGGER)
    if not any(isinstance(f, DeliberateTokenNote) for f in note.filters):
        note.addFilter(DeliberateTokenNote())
    saved_env, saved_flag = os.environ.get(LOOPBACK_ENV), loopback_flag()
    os.environ[LOOPBACK_ENV] = "0"
    set_loopback_flag(False)
    main = threading.current_thread() is threading.main_thread()
    sigterm = signal.getsignal(signal.SIGTERM) if main else None
    try:
        # address="local": always a new cluster of our own; plain ray.init() would join any cluster
        # another process left running on this machine.
        ray.init(address="local", _node_ip_address="127.0.0.1", include_dashboard=False, logging_level="WARNING",
                 **init_kwargs)
    except KeyboardInterrupt:
        _abandon_start()
        raise
    except SystemExit as exc:
        if exc.code != signal.SIGTERM:
            raise
        _abandon_start()  # ray.init's own SIGTERM handler (sys.exit(15)) ran: a SIGTERM is Ctrl-C here too
        raise KeyboardInterrupt from None
    finally:
        if main:  # ray.init replaced it with its own, which exits without running the caller's clean-up
            signal.signal(signal.SIGTERM, sigterm)
        set_loopback_flag(saved_flag)
        if saved_env is None:
            os.environ.pop(LOOPBACK_ENV)
        else:
            os.environ[LOOPBACK_ENV] = saved_env
    private_token()
    if private:
        context = ray.get_runtime_context()
        _record(str(Path(context.get_temp_dir()) / context.get_session_name()))
