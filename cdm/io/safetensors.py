"""safetensors files: the project's own weights, caches and shards, written and read back within stated bounds.

The format (https://huggingface.co/docs/safetensors): a little-endian uint64 ``N``, ``N`` bytes of JSON
naming each tensor's dtype, shape and ``data_offsets`` (begin, end) in the byte buffer that follows, and
an optional ``__metadata__`` of string to string. It holds no code, so nothing read here can run any;
``safetensors.torch.load_file`` reads what :func:`write_safetensors` writes.

Reading goes through :func:`cdm.io.files.open_regular` like every other reader of :mod:`cdm.io`, and the
header is checked before any tensor is made: its size (:data:`MAX_HEADER_BYTES`, the cap the
``safetensors`` package itself applies), its nesting (:func:`cdm.io.json.parse_json`), each entry's
dtype, shape and byte count, and the buffer's layout (tensors back to back from 0 to the file's end, as
the package requires). Each refusal is a ``ValueError`` starting with the caller's label and naming the file.

:func:`encode_tree` and :func:`decode_tree` carry what is not a flat dict of tensors (an optimiser's
state, an evaluation set): tensors go into the file by name, the rest into JSON, tuples, non-string keys
and non-finite floats kept exactly.
"""

from __future__ import annotations

import json
import math
import mmap
import os
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import torch
from torch import Tensor

from cdm.io.files import open_regular
from cdm.io.json import parse_json
from cdm.io.write import write_atomic

__all__ = ["DTYPES", "MAX_HEADER_BYTES", "decode_tree", "encode_tree", "read_safetensors", "write_safetensors"]

MAX_HEADER_BYTES = 100_000_000
"""Most bytes of a safetensors header (the ``safetensors`` package's own cap)."""
DTYPES = {"F64": torch.float64, "F32": torch.float32, "F16": torch.float16, "BF16": torch.bfloat16,
          "I64": torch.int64, "I32": torch.int32, "I16": torch.int16, "I8": torch.int8, "U8": torch.uint8,
          "BOOL": torch.bool}
"""safetensors dtype names read and written here, with the torch dtype each stands for."""
_NAMES = {dtype: name for name, dtype in DTYPES.items()}
_ALIGN = 8
"""The header is padded with spaces to a multiple of this, so each tensor starts aligned (as the package pads)."""


def _entries(tensors: dict[str, Tensor], label: str) -> tuple[dict[str, Any], list[Tensor]]:
    """The header, its entries in ``tensors``' order (a state dict's order survives), and the tensors in
    buffer order: widest dtype first, then by name (the package's order), so every tensor starts at a
    multiple of its element size."""
    for name in tensors:
        if not isinstance(name, str):
            raise ValueError(f"{label}: a tensor's name is {name!r} ({type(name).__name__}); safetensors names are "
                             "strings")
    order = sorted(tensors.items(), key=lambda item: (-item[1].element_size(), item[0]))
    offsets, offset = {}, 0
    for name, t in order:
        if t.dtype not in _NAMES:
            raise ValueError(f"{label}: {name}: dtype {t.dtype} has no safetensors name here; allowed: "
                             f"{sorted(DTYPES)}")
        size = t.numel() * t.element_size()
        offsets[name] = [offset, offset + size]
        offset += size
    header = {name: {"dtype": _NAMES[t.dtype], "shape": list(t.shape), "data_offsets": offsets[name]}
              for name, t in tensors.items()}
    return header, [t for _, t in order]


def write_safetensors(path: Path, tensors: dict[str, Tensor], metadata: dict[str, str], label: str,
                      **atomic: Any) -> None:
    """Write ``tensors`` (any device, layout or storage sharing; saved as contiguous CPU copies) and
    ``metadata`` to ``path`` atomically (:func:`cdm.io.write.write_atomic`, whose keyword arguments
    ``atomic`` passes on), one tensor at a time: no second copy of the whole file is held."""
    header, order = _entries(tensors, label)
    if metadata:
        header = {"__metadata__": metadata, **header}
    raw = json.dumps(header, separators=(",", ":")).encode()
    raw += b" " * (-(8 + len(raw)) % _ALIGN)

    def write(out: IO[bytes]) -> None:
        out.write(len(raw).to_bytes(8, "little") + raw)
        for t in order:
            if t.numel():
                out.write(t.detach().to("cpu").contiguous().reshape(-1).view(torch.uint8).numpy().data)

    write_atomic(path, write, label, **atomic)


def _check_entry(name: str, entry: Any, where: str) -> tuple[torch.dtype, list[int], int, int]:
    if not isinstance(entry, dict) or set(entry) != {"dtype", "shape", "data_offsets"}:
        raise ValueError(f"{where}: tensor {name[:80]!r} is not described by dtype, shape and data_offsets")
    dtype, shape, offsets = entry["dtype"], entry["shape"], entry["data_offsets"]
    if dtype not in DTYPES:
        raise ValueError(f"{where}: tensor {name[:80]!r} has dtype {str(dtype)[:20]!r}; allowed: {sorted(DTYPES)}")
    if not (isinstance(shape, list) and all(type(n) is int and n >= 0 for n in shape)):
        raise ValueError(f"{where}: tensor {name[:80]!r} has shape {str(shape)[:80]}; expected a list of sizes ≥ 0")
    if not (isinstance(offsets, list) and len(offsets) == 2 and all(type(n) is int for n in offsets)):
        raise ValueError(f"{where}: tensor {name[:80]!r} has data_offsets {str(offsets)[:80]}; expected [begin, end]")
    size = math.prod(shape) * DTYPES[dtype].itemsize
    if offsets[1] - offsets[0] != size:
        raise ValueError(f"{where}: tensor {name[:80]!r} spans {offsets[1] - offsets[0]} bytes; its dtype and "
                         f"shape need {size}")
    return DTYPES[dtype], shape, offsets[0], offsets[1]


def _header(f: IO[bytes], label: str, path: Path) -> tuple[dict[str, tuple[torch.dtype, list[int], int, int]],
                                                          dict[str, str], int]:
    """The checked entries of the open file ``f`` (``path``), its metadata and where its buffer starts."""
    where = f"{label}: {path}"
    size = os.fstat(f.fileno()).st_size
    head = f.read(8)
    if len(head) != 8:
        raise ValueError(f"{where} is not a safetensors file: {size} bytes, shorter than its header's length")
    length = int.from_bytes(head, "little")
    if length > MAX_HEADER_BYTES or 8 + length > size:
        raise ValueError(f"{where} is not a safetensors file (or is cut short): its header says {length} bytes, "
                         f"the file holds {size}; at most {MAX_HEADER_BYTES} are read")
    header = parse_json(f.read(length), label, path)
    if not isinstance(header, dict):
        raise ValueError(f"{where}: its header is not a JSON object")
    metadata = header.pop("__metadata__", {})
    if not (isinstance(metadata, dict) and all(isinstance(v, str) for v in metadata.values())):
        raise ValueError(f"{where}: its __metadata__ is not a map of strings")
    entries = {name: _check_entry(name, entry, where) for name, entry in header.items()}
    end = 0
    for name, (_, _, begin, stop) in sorted(entries.items(), key=lambda item: (item[1][2], item[1][3])):
        if begin != end:
            raise ValueError(f"{where}: tensor {name[:80]!r} starts at byte {begin} of the buffer, not {end}: the "
                             "tensors overlap or leave a gap")
        end = stop
    if 8 + length + end != size:
        raise ValueError(f"{where}: its tensors end at byte {8 + length + end}, the file at {size} (cut short or "
                         "with bytes appended)")
    return entries, metadata, 8 + length


def read_safetensors(path: Path, label: str, mapped: bool = False) -> tuple[dict[str, Tensor], dict[str, str]]:
    """``path``'s tensors (on the CPU) and metadata, the header checked first (module docstring).

    With ``mapped`` the tensors are views of a private (copy-on-write) map of the file: processes reading
    the same file share its pages until one writes; else each is read into memory of its own.

    Raises:
        ValueError: not a regular file, not a safetensors file, a header past the caps, or a layout the
            format forbids; the message starts with ``label: path``.
    """
    where = f"{label}: {path}"
    with open_regular(path, label) as f:
        entries, metadata, start = _header(f, label, path)
        buffer = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_COPY) if mapped and entries else None
        read: Callable[[int, int], Tensor] = (
            (lambda begin, stop: torch.frombuffer(buffer, dtype=torch.uint8, count=stop - begin, offset=start + begin))
            if buffer is not None else (lambda begin, stop: _read_into(f, start + begin, stop - begin, where)))
        tensors = {}
        for name, (dtype, shape, begin, stop) in entries.items():
            raw = read(begin, stop) if stop > begin else torch.empty(0, dtype=torch.uint8)
            tensors[name] = raw.view(dtype).reshape(shape)
    return tensors, metadata


def _read_into(f: IO[bytes], offset: int, size: int, where: str) -> Tensor:
    out = torch.empty(size, dtype=torch.uint8)
    f.seek(offset)
    if f.readinto(out.numpy().data) != size:  # the file shrank since its size was read
        raise ValueError(f"{where} was cut short while it was read")
    return out


_TENSOR, _TUPLE, _ITEMS, _FLOAT = "__tensor__", "__tuple__", "__items__", "__float__"


def encode_tree(tree: Any, prefix: str = "") -> tuple[Any, dict[str, Tensor]]:
    """``tree`` (dicts, lists, tuples, strings, numbers, bools, None and tensors) as JSON-ready data and
    the tensors it holds, each by a name spelling its path (``optimizer.state.0.exp_avg``) and replaced
    by ``{"__tensor__": name}``. Tuples become ``{"__tuple__": [...]}``, dicts with keys other than
    strings ``{"__items__": [[key, value], ...]}``, non-finite floats ``{"__float__": "nan"}``; so
    :func:`decode_tree` gives back an equal tree, types included."""
    tensors: dict[str, Tensor] = {}

    def encode(node: Any, path: str) -> Any:
        if isinstance(node, Tensor):
            if path in tensors:
                raise ValueError(f"{path}: two tensors of the tree would share this name")
            tensors[path] = node
            return {_TENSOR: path}
        if isinstance(node, float) and not math.isfinite(node):
            return {_FLOAT: repr(node)}
        if isinstance(node, tuple | list):
            items = [encode(v, _join(path, i)) for i, v in enumerate(node)]
            return {_TUPLE: items} if isinstance(node, tuple) else items
        if isinstance(node, dict):
            if all(isinstance(k, str) and not k.startswith("__") for k in node):
                return {k: encode(v, _join(path, k)) for k, v in node.items()}
            return {_ITEMS: [[encode(k, _join(path, f"key{i}")), encode(v, _join(path, k))]
                             for i, (k, v) in enumerate(node.items())]}
        if node is None or isinstance(node, bool | int | float | str):
            return node
        raise ValueError(f"{path}: a {type(node).__name__} is neither a tensor nor plain data")

    return encode(tree, prefix), tensors


def _join(path: str, key: object) -> str:
    return f"{path}.{key}" if path else str(key)


def decode_tree(data: Any, tensors: dict[str, Tensor], where: str) -> Any:
    """The tree :func:`encode_tree` gave ``data`` and ``tensors`` for; ValueError starting with ``where`` for a
    reference to a tensor that is absent or a marker of another shape."""
    if isinstance(data, list):
        return [decode_tree(v, tensors, where) for v in data]
    if not isinstance(data, dict):
        return data
    if len(data) == 1 and (key := next(iter(data))).startswith("__"):
        value = data[key]
        if key == _TENSOR and isinstance(value, str) and value in tensors:
            return tensors[value]
        if key == _TUPLE and isinstance(value, list):
            return tuple(decode_tree(v, tensors, where) for v in value)
        if key == _ITEMS and isinstance(value, list) and all(isinstance(p, list) and len(p) == 2 for p in value):
            return {_hashable(decode_tree(k, tensors, where), where): decode_tree(v, tensors, where) for k, v in value}
        if key == _FLOAT and value in ("nan", "inf", "-inf"):
            return float(value)
        raise ValueError(f"{where}: {json.dumps(data)[:120]} names no tensor of the file, or is not a value")
    return {k: decode_tree(v, tensors, where) for k, v in data.items()}


def _hashable(key: Any, where: str) -> Any:
    if isinstance(key, dict | list):
        raise ValueError(f"{where}: a map's key is a {type(key).__name__}")
    return key
