"""Files a user, a data set or a neighbour names, opened and read within stated bounds.

A symbolic link to ``/dev/zero`` reads forever, a FIFO blocks the ``open`` itself, and a 3 MB gzip of
zeros decompresses to gigabytes. So every reader of :mod:`cdm.io` opens through :func:`open_regular`
(non-blocking open, then ``fstat`` of the descriptor itself: no race between the check and the read)
and reads whole files through :func:`read_bounded` or :func:`read_gzip`, each refusal a ``ValueError``
that names the file and the cap. The caps (also in docs/security.md):

- :data:`MAX_TEXT_BYTES`: a JSON or text file read whole (set lists, split files, metadata, manifests);
- :func:`annotation_cap`: a decompressed annotation file (``CDM_MAX_ANNOTATION_MIB``, default 256 MiB:
  ~320,000 Co3D frame entries of ~830 bytes).

A file in a pyarrow file system (an object store's ``s3://``, ``gs://``, ``file://`` URI: a sweep's folder) is
read through :func:`read_from` and :func:`sha256_from`, within the same caps: :func:`read_bounded` and
:func:`read_text` take such a URI in place of a path.
"""

from __future__ import annotations

import gzip
import hashlib
import os
import stat
import zlib
from pathlib import Path
from typing import IO

__all__ = ["ANNOTATION_ENV", "MAX_TEXT_BYTES", "annotation_cap", "file_sha256", "is_uri", "open_regular",
           "read_bounded", "read_from", "read_gzip", "read_text", "sha256_from"]

MAX_TEXT_BYTES = 64 * 2**20
"""Most bytes of a JSON or text file read whole (Co3D's largest set list is a few MB)."""
ANNOTATION_ENV = "CDM_MAX_ANNOTATION_MIB"
"""Environment variable raising (or lowering) the decompressed-annotation cap, in MiB."""
_DEFAULT_ANNOTATION_MIB = 256

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def open_regular(path: Path, label: str, show_path: bool = True) -> IO[bytes]:
    """``path`` opened for binary reading if it is a regular file (after links); ValueError otherwise.

    The open does not block (``O_NONBLOCK``: a FIFO with no writer would hang it), and the kind is
    read from the open descriptor, so no file can be swapped in between the check and the read.
    ``label`` starts the message (the field or option that named the file; with ``show_path=False``
    it names the path itself).
    """
    where = f"{label}: {path}" if show_path else label
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise ValueError(f"{where} does not exist") from None
    except OSError as exc:
        raise ValueError(f"{where} cannot be opened: {exc.strerror}") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
        raise ValueError(f"{where} is {kind}; expected a regular file")
    os.set_blocking(fd, True)
    return os.fdopen(fd, "rb")


def is_uri(location: str | Path) -> bool:
    """``s3://…``, ``gs://…``, ``file://…``: a file read through pyarrow's file systems; else a local path."""
    return isinstance(location, str) and "://" in location


def _too_big(label: str, path: object, size: int, cap: int, show_path: bool = True) -> ValueError:
    return ValueError(f"{label}: {path} is {size} bytes; at most {cap} are read" if show_path
                      else f"{label} is {size} bytes; at most {cap} are read")


def _input_stream(filesystem, path: str, label: str):
    """``path`` of the pyarrow ``filesystem`` opened for reading, and its size; ValueError unless a file."""
    from pyarrow import fs

    info = filesystem.get_file_info(path)
    if info.type != fs.FileType.File:
        raise ValueError(f"{label}: {path} does not exist" if info.type == fs.FileType.NotFound
                         else f"{label}: {path} is not a regular file")
    return filesystem.open_input_stream(path), info.size


def read_from(filesystem, path: str, label: str, cap: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of the file ``path`` of the pyarrow ``filesystem`` (an object store's, or the local one),
    refused past ``cap`` bytes before reading them, or once more arrive than the listing said."""
    stream, size = _input_stream(filesystem, path, label)
    with stream:
        if size > cap:
            raise _too_big(label, path, size, cap)
        raw = stream.read(size + 1)
    if len(raw) > cap:
        raise _too_big(label, path, len(raw), cap)
    return raw


def sha256_from(filesystem, path: str, label: str) -> str:
    """Hex SHA-256 of the file ``path`` of the pyarrow ``filesystem``, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    stream, _ = _input_stream(filesystem, path, label)
    with stream:
        while chunk := stream.read(2**20):
            digest.update(chunk)
    return digest.hexdigest()


def read_bounded(path: Path | str, label: str, cap: int = MAX_TEXT_BYTES, show_path: bool = True) -> bytes:
    """The bytes of the regular file ``path`` (or the URI :func:`is_uri`, through :func:`read_from`), refused
    past ``cap`` bytes before reading them (messages as :func:`open_regular`'s)."""
    if is_uri(path):
        from pyarrow import fs

        return read_from(*fs.FileSystem.from_uri(path), label, cap)
    with open_regular(Path(path), label, show_path) as f:
        size = os.fstat(f.fileno()).st_size
        if size > cap:
            raise _too_big(label, path, size, cap, show_path)
        return f.read(size + 1)[:cap]  # not read(cap): a reader allocates the size it is asked for


def read_text(path: Path | str, label: str, cap: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of the regular file or URI ``path``, within ``cap`` bytes (:func:`read_bounded`); ValueError
    naming ``label`` and the file for one that is not UTF-8."""
    raw = read_bounded(path, label, cap)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{label}: {path} is not UTF-8 text (byte {exc.start})") from None


def file_sha256(path: Path, label: str) -> str:
    """Hex SHA-256 of the regular file ``path``'s bytes, read in 1 MiB chunks (messages as :func:`open_regular`'s)."""
    digest = hashlib.sha256()
    with open_regular(path, label) as f:
        while chunk := f.read(2**20):
            digest.update(chunk)
    return digest.hexdigest()


def annotation_cap() -> int:
    """The decompressed-annotation cap in bytes: ``$CDM_MAX_ANNOTATION_MIB`` MiB, or 256 MiB."""
    text = os.environ.get(ANNOTATION_ENV, str(_DEFAULT_ANNOTATION_MIB))
    if not (text.isascii() and text.isdigit() and 0 < len(text) <= 7 and int(text) > 0):
        raise ValueError(f"{ANNOTATION_ENV}: {text[:40]!r}; give a whole number of MiB, 1 to 9999999")
    return int(text) * 2**20


def read_gzip(path: Path, label: str, cap: int | None = None) -> bytearray:
    """``path`` gunzipped, refused (naming the file and the cap) as soon as it passes ``cap`` bytes
    (default :func:`annotation_cap`): memory stays near the cap whatever the compression ratio."""
    cap = annotation_cap() if cap is None else cap
    out = bytearray()
    try:
        with open_regular(path, label) as f, gzip.GzipFile(fileobj=f) as gz:
            while chunk := gz.read(2**20):
                out += chunk
                if len(out) > cap:
                    raise ValueError(f"{label}: {path} decompresses to more than {cap // 2**20} MiB; set "
                                     f"{ANNOTATION_ENV} higher if the file is genuine")
    except (OSError, EOFError, zlib.error) as exc:  # gzip.BadGzipFile is an OSError
        raise ValueError(f"{label}: cannot read {path}: {exc}") from None
    return out  # not bytes(out): a copy would double the peak for a file near the cap


