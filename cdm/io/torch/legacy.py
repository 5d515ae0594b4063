"""The pre-zip ("legacy") file ``torch.save`` wrote before torch 1.6, read inertly: PVD pins torch 1.4
(alexzhou907/PVD), so BDM's released priors are in it.

The layout, as torch/serialization.py's ``_legacy_save`` writes it: five pickles back to back, then the raw
storages. The pickles are the magic number, the protocol version, a sys-info dict, the main pickle (its
persistent ids name storages as ``('storage', type, key, location, numel, None)``) and the sorted list of
storage keys; then, per key, an 8-byte element count and the storage's bytes. Every pickle runs through the
inert unpickler of :mod:`cdm.io.torch.unpickler` with its step and nesting caps (the header and the key list
may hold plain data only), and all five together are read from at most :data:`MAX_PICKLE_BYTES` of the
file. Storage sizes the main pickle declares are checked against :data:`MAX_STORAGE_BYTES` and against the
bytes the file has left before anything is allocated. Refused: torch < 0.4's tar archive, a file written
on a big-endian machine (torch itself reads one only on such a machine), storage views (which torch has not
written since 0.4), a key list that differs from the storages the pickle names, and bytes after the last
storage.
"""

from __future__ import annotations

import io
import os
from typing import IO, Any

import torch

from cdm.io.torch.archive import MAX_PICKLE_BYTES, MAX_STORAGE_BYTES, ArchiveError
from cdm.io.torch.unpickler import PICKLE_DAMAGE, Refused, unpickle

__all__ = ["MAGIC_NUMBER", "PROTOCOL_VERSION", "load_legacy"]

MAGIC_NUMBER = 0x1950A86A20F9469CFC6C
"""The first pickle of every legacy file (torch/serialization.py ``MAGIC_NUMBER``)."""
PROTOCOL_VERSION = 1001
"""The second (torch/serialization.py ``PROTOCOL_VERSION``, unchanged since torch 0.4)."""

_ITEM_SIZES = frozenset(dtype.itemsize for dtype in torch.storage._dtype_to_storage_type_map())


class _Storages:
    """The storages a legacy main pickle names: each allocated, within the file's bytes, as it is named and
    filled after the key list (the unpickler's tensors view them, so they see the bytes once read)."""

    byteorder = "little"
    STORAGE_ID = ("type", "key", "location", "size", "view")

    def __init__(self, left: int | None) -> None:
        self.left = left  # None: a header pickle, which names no storage
        self.named: dict[str, torch.Tensor] = {}

    def storage(self, key: str, nbytes: int) -> torch.Tensor:
        if self.left is None:
            raise ArchiveError("its header names a storage")
        if key not in self.named:
            total = nbytes + sum(t.numel() for t in self.named.values())
            if total > MAX_STORAGE_BYTES:
                raise ArchiveError(f"its pickle declares {total:,} bytes of tensors, more than the "
                                   f"{MAX_STORAGE_BYTES:,} allowed")
            if total > self.left:
                raise ArchiveError(f"its pickle declares {total:,} bytes of tensors; the file has {self.left:,} "
                                   "left")
            self.named[key] = torch.empty(nbytes, dtype=torch.uint8)
        out = self.named[key]
        if out.numel() != nbytes:
            raise ArchiveError(f"its pickle names storage {key!r} as {out.numel():,} and as {nbytes:,} bytes")
        return out


def load_legacy(f: IO[bytes], records: bool) -> Any:
    """The legacy file open as ``f`` (at its start), read inertly (``records`` as :func:`unpickle`'s).

    Raises:
        ArchiveError: not a legacy file, a broken cap, or storages that do not match the pickle.
        cdm.io.torch.unpickler.Refused: a pickle calls or builds what a file of tensors and data does not.
    """
    size = os.fstat(f.fileno()).st_size
    head = io.BytesIO(f.read(min(size, MAX_PICKLE_BYTES)))
    try:
        _header(head)
        storages = _Storages(size - head.tell())
        result = unpickle(head, storages, records)
        keys = unpickle(head, _Storages(None), records=False)
    except Refused:
        raise
    except PICKLE_DAMAGE:
        if head.tell() >= MAX_PICKLE_BYTES and size > MAX_PICKLE_BYTES:
            raise ArchiveError(f"its pickles take more than the {MAX_PICKLE_BYTES:,} bytes allowed") from None
        raise
    _check_keys(keys, storages.named)
    f.seek(head.tell())
    for key in keys:
        _fill(f, key, storages.named[key])
    if f.read(1):
        raise ArchiveError("it holds bytes after its last storage")
    return result


def _header(head: io.BytesIO) -> None:
    try:
        magic = unpickle(head, _Storages(None), records=False)
    except Refused:
        raise
    except PICKLE_DAMAGE:
        magic = None  # ArchiveError and pickle's errors alike: not a pickle, so not this format
    if type(magic) is not int or magic != MAGIC_NUMBER:
        raise ArchiveError("not in torch's file format")
    protocol = unpickle(head, _Storages(None), records=False)
    if type(protocol) is not int or protocol != PROTOCOL_VERSION:
        raise ArchiveError(f"a legacy torch file of protocol {protocol!r}; torch writes {PROTOCOL_VERSION}")
    info = unpickle(head, _Storages(None), records=False)
    if type(info) is not dict or info.get("little_endian") is not True:
        raise ArchiveError("a legacy torch file written on a big-endian machine (or with no byte order); "
                           "torch reads one only on such a machine")


def _check_keys(keys: Any, named: dict[str, torch.Tensor]) -> None:
    if type(keys) is not list or not all(type(key) is str for key in keys):
        raise ArchiveError("its storage key list is not a list of strings")
    if len(set(keys)) != len(keys) or set(keys) != set(named):
        missing = sorted(set(named) - set(keys))[:3]
        raise ArchiveError(f"its storage key list does not match the storages its pickle names (missing "
                           f"{missing}, {len(keys) - len(set(keys))} repeated, {len(set(keys) - set(named))} extra)")


def _fill(f: IO[bytes], key: str, out: torch.Tensor) -> None:
    """Storage ``key``'s record: its element count, then ``out.numel()`` bytes read into ``out``."""
    head = f.read(8)
    count = int.from_bytes(head, "little", signed=True) if len(head) == 8 else -1
    nbytes = out.numel()
    if count < 0 or (count == 0) != (nbytes == 0) or (count and (nbytes % count or nbytes // count
                                                                   not in _ITEM_SIZES)):
        raise ArchiveError(f"its storage {key!r} gives {count:,} elements; the pickle says {nbytes:,} bytes")
    if f.readinto(memoryview(out.numpy())) != nbytes:
        raise ArchiveError(f"its storage {key!r} ends past the end of the file")
