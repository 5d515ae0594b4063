"""Every file a command writes where a user points it: atomically, and never through a link.

A folder a user names (``--out``) may hold what someone else put there: a dangling ``estimator.json``
link makes ``open(path, "w")`` create the link's target, anywhere this user can write; a predictable
temporary name (``.x.tmp-<pid>``) can be planted as a link too. So :func:`write_atomic` writes a
temporary file created with ``O_CREAT | O_EXCL | O_NOFOLLOW`` under a random name of its own,
flushes it to disk and renames it over the destination, refusing a destination that is a link or not
a regular file. A reader sees the whole file or the old one; a killed run leaves only a temporary
file whose name matches :data:`TEMP_NAME`. Each refusal is a ``ValueError`` naming the option and
the path.
"""

from __future__ import annotations

import os
import re
import secrets
import stat
from collections.abc import Callable
from pathlib import Path
from typing import IO

__all__ = ["TEMP_NAME", "check_within", "make_folder", "write_atomic"]

TEMP_NAME = re.compile(r"\..+\.tmp-[0-9a-f]{16}")
"""Name of a temporary file :func:`write_atomic` makes: ``.<destination name>.tmp-<16 random hex digits>``."""


def check_within(path: Path, within: Path, label: str) -> None:
    """Refuse ``path`` unless it lies below ``within`` once the links of its existing part are resolved: a
    folder link planted below ``--out`` leads nowhere else. Made folders included, so check before making."""
    if not path.resolve().is_relative_to(within.resolve()):
        raise ValueError(f"{label}: {path} would be written to {path.resolve()}, outside {within} "
                         "(a link below it leads out); remove the link")


def make_folder(path: Path, label: str, within: Path | None = None) -> Path:
    """``path`` as a folder (made with its parents if absent); ValueError starting with ``label`` if it is
    a file or cannot be made (a read-only file system, no permission), or with ``within``, if it does not
    lie below ``within`` (:func:`check_within`, before anything is made)."""
    if within is not None:
        check_within(path, within, label)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ValueError(f"{label}: {path} is a file, not a folder") from None
    except OSError as exc:
        raise ValueError(f"{label}: cannot make the folder {path}: {exc.strerror}") from None
    return path


def _refuse_existing(path: Path, label: str) -> None:
    try:
        info = path.lstat()
    except FileNotFoundError:
        return
    if stat.S_ISLNK(info.st_mode):
        raise ValueError(f"{label}: {path} is a symbolic link where this command writes a file; remove it "
                         "(a write never follows one)")
    if not stat.S_ISREG(info.st_mode):
        raise ValueError(f"{label}: {path} exists and is not a regular file; remove it or choose another folder")
    if info.st_nlink != 1:  # a second name of someone's file: it may be the one meant to be written
        raise ValueError(f"{label}: {path} is a file with {info.st_nlink} links (a second name of another file) "
                         "where this command writes; remove it")


def write_atomic(path: Path, data: bytes | str | Callable[[IO[bytes]], None], label: str, *,
                 scratch: Path | None = None, within: Path | None = None, mode: int = 0o644) -> None:
    """Write ``data`` (bytes, text as UTF-8, or a function writing into a binary file) to ``path``.

    The temporary file lives in ``scratch`` (a folder of the caller's on the same file system, whose
    leftovers it may remove: :data:`TEMP_NAME`), else beside ``path``; it is renamed over ``path`` only
    when complete and on disk. With ``within``, ``path``'s folder must lie below it once links are
    resolved: a folder link planted below ``--out`` leads nowhere else.

    Raises:
        ValueError: ``path`` is a link, not a regular file or outside ``within``, or the folder cannot be
            written (named after ``label``); nothing is left behind.
    """
    if within is not None:
        check_within(path.parent, within, label)
    _refuse_existing(path, label)
    temp = (scratch or path.parent) / f".{path.name}.tmp-{secrets.token_hex(8)}"
    try:
        fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    except OSError as exc:
        raise ValueError(f"{label}: cannot write {path}: {exc.strerror}") from None
    try:
        with os.fdopen(fd, "wb") as out:
            if callable(data):
                data(out)
            else:
                out.write(data.encode() if isinstance(data, str) else data)
            out.flush()
            os.fsync(out.fileno())
        _refuse_existing(path, label)  # planted while we wrote: the rename would replace the link, not follow it
        os.replace(temp, path)
    except OSError as exc:
        raise ValueError(f"{label}: cannot write {path}: {exc.strerror}") from None
    finally:
        temp.unlink(missing_ok=True)
