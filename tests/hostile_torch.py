"""Hostile torch files for tests: a TorchScript archive whose ``__setstate__`` writes a file, pickles that
poison torch's own functions or name storages wrongly, archives small on disk that inflate when read, and
pre-zip (torch < 1.6) files laid out by hand.

Each is built here, by torch itself where it can be (``torch.jit.script``/``save``), or by writing the
pickle opcodes and the zip by hand where torch would refuse to write it.
"""

from __future__ import annotations

import io
import pickle
import struct
import zipfile
from pathlib import Path
from typing import Any

import torch

PC2_FIRST_WEIGHT = "point_cloud_model.model.sa_layers.0.0.point_features.layers.0.weight"
"""A string naming PC²'s first PVCNN2 weight, so ``train --init-from`` treats the file as PC²'s."""


def torchscript_archive(path: Path, marker: Path, tag: str = PC2_FIRST_WEIGHT) -> None:
    """A TorchScript archive whose scripted ``__setstate__`` creates ``marker`` (``torch.from_file(...,
    shared=True)``, which creates and writes any file) when ``torch.load`` or ``torch.jit.load`` reads it;
    its pickle also holds ``tag``."""

    class Writer(torch.nn.Module):
        def __init__(self, target: str, name: str) -> None:
            super().__init__()
            self.target, self.name = target, name
            self.written = torch.zeros(8, dtype=torch.uint8)

        @torch.jit.export
        def __getstate__(self) -> tuple[str, str, bool]:
            return self.target, self.name, self.training

        @torch.jit.export
        def __setstate__(self, state: tuple[str, str, bool]) -> None:
            self.target, self.name, self.training = state
            self.written = torch.from_file(self.target, shared=True, size=8, dtype=torch.uint8)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return x

    torch.jit.save(torch.jit.script(Writer(str(marker), tag)), str(path))


def archive(path: Path, pickle_bytes: bytes, records: dict[str, bytes] | None = None,
            extra: dict[str, bytes] | None = None, compress: int = zipfile.ZIP_STORED,
            byteorder: str = "little") -> None:
    """A zip laid out as ``torch.save`` lays one out, holding ``pickle_bytes`` as its ``data.pkl``."""
    with zipfile.ZipFile(path, "w", compress) as z:
        z.writestr("archive/data.pkl", pickle_bytes)
        z.writestr("archive/byteorder", byteorder)
        for key, data in (records or {}).items():
            z.writestr(f"archive/data/{key}", data)
        for name, data in (extra or {}).items():
            z.writestr(f"archive/{name}", data)
        z.writestr("archive/version", "3\n")


def saved(obj: Any) -> dict[str, bytes]:
    """The entries ``torch.save(obj)`` writes, by their names below the archive's folder."""
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    with zipfile.ZipFile(buffer) as z:
        return {name.split("/", 1)[1]: z.read(name) for name in z.namelist()}


def tensor_pickle(storage_id: bytes, tail: bytes = b"", key: str = "w") -> bytes:
    """A protocol-2 pickle of ``{key: <a float tensor of 3>}`` whose persistent id is the pickled
    ``storage_id`` (normally ``('storage', torch.FloatStorage, '0', 'cpu', 3)``), then ``tail`` before STOP."""
    name = key.encode()
    return (b"\x80\x02}X" + struct.pack("<I", len(name)) + name
            + b"ctorch._utils\n_rebuild_tensor_v2\n(" + storage_id + b"Q"
            + b"K\x00K\x03\x85K\x01\x85\x89ccollections\nOrderedDict\n)RtRs" + tail + b".")


GOOD_ID = b"(X\x07\x00\x00\x00storagectorch\nFloatStorage\nX\x01\x00\x00\x000X\x03\x00\x00\x00cpuK\x03t"
"""The persistent id ``torch.save`` writes for storage '0' of 3 floats."""


def poisoning_pickle(storage_id: bytes = GOOD_ID) -> bytes:
    """A pickle that BUILDs ``torch._utils._rebuild_tensor_v2`` with a state tuple: done by a plain
    unpickler, it sets the function's ``__defaults__`` for the whole process (every later tensor negated
    or worse), then loads one tensor."""
    poison = b"ctorch._utils\n_rebuild_tensor_v2\nN}X\x0c\x00\x00\x00__defaults__K\x00\x85s\x86b0"
    return b"\x80\x02" + poison + tensor_pickle(storage_id)[2:]


def nested_list_pickle(depth: int) -> bytes:
    """A pickle of a list nested ``depth`` deep (``[[[…]]]``): a few bytes per level."""
    return b"\x80\x02" + b"]" * depth + b"a" * (depth - 1) + b"."


def long_list_pickle(count: int) -> bytes:
    """A pickle of one list of ``count`` Nones, one byte each (deflates ~1000×)."""
    return b"\x80\x02](" + b"N" * count + b"e."


def reduce_call(name: str, *args: Any) -> bytes:
    """A pickle that calls ``name`` (dotted) with ``args``, as a ``__reduce__`` payload does."""
    module, attr = name.rsplit(".", 1)
    return b"\x80\x02c" + f"{module}\n{attr}\n".encode() + pickle.dumps(args, 2)[2:-1] + b"R."


LEGACY_ID = GOOD_ID[:-1] + b"Nt"
"""The persistent id torch < 1.6's ``torch.save`` writes for storage '0' of 3 floats (no view)."""
MAGIC = 0x1950A86A20F9469CFC6C
"""The magic number every legacy file starts with (torch/serialization.py ``MAGIC_NUMBER``)."""
LITTLE_ENDIAN = {"protocol_version": 1001, "little_endian": True, "type_sizes": {"short": 2, "int": 4, "long": 8}}


def legacy_file(path: Path, pickle_bytes: bytes, records: dict[str, bytes] | None = None, *,
                keys: list[str] | None = None, counts: dict[str, int] | None = None,
                header: tuple[Any, Any, Any] = (MAGIC, 1001, LITTLE_ENDIAN), tail: bytes = b"") -> None:
    """A pre-zip file laid out as torch < 1.6's ``torch.save`` lays one out: the magic number, protocol and
    sys-info pickles of ``header`` (each pickled, or a pickle's bytes as they are), ``pickle_bytes``, the key
    list (``keys``, else ``records``' keys), then per
    key its element count (``counts``, else its bytes over 4: float storages) and its bytes, then ``tail``."""
    records = records or {}
    keys = sorted(records) if keys is None else keys
    parts = [value if type(value) is bytes else pickle.dumps(value, 2) for value in header]
    parts += [pickle_bytes, pickle.dumps(keys, 2)]
    for key in keys:
        data = records.get(key, b"")
        parts += [struct.pack("<q", (counts or {}).get(key, len(data) // 4)), data]
    path.write_bytes(b"".join(parts) + tail)
