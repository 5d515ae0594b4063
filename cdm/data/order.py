"""Which objects each training step sees, as a pure function of the step (resumable, worker-independent)."""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch.utils.data import Dataset

__all__ = ["ByRound", "StepBatches", "batch_indices"]


def batch_indices(step: int, batch_size: int, size: int, seed: int) -> list[tuple[int, int]]:
    """``(epoch, index)`` pairs of the batch at ``step``.

    A pure function of the step, so a resumed run sees the same data; the epoch doubles as the
    view round, so each object is seen from a fresh camera every epoch.
    """
    out = []
    for k in range(step * batch_size, (step + 1) * batch_size):
        epoch, pos = divmod(k, size)
        perm = torch.randperm(size, generator=torch.Generator().manual_seed(seed * 1_000_003 + epoch))
        out.append((epoch, int(perm[pos])))
    return out


class StepBatches:
    """Batch sampler of a data loader: the ``(view round, index)`` pairs of steps ``start``…``stop − 1``
    (:func:`batch_indices`; rank ``rank`` of ``world`` data-parallel ranks)."""

    def __init__(self, start: int, stop: int, world: int, rank: int, batch_size: int, size: int, seed: int):
        self.start, self.stop, self.world, self.rank = start, stop, world, rank
        self.batch_size, self.size, self.seed = batch_size, size, seed

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        for step in range(self.start, self.stop):
            yield batch_indices(step * self.world + self.rank, self.batch_size, self.size, self.seed)

    def __len__(self) -> int:
        return max(0, self.stop - self.start)


class ByRound(Dataset):
    """A data set indexed by ``(view round, object index)``, as :class:`StepBatches` yields them."""

    def __init__(self, dataset):
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, key: tuple[int, int]):
        epoch, index = key
        return self.dataset.sample(index, epoch)
