"""Arrays a user or a data set wrote (``.npy``, ``.npz``), read from their headers before allocation.

An ``.npy`` header may promise ``(100000, 100000)`` with no data behind it, and an ``.npz`` member may
hold pickled Python objects. So each header is read first and refused past its cap or for object
arrays, and a member is read no further than its header says. The caps (also in docs/security.md):
:data:`MAX_ARRAY_BYTES` one array or member, :data:`MAX_NPZ_BYTES` all members of an ``.npz`` together.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path
from typing import IO

import numpy as np

from cdm.io.files import open_regular

__all__ = ["MAX_ARRAY_BYTES", "MAX_NPZ_BYTES", "load_npy", "load_npz"]

MAX_ARRAY_BYTES = 512 * 2**20
"""Most bytes of one array read from ``.npy`` or one ``.npz`` member (an 8,192² float64 depth map)."""
MAX_NPZ_BYTES = 512 * 2**20
"""Most bytes of all arrays of one ``.npz`` together, from their headers."""

_NPY_MAGIC = b"\x93NUMPY"
"""How an ``.npy`` file starts: a single array where an ``.npz`` was expected."""


def _array_header(f: IO[bytes], label: str, path: Path, cap: int) -> tuple[tuple[int, ...], np.dtype, int]:
    """Shape, dtype and byte count from the ``.npy`` header at ``f``'s position, refused past ``cap``
    bytes (or for object arrays) before anything is allocated."""
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"format version {version}")
    except (ValueError, EOFError, OSError) as exc:
        raise ValueError(f"{label}: {path} is not a .npy array ({exc})") from None
    if dtype.hasobject:
        raise ValueError(f"{label}: {path} holds Python objects, refused (reading them would unpickle the file)")
    nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if nbytes > cap:
        raise ValueError(
            f"{label}: {path} declares a {dtype} array of shape {tuple(shape)} ({nbytes / 2**30:.1f} GiB); "
            f"an array read here may hold at most {cap // 2**20} MiB"
        )
    return tuple(shape), dtype, nbytes


def load_npy(path: Path, label: str, cap: int = MAX_ARRAY_BYTES) -> np.ndarray:
    """The ``.npy`` array at ``path``: a regular file whose header declares at most ``cap`` bytes, all
    of them present (checked against the file's size before allocating)."""
    with open_regular(path, label) as f:
        _, _, nbytes = _array_header(f, label, path, cap)
        if os.fstat(f.fileno()).st_size < f.tell() + nbytes:
            raise ValueError(f"{label}: {path} is shorter than its header says ({nbytes} bytes of data); truncated")
        f.seek(0)
        try:
            return np.load(f, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise ValueError(f"{label}: {path} is not a .npy array ({exc})") from None


def load_npz(path: Path, label: str, names: bool = False, cap: int = MAX_ARRAY_BYTES,
             total: int = MAX_NPZ_BYTES) -> dict[str, np.ndarray] | list[str]:
    """Every array of the ``.npz`` at ``path`` by name (``names``: only the names, nothing decompressed).

    Each member's header is read first and refused past ``cap`` bytes, all of them together past
    ``total``; a member is then read no further than its header says.
    """
    with open_regular(path, label) as f:
        if f.read(len(_NPY_MAGIC)) == _NPY_MAGIC:
            raise ValueError(f"{label}: {path} is a single array, not an .npz of named arrays (use numpy.savez)")
        f.seek(0)
        try:
            archive = zipfile.ZipFile(f)
        except (zipfile.BadZipFile, OSError, ValueError) as exc:
            raise ValueError(f"{label}: {path} is not an .npz file ({exc})") from None
        with archive:
            members = [i for i in archive.infolist() if i.filename.endswith(".npy")]
            keys = [i.filename.removesuffix(".npy") for i in members]
            if names:
                return keys
            try:
                return _npz_arrays(archive, members, keys, label, path, cap, total)
            except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as exc:
                raise ValueError(f"{label}: {path} is a damaged .npz file ({exc})") from None


def _npz_arrays(archive: zipfile.ZipFile, members: list[zipfile.ZipInfo], keys: list[str], label: str, path: Path,
                cap: int, total: int) -> dict[str, np.ndarray]:
    declared = 0
    for info in members:
        with archive.open(info) as member:
            declared += _array_header(member, label, Path(f"{path}:{info.filename}"), cap)[2]
        if declared > total:
            raise ValueError(f"{label}: {path} declares more than {total // 2**20} MiB of arrays; at most that is read")
    out = {}
    for key, info in zip(keys, members):
        with archive.open(info) as member:
            try:
                out[key] = np.lib.format.read_array(member, allow_pickle=False)
            except ValueError as exc:
                raise ValueError(f"{label}: {path}:{info.filename} is not a .npy array ({exc})") from None
    return out
