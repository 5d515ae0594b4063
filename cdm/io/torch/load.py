"""Torch files a user or a neighbour could have written, read as tensors and plain data only.

This module owns reading pickles, and no module calls ``torch.load``, ``torch.jit.load`` or ``pickle.load``
(tests/test_read_audit.py walks the code). It reads foreign releases only (PC²'s, PVD's and MSN's weights,
a depth model's ``*.bin``) and cdm 0.1.0's ``checkpoint.pt`` for ``convert``: the project's own files are
safetensors and JSON (:mod:`cdm.io.safetensors`). Its readers open the archive themselves
(:class:`cdm.io.torch.archive.Archive`: no TorchScript, bounded members; or a pre-zip file,
:mod:`cdm.io.torch.legacy`) and run one inert unpickler on its pickles; torch's loader never sees such a
file, so ``torch.jit.load`` cannot be reached:

- :func:`load_tensors`: what ``torch.load(weights_only=True)`` reads: tensors, ``OrderedDict``, plain data.
- :func:`load_inert`: also a pickled config, as PC²'s ``checkpoint-latest.pth`` pickles its OmegaConf ``cfg``
  (``experiments/main.py``): every object other than a tensor becomes a :class:`Pickled` record of its
  class name, arguments and state. No class is imported and nothing the pickle names is called but
  torch's tensor rebuilding (done here, its arguments checked), so a ``__reduce__`` payload cannot run; a
  pickle that calls anything outside :data:`CONFIG_CALLS` is refused, so a payload is reported.

BUILD, SETITEM(S), APPEND(S) and ADDITEMS only fill records and the plain containers the pickle itself
built: a BUILD onto an allow-listed function would set its ``__defaults__`` for the whole process.
Caps: :data:`MAX_PICKLE_OPS`, :data:`MAX_NESTING` and the archive's (docs/security.md).
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path
from typing import Any

from cdm.io.files import open_regular
from cdm.io.torch.archive import MAX_PICKLE_BYTES, Archive, ArchiveError
from cdm.io.torch.legacy import load_legacy
from cdm.io.torch.unpickler import CONFIG_CALLS, MAX_NESTING, MAX_PICKLE_OPS, PICKLE_DAMAGE, Pickled, Refused, unpickle

__all__ = ["CONFIG_CALLS", "MAX_NESTING", "MAX_PICKLE_OPS", "Pickled", "load_inert", "load_tensors",
           "pickle_bytes"]


def load_tensors(file: Path, label: str, kind: str, advice: str) -> Any:
    """``file``'s contents on the CPU, tensors and plain data only.

    Args:
        file: the torch file.
        label: how the refusal starts: the field and the path, e.g. ``"--checkpoint: /runs/pc2/checkpoint-latest.pth"``.
        kind: what an unreadable file is not, e.g. ``"CDM checkpoint"``.
        advice: the sentence after a refusal of pickled objects: what to pass instead.

    Raises:
        ValueError: the file pickles other objects, is not a ``torch.save`` archive of tensors (a TorchScript
            archive included), breaks a cap, or is not a regular file; the message starts with ``label``.
    """
    try:
        return _read(file, label, kind, records=False)
    except Refused as exc:
        raise ValueError(f"{label} holds Python objects other than tensors and plain data; refused, since loading "
                         f"them ({exc}) could run code from the file. {advice}") from None


def load_inert(file: Path, label: str, kind: str) -> Any:
    """``file``'s contents on the CPU: tensors as tensors, other objects as :class:`Pickled` records.

    Raises:
        ValueError: the file's pickle calls something outside :data:`CONFIG_CALLS` (nothing of it was
            run), or it is not a ``torch.save`` archive, breaks a cap, or is not a regular file; the
            message starts with ``label``.
    """
    try:
        return _read(file, label, kind, records=True)
    except Refused as exc:
        raise ValueError(
            f"{label} could run code from the file while loading ({exc}); refused, and nothing of it was run. "
            f"Only tensors, plain data and a config ({', '.join(CONFIG_CALLS)}) are read"
        ) from None


def pickle_bytes(file: Path, label: str) -> bytes:
    """The bytes of ``file``'s pickles, within the archive's caps and nothing unpickled: what a reader
    recognises a file by (the names its pickle holds) before choosing how to load it. That is a zip
    archive's ``data.pkl``, or a pre-zip file's first :data:`MAX_PICKLE_BYTES` (its pickles come first,
    its storages after them).

    Raises:
        ValueError: ``file`` is not a regular file or not a ``torch.save`` archive; the message starts with ``label``.
    """
    with open_regular(file, label, show_path=False) as f:
        if not zipfile.is_zipfile(f):
            f.seek(0)
            head = f.read(MAX_PICKLE_BYTES)
            if not head.startswith(b"\x80"):  # a pickle's PROTO opcode, as a pre-zip file's magic number opens
                raise ValueError(f"{label} is not in torch's file format (neither a zip archive nor a pre-zip file)")
            return head
        try:
            return Archive(f).pickle()
        except ArchiveError as exc:
            raise ValueError(f"{label} is not a torch archive: {exc}") from None


def _read(file: Path, label: str, kind: str, records: bool) -> Any:
    with open_regular(file, label, show_path=False) as f:
        try:
            if not zipfile.is_zipfile(f):
                f.seek(0)
                return load_legacy(f, records)
            archive = Archive(f)
            return unpickle(io.BytesIO(archive.pickle()), archive, records)
        except ArchiveError as exc:
            raise ValueError(f"{label} is not a readable {kind}: {exc}") from None
        except Refused:
            raise
        except PICKLE_DAMAGE as exc:
            # A malformed pickle (a bad opcode, a stack underflow, an unhashable key) is damage, not a payload.
            raise ValueError(f"{label} is not a readable {kind} ({type(exc).__name__}: {exc})") from None

