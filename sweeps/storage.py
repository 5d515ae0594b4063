"""Where a sweep keeps its files and runs, checked before Ray starts and before any MLflow run exists.

- :func:`check_tracking_uri`: an MLflow store MLflow can open (``sqlite:``, ``file:``, ``http(s):``,
  a database URL), whose folder can be written (SQLite, files) or whose server answers (HTTP).
- :func:`check_storage`: a sweep folder that can be created — a local path under a writable folder,
  or an object-store URI (``s3://``, ``gs://``, ``file://``) whose bucket exists and takes a write
  with the credentials of this environment (``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``, and
  ``AWS_ENDPOINT_URL`` for an S3-compatible server other than AWS, as pyarrow reads them; Ray's
  processes inherit them from the driver).
- :func:`parse_state`: a sweep's ``sweep.json`` as ``--resume`` needs it.
- :func:`sweep_location`, :func:`exists`, :func:`read_text`, :func:`publish_files`: a sweep folder
  named by a local path or a URI, read and written through pyarrow's file systems.

Each refusal is a :class:`StoreError` of one line naming the URI or file and what is allowed.
"""

from __future__ import annotations

import json
import os
import tempfile
import urllib.error
import urllib.parse
import urllib.request
import uuid
from pathlib import Path
from typing import Any

__all__ = ["TRACKING_SCHEMES", "StoreError", "check_storage", "check_tracking_uri", "exists", "is_uri", "parse_state",
           "publish_files", "read_text", "sweep_location"]

TRACKING_SCHEMES = ("sqlite", "file", "http", "https", "postgresql", "mysql", "mssql")
"""MLflow stores a sweep can log to."""

_STATE_KEYS = {"spec": dict, "sets": dict, "profile": str, "tracking_uri": str, "parent_run_id": str}


class StoreError(ValueError):
    """A tracking URI, storage location or state file cannot be used; the message says why."""


def _writable_folder(path: Path, what: str) -> None:
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
        raise StoreError(f"{what} {path}: cannot write in {probe} ({exc.strerror}); choose a folder you can write") from None
    os.close(fd)
    os.unlink(name)


def check_tracking_uri(uri: str) -> None:
    """Refuse an MLflow URI this sweep could not log to, before any run is created."""
    scheme = urllib.parse.urlsplit(uri).scheme.split("+")[0]
    if scheme not in TRACKING_SCHEMES:
        raise StoreError(f"--tracking-uri {uri}: unsupported scheme {scheme or '(none)'!r}; use one of "
                         + ", ".join(f"{s}://" for s in TRACKING_SCHEMES))
    if scheme == "sqlite":
        _writable_folder(Path(uri.removeprefix("sqlite:///")).parent, "--tracking-uri")
    elif scheme == "file":
        _writable_folder(Path(urllib.parse.urlsplit(uri).path), "--tracking-uri")
    elif scheme in ("http", "https"):
        try:
            with urllib.request.urlopen(f"{uri.rstrip('/')}/health", timeout=10):
                pass
        except (urllib.error.URLError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            raise StoreError(f"--tracking-uri {uri}: no MLflow server answers there ({reason}); start one "
                             "(`mlflow server --host 127.0.0.1 --port 5000`) or give another URI") from None


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def check_storage(sweep_dir: str) -> None:
    """Refuse a sweep folder that cannot be written, before Ray starts (nothing is left behind).

    A local path needs a writable folder above it. An object-store URI needs its bucket to exist and
    to take (and delete) a small probe object at the bucket's top, where removing it leaves no folder
    marker behind in the sweep's own path.
    """
    if not is_uri(sweep_dir):
        _writable_folder(Path(sweep_dir), "--storage")
        return
    from pyarrow import fs

    try:
        filesystem, path = fs.FileSystem.from_uri(sweep_dir)
    except (ValueError, OSError) as exc:
        raise StoreError(f"--storage {sweep_dir}: {_one_line(exc)}") from None
    if isinstance(filesystem, fs.LocalFileSystem):
        _writable_folder(Path(path), "--storage")
        return
    bucket = path.split("/", 1)[0]
    try:
        info = filesystem.get_file_info(bucket)
        if info.type == fs.FileType.NotFound:
            raise StoreError(f"--storage {sweep_dir}: bucket {bucket!r} does not exist; create it first")
        probe = f"{bucket}/.cdm-write-probe-{uuid.uuid4().hex}"
        with filesystem.open_output_stream(probe) as stream:
            stream.write(b"probe")
        filesystem.delete_file(probe)
    except OSError as exc:
        raise StoreError(f"--storage {sweep_dir}: cannot write to bucket {bucket!r} with this environment's "
                         f"credentials ({_one_line(exc)})") from None


def parse_state(text: str, where: str) -> dict[str, Any]:
    """The ``sweep.json`` a sweep wrote when it started: spec, ``--set`` values, profile, MLflow store, parent run.

    Raises:
        StoreError: not JSON, or a key missing or of the wrong type.
    """
    try:
        state = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StoreError(f"--resume: {where} is damaged (not JSON: {exc}); remove the folder to start over") from None
    if not isinstance(state, dict):
        raise StoreError(f"--resume: {where} is damaged (a JSON {type(state).__name__}, not an object); "
                         "remove the folder to start over")
    for key, kind in _STATE_KEYS.items():
        if not isinstance(state.get(key), kind):
            raise StoreError(f"--resume: {where} is damaged ({key}: expected a JSON "
                             f"{'object' if kind is dict else 'string'}); remove the folder to start over")
    return state


def is_uri(storage: str) -> bool:
    """``s3://…``, ``gs://…``, ``file://…``: kept as written and read through pyarrow; else a local path."""
    return "://" in storage


def sweep_location(storage: str, spec: str, profile: str) -> str:
    """``<storage>/<spec>/<profile>``: an absolute path, or a URI joined as a string (no Path: it eats ``//``)."""
    if is_uri(storage):
        return f"{storage.rstrip('/')}/{spec}/{profile}"
    return str((Path(storage) / spec / profile).resolve())


def exists(location: str) -> bool:
    from pyarrow import fs

    filesystem, path = fs.FileSystem.from_uri(location)
    return filesystem.get_file_info(path).type != fs.FileType.NotFound


def read_text(location: str) -> str:
    from pyarrow import fs

    filesystem, path = fs.FileSystem.from_uri(location)
    with filesystem.open_input_stream(path) as stream:
        return stream.read().decode(errors="replace")  # a damaged file fails as JSON, with its name


def publish_files(local: Path, location: str) -> None:
    """Copy the staging folder ``local`` into the sweep folder ``location`` (a URI; local paths write in place)."""
    from pyarrow import fs

    filesystem, path = fs.FileSystem.from_uri(location)
    filesystem.create_dir(path, recursive=True)
    fs.copy_files(str(local), path, source_filesystem=fs.LocalFileSystem(), destination_filesystem=filesystem)
