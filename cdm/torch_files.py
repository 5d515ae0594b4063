"""Torch files a user or a neighbour could have written, read as tensors and plain data only.

``torch.load(weights_only=True)`` runs no code from the file; a file that pickles other objects is refused
in our words, since torch's own message advises ``weights_only=False``, i.e. running the file's code.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path
from typing import Any

import torch

from cdm.safe_io import open_regular

__all__ = ["load_tensors"]


def load_tensors(file: Path, label: str, kind: str, advice: str) -> Any:
    """``file``'s contents on the CPU, tensors and plain data only.

    Args:
        file: the torch file.
        label: how the refusal starts: the field and the path, e.g. ``"checkpoint: /runs/a/checkpoint.pt"``.
        kind: what an unreadable file is not, e.g. ``"CDM checkpoint"``.
        advice: the sentence after a refusal of pickled objects: what to pass instead.

    Raises:
        ValueError: the file pickles other objects, torch cannot read it, or it is not a regular file (a
            FIFO, a device such as ``/dev/zero``, a folder: refused before a byte is read); the message
            starts with ``label``.
    """
    with open_regular(file, label, show_path=False) as f:
        return _load(f, label, kind, advice)


def _load(f, label: str, kind: str, advice: str) -> Any:
    try:
        return torch.load(f, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        # torch.save writes a zip archive; what is not one is not a torch file at all, pickled objects or not.
        f.seek(0)
        if not zipfile.is_zipfile(f):
            raise ValueError(f"{label} is not a readable {kind}: not in torch's file format") from None
        raise ValueError(f"{label} holds Python objects other than tensors and plain data; refused, since loading "
                         f"them could run code from the file. {advice}") from None
    except (RuntimeError, EOFError) as exc:
        raise ValueError(f"{label} is not a readable {kind} ({exc})") from None
