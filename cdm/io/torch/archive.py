"""The zip archive ``torch.save`` writes, read with :mod:`zipfile` and bounded, never by torch's loader.

torch's own ``torch.load`` hands a TorchScript archive (``constants.pkl``, ``code/``) to ``torch.jit.load``
before any pickle module sees a byte, and that runs the archive's scripted code. So the archive is opened
here: only the entries a ``torch.save`` of tensors and plain data writes are accepted (:data:`ENTRIES`,
plus ``data/<key>`` storage records), each member's inflated size is capped from the zip header and again
while reading, and storage records become CPU tensors of bytes without torch ever parsing the archive.
Legacy (pre-zip, torch < 1.6) files are read by :mod:`cdm.io.torch.legacy`.

Caps (also in docs/security.md): :data:`MAX_PICKLE_BYTES`, :data:`MAX_STORAGE_BYTES`,
:data:`MAX_INFLATE_RATIO`, :data:`MAX_ENTRIES`.
"""

from __future__ import annotations

import zipfile
import zlib
from typing import IO

import torch

__all__ = ["ENTRIES", "MAX_ENTRIES", "MAX_INFLATE_RATIO", "MAX_PICKLE_BYTES", "MAX_STORAGE_BYTES", "Archive",
           "ArchiveError"]

MAX_PICKLE_BYTES = 16 * 2**20
"""Most inflated bytes of ``data.pkl``. A state dict's pickle holds names and shapes, not weights: PC²'s
checkpoint (model, EMA, optimizer and cfg) pickles to well under 1 MiB."""
MAX_STORAGE_BYTES = 8 * 2**30
"""Most bytes of all storage records together (PC²'s 28 M-parameter checkpoint with optimizer state is
~0.5 GB)."""
MAX_INFLATE_RATIO = 20
"""Most inflated-to-compressed ratio of a compressed member above 1 MiB. ``torch.save`` stores records
uncompressed, and float weights deflate by far less than 2×; a gigabyte of zeros deflates 1000×."""
MAX_ENTRIES = 100_000
"""Most entries in an archive (one per storage: a state dict holds hundreds to a few thousand)."""
ENTRIES = frozenset({"data.pkl", "version", "byteorder", ".data/version", ".data/serialization_id",
                     ".format_version", ".storage_alignment"})
"""Entries below the archive's root folder that ``torch.save`` writes besides ``data/<key>``."""

_FLOOR = 2**20


class ArchiveError(ValueError):
    """The archive is not one ``torch.save`` of tensors and plain data writes; the text says why."""


class Archive:
    """An open ``torch.save`` zip archive: its ``data.pkl`` and its storage records, each read once."""

    byteorder: str
    STORAGE_ID = ("type", "key", "location", "size")
    """The fields of a storage's persistent id after ``'storage'``."""

    def __init__(self, f: IO[bytes]) -> None:
        if not zipfile.is_zipfile(f):
            raise ArchiveError("not in torch's file format")
        f.seek(0)
        try:
            self._zip = zipfile.ZipFile(f)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, EOFError) as exc:
            raise ArchiveError(f"a damaged zip archive ({exc})") from None
        infos = self._zip.infolist()
        if len(infos) > MAX_ENTRIES:
            raise ArchiveError(f"it holds {len(infos):,} entries, more than the {MAX_ENTRIES:,} allowed")
        self._root = _root(infos)
        self._infos = {info.filename[len(self._root):]: info for info in infos}
        if len(self._infos) != len(infos):  # readers differ on which copy counts
            raise ArchiveError("it holds an entry twice")
        _check_entries(self._infos)
        total = sum(info.file_size for name, info in self._infos.items() if name.startswith("data/"))
        if total > MAX_STORAGE_BYTES:
            raise ArchiveError(f"it holds {total:,} bytes of tensors, more than the {MAX_STORAGE_BYTES:,} allowed")
        self._storages: dict[str, torch.Tensor] = {}
        self.byteorder = self._byteorder()

    def pickle(self) -> bytes:
        """``data.pkl``, at most :data:`MAX_PICKLE_BYTES`."""
        if "data.pkl" not in self._infos:
            raise ArchiveError("it holds no data.pkl")
        return self._read_small("data.pkl", MAX_PICKLE_BYTES)

    def storage(self, key: str, nbytes: int) -> torch.Tensor:
        """Record ``data/<key>`` as a uint8 tensor of exactly ``nbytes`` (the same tensor for the same key)."""
        if key not in self._storages:
            info = self._infos.get(f"data/{key}")
            if info is None:
                raise ArchiveError(f"its pickle names storage {key!r}, which the archive does not hold")
            _check_size(info, info.file_size)
            out = torch.empty(info.file_size, dtype=torch.uint8)
            with self._member(info) as member:
                got = member.readinto(memoryview(out.numpy()))
                if got != info.file_size or member.read(1):
                    raise ArchiveError(f"its storage {key!r} does not hold the {info.file_size:,} bytes "
                                       "its header says")
            self._storages[key] = out
        out = self._storages[key]
        if out.numel() != nbytes:
            raise ArchiveError(f"its storage {key!r} holds {out.numel():,} bytes; the pickle says {nbytes:,}")
        return out

    def _byteorder(self) -> str:
        if "byteorder" not in self._infos:
            return "little"  # torch < 1.13 wrote none, and wrote little-endian on every machine it ran on
        order = self._read_small("byteorder", 16).decode("ascii", "replace")
        if order not in ("little", "big"):
            raise ArchiveError(f"it gives byte order {order!r}; only 'little' or 'big' exist")
        return order

    def _read_small(self, name: str, cap: int) -> bytes:
        info = self._infos[name]
        if info.file_size > cap:
            raise ArchiveError(f"it has a {name} of {info.file_size:,} bytes, more than the {cap:,} allowed")
        _check_size(info, cap)
        with self._member(info) as member:
            data = member.read(cap + 1)
        if len(data) > cap:
            raise ArchiveError(f"it has a {name} larger than the {cap:,} bytes allowed")
        return data

    def _member(self, info: zipfile.ZipInfo) -> IO[bytes]:
        try:
            return _Guarded(self._zip.open(info))
        except (zipfile.BadZipFile, NotImplementedError, RuntimeError, ValueError) as exc:
            raise ArchiveError(f"it has an unreadable entry {info.filename!r} ({exc})") from None


class _Guarded:
    """A member whose damage (bad CRC, corrupt deflate stream) surfaces as :class:`ArchiveError`."""

    def __init__(self, member: IO[bytes]) -> None:
        self._member = member

    def __enter__(self) -> _Guarded:
        return self

    def __exit__(self, *exc: object) -> None:
        self._member.close()

    def read(self, n: int) -> bytes:
        return self._call(self._member.read, n)

    def readinto(self, buffer: memoryview) -> int:
        return self._call(self._member.readinto, buffer)

    def _call(self, method, arg):
        try:
            return method(arg)
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as exc:
            raise ArchiveError(f"it has a damaged entry ({exc})") from None


def _root(infos: list[zipfile.ZipInfo]) -> str:
    roots = {info.filename.split("/", 1)[0] for info in infos}
    if len(roots) != 1 or any("/" not in info.filename for info in infos):
        raise ArchiveError("a zip archive but not torch's: its entries are not all under one folder")
    return f"{roots.pop()}/"


def _check_entries(infos: dict[str, zipfile.ZipInfo]) -> None:
    if "constants.pkl" in infos or any(name.startswith("code/") for name in infos):
        raise ArchiveError("it is a TorchScript archive, which holds code; refused, and nothing of it was run. "
                           "Pass a state dict saved with torch.save")
    for name in infos:
        key = name[len("data/"):] if name.startswith("data/") else None
        if name not in ENTRIES and not (key and key.isascii() and key.replace("_", "").isalnum()):
            raise ArchiveError(f"it holds {name!r}, which no torch.save of tensors and plain data writes; refused")


def _check_size(info: zipfile.ZipInfo, cap: int) -> None:
    bound = max(_FLOOR, MAX_INFLATE_RATIO * info.compress_size)
    if info.compress_type != zipfile.ZIP_STORED and info.file_size > bound:
        raise ArchiveError(f"it has an entry {info.filename!r} that inflates {info.compress_size:,} bytes to "
                           f"{info.file_size:,}, more than {MAX_INFLATE_RATIO}× (a decompression bomb)")
    if info.file_size > cap:
        raise ArchiveError(f"it has an entry {info.filename!r} of {info.file_size:,} bytes, more than {cap:,}")
