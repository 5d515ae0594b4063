"""A least-recently-used cache bounded by the bytes its values hold (decoded views, object surfaces)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, Protocol, TypeVar

__all__ = ["ByteLRU", "Sized"]


class Sized(Protocol):
    def nbytes(self) -> int:
        """Memory the value holds, in bytes."""


V = TypeVar("V", bound=Sized)


class ByteLRU(Generic[V]):
    """Values by key, least recently used out once they hold more than ``max_bytes`` (``value.nbytes()``).

    The most recent value always stays, even alone over the budget, so a caller asking for it again
    does not rebuild it. ``hits`` and ``misses`` count :meth:`get` calls since the last :meth:`clear`.
    """

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self.hits = 0
        self.misses = 0
        self._items: OrderedDict[Hashable, V] = OrderedDict()
        self._bytes = 0

    def get(self, key: Hashable, make: Callable[[], V]) -> V:
        """The cached value of ``key``, or ``make()`` stored under it."""
        if key in self._items:
            self._items.move_to_end(key)
            self.hits += 1
            return self._items[key]
        self.misses += 1
        value = make()
        self._items[key] = value
        self._bytes += value.nbytes()
        while self._bytes > self.max_bytes and len(self._items) > 1:
            _, dropped = self._items.popitem(last=False)
            self._bytes -= dropped.nbytes()
        return value

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._items

    def clear(self) -> None:
        self._items.clear()
        self._bytes = 0
        self.hits = self.misses = 0
