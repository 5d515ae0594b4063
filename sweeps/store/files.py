"""A sweep's folder: a local path or an object-store URI (``s3://``, ``gs://``, ``file://``), read through
:mod:`cdm.io` and written through :mod:`cdm.io.write` (local) or pyarrow's file systems (object stores).

An object store takes the credentials of this environment (``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``, and
``AWS_ENDPOINT_URL`` for an S3-compatible server other than AWS, as pyarrow reads them; Ray's processes inherit
them from the driver). Tune's state there is pickles: :func:`check_resume_trust` lets ``--resume`` unpickle it
only from a folder no one else could have written, or matching the digests this user recorded
(:func:`record_digest`). Each refusal is a :class:`StoreError` of one line naming the URI or file and what is
allowed.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
import tempfile
import uuid
from pathlib import Path
from typing import Any

from cdm.io.files import is_uri, read_bounded, sha256_from
from cdm.io.json import parse_json, read_json
from cdm.io.write import write_atomic

__all__ = [
    "MAX_NAME", "MAX_STATE_BYTES", "TRUST_FLAG", "StoreError", "check_name", "check_no_links", "check_resume_trust",
    "check_storage", "exists", "is_uri", "location_filesystem", "one_line", "parse_state", "private_folder",
    "publish_files", "read_record", "read_state", "record_digest", "storage_location", "sweep_location",
    "writable_folder", "write_file", "write_private", "write_record",
]

MAX_NAME = 100
"""Longest spec, profile or data set name: one path component, well under the 255 bytes of a file name."""

MAX_STATE_BYTES = 16 * 2**20
"""Most bytes of a sweep's own JSON record read back (``sweep.json``: a spec of the 1,000-trial cap is well under
1 MiB; ``resume_retries.json``)."""

_STATE_KEYS = {"spec": dict, "sets": dict, "profile": str, "tracking_uri": str, "parent_run_id": str}


class StoreError(ValueError):
    """A tracking URI, storage location or record cannot be used; the message says why."""


def one_line(exc: BaseException) -> str:
    """``exc``'s message on one line, its whitespace runs collapsed to single spaces."""
    return " ".join(str(exc).split())


def writable_folder(path: Path, what: str) -> None:
    """``path`` (a folder to create or use) lies under an existing folder this process may write."""
    probe = path
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise StoreError(f"{what} {path}: {probe} is a file, not a folder")
    # A real write, not os.access: root passes every permission check yet cannot write /proc or a
    # read-only mount. The probe file is removed at once.
    try:
        fd, name = tempfile.mkstemp(prefix=".cdm-write-probe-", dir=probe)
    except OSError as exc:
        raise StoreError(
            f"{what} {path}: cannot write in {probe} ({exc.strerror}); choose a folder you can write"
        ) from None
    os.close(fd)
    os.unlink(name)


def location_filesystem(location: str):
    """pyarrow's file system of ``location`` (a path or URI) and the path in it."""
    from pyarrow import fs

    return fs.FileSystem.from_uri(location if is_uri(location) else str(Path(location).resolve()))


def check_storage(sweep_dir: str) -> None:
    """Refuse a sweep folder that cannot be written, before Ray starts (nothing is left behind).

    A local path needs a writable folder above it. An object-store URI needs its bucket to exist and
    to take (and delete) a small probe object at the bucket's top, where removing it leaves no folder
    marker behind in the sweep's own path.
    """
    if not is_uri(sweep_dir):
        writable_folder(Path(sweep_dir), "--out")
        return
    from pyarrow import fs

    try:
        filesystem, path = fs.FileSystem.from_uri(sweep_dir)
    except (ValueError, OSError) as exc:
        raise StoreError(f"--out {sweep_dir}: {one_line(exc)}") from None
    if isinstance(filesystem, fs.LocalFileSystem):
        writable_folder(Path(path), "--out")
        return
    bucket = path.split("/", 1)[0]
    try:
        info = filesystem.get_file_info(bucket)
        if info.type == fs.FileType.NotFound:
            raise StoreError(f"--out {sweep_dir}: bucket {bucket!r} does not exist; create it first")
        probe = f"{bucket}/.cdm-write-probe-{uuid.uuid4().hex}"
        with filesystem.open_output_stream(probe) as stream:
            stream.write(b"probe")
        filesystem.delete_file(probe)
    except OSError as exc:
        raise StoreError(f"--out {sweep_dir}: cannot write to bucket {bucket!r} with this environment's "
                         f"credentials ({one_line(exc)})") from None


def parse_state(raw: bytes, where: str) -> dict[str, Any]:
    """The ``sweep.json`` a sweep wrote when it started: spec, ``--set`` values, profile, MLflow store, parent run.

    Raises:
        StoreError: not JSON, or a key missing or of the wrong type.
    """
    try:  # nesting bounded: a planted file deep enough would overflow the parser's recursion
        state = parse_json(raw, "--resume", Path(where))
    except ValueError as exc:
        raise StoreError(f"{exc}; {where} is damaged: remove the folder to start over") from None
    if not isinstance(state, dict):
        raise StoreError(f"--resume: {where} is damaged (a JSON {type(state).__name__}, not an object); "
                         "remove the folder to start over")
    for key, kind in _STATE_KEYS.items():
        if not isinstance(state.get(key), kind):
            raise StoreError(f"--resume: {where} is damaged ({key}: expected a JSON "
                             f"{'object' if kind is dict else 'string'}); remove the folder to start over")
    return state


def read_record(location: str) -> bytes:
    """The bytes of the sweep's own record file at ``location`` (a path or URI), refused past
    :data:`MAX_STATE_BYTES` (:func:`cdm.io.files.read_bounded`)."""
    try:
        return read_bounded(location, "--resume", MAX_STATE_BYTES)
    except ValueError as exc:
        raise StoreError(f"{exc}; not a sweep's record: remove the folder to start over") from None


def read_state(location: str) -> dict[str, Any]:
    """The sweep's ``sweep.json`` at ``location`` (:func:`read_record`, :func:`parse_state`)."""
    return parse_state(read_record(location), location)


def write_record(location: str, text: str) -> None:
    """Write ``text`` to the file ``location`` of a sweep folder: :func:`write_file` for a path, pyarrow for a URI."""
    if not is_uri(location):
        write_file(Path(location), text)
        return
    filesystem, path = location_filesystem(location)
    with filesystem.open_output_stream(path) as stream:
        stream.write(text.encode())


def storage_location(sweep_dir: str, fs_path: str) -> str:
    """A path Ray's storage file system gives (``Checkpoint.path``: a URI's scheme and query stripped, as
    pyarrow's ``FileSystem.from_uri`` does) as the sweep's storage spells it: unchanged for a local sweep folder,
    ``s3://bucket/…`` again for ``s3://bucket/…`` storage."""
    if not is_uri(sweep_dir):
        return fs_path
    return f"{sweep_dir.split('://', 1)[0]}://{fs_path}"


def check_name(name: str, what: str) -> None:
    """Refuse a name that would not stay one path component below ``--out``: empty, ``.``/``..``,
    a separator or NUL, a leading dot (hidden, and the lock files' prefix), or longer than :data:`MAX_NAME`."""
    if not name or name in (".", "..") or name.startswith(".") or any(c in name for c in "/\\\0"):
        raise StoreError(f"{what} {name[:MAX_NAME]!r}: not a plain name; use letters, digits, '_', '-' and '.' "
                         "(not first), without '/'")
    if len(name) > MAX_NAME:
        raise StoreError(f"{what} {name[:40]!r}…: {len(name)} characters; a name may have at most {MAX_NAME}")


def sweep_location(storage: str, spec: str, profile: str) -> str:
    """``<storage>/<spec>/<profile>``: an absolute path, or a URI joined as a string (no Path: it eats ``//``).

    Only ``storage`` itself is resolved (the user named it, links included); ``spec`` and ``profile`` are
    checked by :func:`check_name` and a link in their place is refused (:func:`check_no_links`).
    """
    check_name(spec, "spec name")
    check_name(profile, "profile")
    if is_uri(storage):
        return f"{storage.rstrip('/')}/{spec}/{profile}"
    return str(Path(storage).resolve() / spec / profile)


def check_no_links(sweep_dir: str) -> None:
    """Refuse a local sweep folder where ``<spec>`` or ``<profile>`` below the storage is a symbolic link:
    whoever made it would choose where the sweep writes (a dangling one, too)."""
    if is_uri(sweep_dir):
        return
    folder = Path(sweep_dir)
    for path in (folder.parent, folder):
        if path.is_symlink():
            raise StoreError(f"--out: {path} is a symbolic link (to {os.readlink(path)}); a sweep folder is never "
                             "followed through a link: remove it, or give its target as --out")


def private_folder(path: Path) -> Path:
    """``path`` as a folder of this user with mode 0700, made so if absent (for files kept in a shared
    temporary folder, where anyone could make the folder first).

    Raises:
        StoreError: ``path`` is a link, not a folder, another user's, or others can use it.
    """
    try:
        path.mkdir(mode=0o700, parents=True)
    except FileExistsError:
        pass
    info = path.lstat()
    if stat.S_ISLNK(info.st_mode) or not stat.S_ISDIR(info.st_mode):
        raise StoreError(f"{path}: a link or a file where this user's private folder should be; remove it")
    if info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise StoreError(f"{path}: owned by uid {info.st_uid} with mode {stat.S_IMODE(info.st_mode):o}; this user's "
                         "private folder must be its own with mode 700: remove it (someone else may have made it)")
    return path


def write_file(path: Path, text: str | bytes, mode: int = 0o644) -> None:
    """Write ``text`` (or bytes) to ``path`` (made with ``mode`` if absent) through the one no-follow atomic
    writer (:func:`cdm.io.write.write_atomic`): a link standing at ``path`` is refused, its target untouched."""
    try:
        write_atomic(path, text, "sweep", mode=mode)
    except ValueError as exc:
        raise StoreError(str(exc)) from None


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` with mode 600 (:func:`write_file`)."""
    write_file(path, text, 0o600)


def exists(location: str) -> bool:
    from pyarrow import fs

    filesystem, path = location_filesystem(location)
    return filesystem.get_file_info(path).type != fs.FileType.NotFound


def publish_files(local: Path, location: str) -> None:
    """Copy the staging folder ``local`` into the sweep folder ``location`` (a URI; local paths write in place)."""
    from pyarrow import fs

    filesystem, path = location_filesystem(location)
    filesystem.create_dir(path, recursive=True)
    fs.copy_files(str(local), path, source_filesystem=fs.LocalFileSystem(), destination_filesystem=filesystem)


TRUST_FLAG = "--trust-storage"
"""The way out of :func:`check_resume_trust` for storage this user alone writes but cannot prove it."""


def _untrusted_entry(top: Path) -> str | None:
    """The first entry under ``top`` (itself included) that another user could have written: a link, an
    entry of another user, or one others may write (as ssh treats ``~/.ssh``); None when there is none."""
    uid = os.getuid()
    for folder, dirs, files in os.walk(top, followlinks=False):
        for entry in [Path(folder), *(Path(folder) / n for n in dirs + files)]:
            info = entry.lstat()
            if stat.S_ISLNK(info.st_mode):
                return f"{entry} is a symbolic link"
            if info.st_uid != uid:
                return f"{entry} belongs to uid {info.st_uid}"
            if info.st_mode & 0o022:
                return f"{entry} can be written by others (mode {stat.S_IMODE(info.st_mode):o})"
    return None


def _digest_file(sweep_dir: str) -> Path:
    state = Path(os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state")
    key = hashlib.sha256(sweep_dir.encode()).hexdigest()[:32]
    return private_folder(state / "cdm" / "sweep-digests") / f"{key}.json"


def _tune_state_digests(sweep_dir: str) -> dict[str, str]:
    """SHA-256 of every file of the sweep folder Tune may unpickle: all but the checkpoints' contents
    (safetensors and JSON, read by :func:`cdm.checkpoint.load_checkpoint`: nothing there is unpickled), keyed
    by their path below the folder."""
    from pyarrow import fs

    filesystem, root = location_filesystem(sweep_dir)
    digests = {}
    for info in filesystem.get_file_info(fs.FileSelector(root, recursive=True, allow_not_found=True)):
        rel = info.path[len(root):].lstrip("/")
        if info.type != fs.FileType.File or any(part.startswith("checkpoint_") for part in rel.split("/")[:-1]):
            continue
        digests[rel] = sha256_from(filesystem, info.path, "--resume")
    return digests


def record_digest(sweep_dir: str) -> None:
    """Note, where only this user writes, the digests of an object-store sweep's Tune state as this driver
    leaves it, so the next ``--resume`` can tell it untouched (:func:`check_resume_trust`)."""
    write_private(_digest_file(sweep_dir), json.dumps(_tune_state_digests(sweep_dir)))


def check_resume_trust(sweep_dir: str) -> None:
    """Refuse to let Tune unpickle (``tuner.pkl``, ``experiment_state-*.json``, searcher state) a sweep folder
    that someone else could have written: unpickling runs whatever code the file names.

    A local folder passes when every entry is this user's, no link, and not writable by others. An
    object-store folder cannot show who wrote it: it passes when its files match the digests
    :func:`record_digest` kept when the last driver exited (a killed driver kept none).

    Raises:
        StoreError: naming the file or the missing record, and the way out (:data:`TRUST_FLAG`).
    """
    way_out = (f"if you alone write this storage, pass {TRUST_FLAG}; else start the sweep over in a new folder "
               "(finished trials are in MLflow)")
    if not is_uri(sweep_dir):
        if bad := _untrusted_entry(Path(sweep_dir)):
            raise StoreError(f"--resume: {bad}; Tune's state there is unpickled (runs code) only from a folder "
                             f"no one else could write: {way_out}")
        return
    if not _digest_file(sweep_dir).is_file():
        raise StoreError(f"--resume: no digest of {sweep_dir}'s Tune state was recorded (its driver was killed); "
                         f"that state is pickles anyone who writes the bucket could have changed: {way_out}")
    try:
        recorded = read_json(_digest_file(sweep_dir), "--resume")
    except ValueError as exc:
        raise StoreError(f"{exc}; the digest of Tune's state is damaged: {way_out}") from None
    if not isinstance(recorded, dict):
        raise StoreError(f"--resume: {_digest_file(sweep_dir)} is damaged (not a JSON object): {way_out}")
    found = _tune_state_digests(sweep_dir)
    changed = sorted(k for k in recorded.keys() | found.keys() if recorded.get(k) != found.get(k))
    if changed:
        raise StoreError(f"--resume: {sweep_dir}/{changed[0]} differs from what this user's last driver left "
                         f"({len(changed)} file(s) changed); Tune would unpickle it: {way_out}")
