"""One running sweep per sweep folder: an exclusive lock taken before the folder is looked at.

"Does the folder already hold a sweep?" followed by "create it" lets two copies of one spec started
together both pass the check. So the runner first takes an ``flock`` on a lock file beside the
sweep folder (``<storage>/<spec>/.<profile>.lock``; for an object-store URI, in this machine's
temporary folder, keyed by the URI) and holds it until it exits. The kernel drops the lock when the
process dies, SIGKILL included, so a killed sweep never leaves a stale claim (its file stays, and the
next copy locks it again). A sweep that ends removes the file while it still holds the lock, and the
folders the claim created if they stayed empty, so a sweep refused after its claim (say, a SQLite
store on a cluster of several machines) leaves nothing behind. A copy that locked the file just
before it was removed finds that it no longer is the file at that path, and tries again.

The lock file records who holds it (process id, host, and once created the MLflow parent run), so
the copy that is refused can say where the running sweep logs.

Nothing here follows a link it did not make: the lock file is opened with ``O_NOFOLLOW`` and must be a
plain file of this user with one name (a link or a hard link planted there would have the claim
truncate its target), and the temporary folder of object-store claims is this user's, mode 0700
(:func:`sweeps.store.files.private_folder`). Either is refused with :class:`ClaimError` naming the path.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import socket
import stat
import tempfile
from pathlib import Path

from cdm.io.files import is_uri
from cdm.io.json import parse_json
from sweeps.store.files import StoreError, private_folder

__all__ = ["ClaimError", "SweepClaim", "claim", "claims_folder"]


class ClaimError(RuntimeError):
    """Another process is running a sweep in this folder, or a link or someone else's file stands where the
    lock should be; the message says which and where."""


def claims_folder() -> Path:
    """Where object-store sweeps keep their lock files: one folder per user in the temporary folder."""
    return Path(tempfile.gettempdir()) / f"cdm-sweep-claims-{os.getuid()}"


def _lock_path(sweep_dir: str) -> Path:
    if is_uri(sweep_dir):
        key = hashlib.sha256(sweep_dir.encode()).hexdigest()[:16]
        try:
            return private_folder(claims_folder()) / f"{key}.lock"
        except StoreError as exc:
            raise ClaimError(str(exc)) from None
    folder = Path(sweep_dir)
    return folder.parent / f".{folder.name}.lock"


def _open_lock(path: Path) -> int:
    """Open (creating) the lock file without following a link; refuse anything but this user's plain file
    with a single name."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ClaimError(f"{path}: a symbolic link where the sweep's lock file should be; remove it "
                             "(a claim never follows one)") from None
        raise
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1 or info.st_uid != os.getuid():
        os.close(fd)
        raise ClaimError(f"{path}: not a plain file of this user with one name (uid {info.st_uid}, "
                         f"{info.st_nlink} links) where the sweep's lock file should be; remove it")
    return fd


class SweepClaim:
    """The held lock of one sweep folder; :meth:`record` notes the parent run for a refused copy."""

    def __init__(self, sweep_dir: str, fd: int, path: Path, created: list[Path]):
        self.sweep_dir, self._fd, self._path, self._created = sweep_dir, fd, path, created

    def record(self, tracking_uri: str | None = None, parent_run_id: str | None = None) -> None:
        """Write who holds the claim into the lock file, with the MLflow parent run once there is one."""
        holder = {"pid": os.getpid(), "host": socket.gethostname(), "sweep_dir": self.sweep_dir}
        if parent_run_id is not None:
            holder |= {"tracking_uri": tracking_uri, "parent_run_id": parent_run_id}
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, json.dumps(holder).encode(), 0)

    def release(self) -> None:
        """Remove the lock file and the folders :func:`claim` created that stayed empty; drop the lock."""
        if self._fd < 0:
            return
        self._path.unlink(missing_ok=True)  # while still locked: see the module's docstring
        for folder in self._created:  # deepest first
            try:
                folder.rmdir()
            except OSError as exc:
                if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOENT):
                    raise
                break  # the sweep (or another claim) put something there: keep it and what holds it
        os.close(self._fd)  # closing the descriptor drops the flock
        self._fd = -1


def _holder_text(fd: int) -> str:
    try:
        holder = parse_json(os.pread(fd, 4096, 0) or b"{}", "sweep lock", "its holder record")
    except ValueError:  # damaged, or planted: the holder stays unnamed
        holder = {}
    who = f"process {holder['pid']} on {holder['host']}" if "pid" in holder else "another process"
    if "parent_run_id" in holder:
        return f"{who}; its MLflow parent run is {holder['parent_run_id']} in {holder['tracking_uri']}"
    return f"{who}, still starting (no MLflow parent run yet)"


def claim(sweep_dir: str) -> SweepClaim:
    """Take the sweep folder ``sweep_dir`` for this process (creates the folder holding the lock file).

    Raises:
        ClaimError: another live process holds it, or a link or someone else's file is where its lock goes.
    """
    path = _lock_path(sweep_dir)
    while True:
        created = [p for p in [path.parent, *path.parent.parents] if not p.exists()]  # deepest first
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = _open_lock(path)
        except (FileNotFoundError, FileExistsError):  # an ending claim removed a folder meanwhile
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            text = _holder_text(fd)
            os.close(fd)
            raise ClaimError(f"{sweep_dir}: a sweep is already running there ({text}); wait for it to end, "
                             "or stop it and pass --resume") from None
        if _same_file(fd, path):
            break
        os.close(fd)  # locked a file its holder removed on release: lock the one at the path now
    held = SweepClaim(sweep_dir, fd, path, created)
    held.record()
    return held


def _same_file(fd: int, path: Path) -> bool:
    try:
        at_path = path.stat()
    except FileNotFoundError:
        return False
    held = os.fstat(fd)
    return (held.st_dev, held.st_ino) == (at_path.st_dev, at_path.st_ino)
