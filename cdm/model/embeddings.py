"""Per-object global embeddings read from a file (``model.global_source: embeddings``, supplementary Table 7).

The paper's global priors are OpenCLIP embeddings of the input image, of a text prompt, or of the
depth image. They are computed once, offline, by whatever model the user has
(``cdm/tools/openclip_embeddings.py`` shows OpenCLIP), and read here; nothing is downloaded.

File format: an ``.npz`` (``numpy.savez``; read with ``allow_pickle=False``) with one array per
object id (the ids of ``python -m cdm objects`` / the data set's ``object_id``), every array of the
same shape, float, finite:

- ``(E,)`` — one vector per object (an image or text embedding): one token;
- ``(T, E)`` — ``T`` tokens per object (e.g. a text encoder's per-token states).

``concat`` (⊕) appends the mean of the tokens to every point; ``cross_attention`` (⊗) attends to the
``T`` tokens.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from cdm.io.arrays import load_npz
from cdm.paths import input_path

__all__ = ["Embeddings", "embedding_ids", "load_embeddings"]

_FIELD = "model.global_embeddings"


class Embeddings(NamedTuple):
    """Per-object token sets.

    Attributes:
        tokens: ``{object_id: (T, E) float32}``.
        num_tokens: ``T``.
        dim: ``E``.
    """

    tokens: dict[str, Tensor]
    num_tokens: int
    dim: int

    def batch(self, object_ids: tuple[str, ...]) -> Tensor:
        """``(B, T, E)`` tokens of the batch's objects; an id missing from the file is a ``ValueError``."""
        missing = [o for o in object_ids if o not in self.tokens]
        if missing:
            raise ValueError(
                f"{_FIELD}: no embedding for object id {missing[0]!r}; the file must hold every object of both splits"
            )
        return torch.stack([self.tokens[o] for o in object_ids])


def _read(path: str | Path, names: bool):
    path = input_path(path)
    if not path.exists():
        raise ValueError(
            f"{_FIELD}: {path} does not exist; write one with cdm/tools/openclip_embeddings.py "
            "(docs/paper.md, 'External inputs')"
        )
    return load_npz(path, _FIELD, names=names)


def embedding_ids(path: str | Path) -> set[str]:
    """Object ids the file holds (reads the index only, not the arrays)."""
    return set(_read(path, names=True))


def load_embeddings(path: str | Path) -> Embeddings:
    """Read and validate an embeddings file (format in the module docstring).

    Raises:
        ValueError: missing or unreadable file, no arrays, mixed shapes, non-float or non-finite
            values, over :mod:`cdm.io.arrays`' caps; the message names ``model.global_embeddings``.
    """
    arrays = _read(path, names=False)
    if not arrays:
        raise ValueError(f"{_FIELD}: {path} holds no arrays; save one per object id with numpy.savez")
    shapes = {a.shape for a in arrays.values()}
    first = next(iter(arrays.values()))
    if len(shapes) != 1 or first.ndim not in (1, 2) or first.shape[-1] < 1:
        raise ValueError(f"{_FIELD}: every array must have the same shape (E,) or (T, E); found {sorted(shapes)[:3]}")
    bad = next(
        (k for k, a in arrays.items() if not np.issubdtype(a.dtype, np.floating) or not np.isfinite(a).all()), None
    )
    if bad is not None:
        raise ValueError(f"{_FIELD}: the embedding of {bad!r} is not finite floating point")
    tokens = {k: torch.from_numpy(np.atleast_2d(a).astype(np.float32)) for k, a in arrays.items()}
    t, e = next(iter(tokens.values())).shape
    return Embeddings(tokens, t, e)
