"""A small thread-safe least-recently-used mapping: the one in-memory cache of geofeat.

Every bounded in-process cache (descriptor instances, spectral bases, geodesic matrices,
surface operators, dataset meshes, the heads' per-mesh inputs) is an `LRUCache`. Persistent
stores on disk are elsewhere (`geofeat.descriptors.cache`).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from typing import Generic, TypeVar

__all__ = ["LRUCache"]

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")

#: A limit, or a function returning it (read at every insertion, so a module-level setting
#: can be changed while the program runs); ``None`` means no limit.
Limit = int | None | Callable[[], "int | None"]


def _value(limit: Limit) -> int | None:
    return limit() if callable(limit) else limit


class LRUCache(Generic[K, V]):
    """A mapping that forgets its least recently used entries beyond a size (and weight).

    Parameters
    ----------
    max_size : int, None or callable
        Most entries kept (``None``: unbounded). A callable is called at every insertion.
    max_weight : int, None or callable
        Most total weight kept (``None``: no weight limit), with ``weigh`` giving each
        entry's weight (e.g. ``lambda a: a.nbytes``). The newest entry is always kept, even
        when it alone weighs more.
    weigh : callable, optional
        ``weigh(value) -> int``; required with ``max_weight``.

    Notes
    -----
    Reads (`get`, ``cache[key]``, `get_or_compute`) make an entry the most recently used;
    `put` inserts or refreshes it and then evicts the oldest entries until the limits hold.
    All methods hold an internal lock; `get_or_compute` runs ``compute`` outside it (two
    threads missing the same key at once both compute, the later result is kept).
    """

    def __init__(self, max_size: Limit = None, *, max_weight: Limit = None, weigh: Callable[[V], int] | None = None):
        if max_weight is not None and weigh is None:
            raise TypeError("LRUCache: max_weight needs weigh, a function giving the weight of a value.")
        self.max_size = max_size
        self.max_weight = max_weight
        self.weigh = weigh
        self._data: OrderedDict[K, V] = OrderedDict()
        self._lock = threading.RLock()

    def _touch(self, key: K) -> bool:
        """Whether ``key`` is stored; if it is, make it the most recently used (call with the lock held)."""
        if key not in self._data:
            return False
        self._data.move_to_end(key)
        return True

    def get(self, key: K, default: V | None = None) -> V | None:
        """The value of ``key`` (now the most recently used), else ``default``."""
        with self._lock:
            return self._data[key] if self._touch(key) else default

    def put(self, key: K, value: V) -> V:
        """Store ``value`` under ``key`` as the most recently used entry, evict beyond the limits, return ``value``."""
        with self._lock:
            self._data[key] = value
            self._data.move_to_end(key)
            self._evict()
        return value

    def get_or_compute(self, key: K, compute: Callable[[], V]) -> V:
        """The value of ``key``; on a miss, ``compute()`` it (outside the lock) and `put` it."""
        with self._lock:
            if self._touch(key):
                return self._data[key]
        return self.put(key, compute())

    def pop(self, key: K, default: V | None = None) -> V | None:
        """Remove ``key`` and return its value, else ``default``."""
        with self._lock:
            return self._data.pop(key, default)

    def clear(self) -> None:
        """Forget every entry."""
        with self._lock:
            self._data.clear()

    def _evict(self) -> None:
        size, weight = _value(self.max_size), _value(self.max_weight)
        data, weigh = self._data, self.weigh
        while data and (
            (size is not None and len(data) > size)
            or (weight is not None and weigh is not None and len(data) > 1 and sum(weigh(v) for v in data.values()) > weight)
        ):
            data.popitem(last=False)

    def __getitem__(self, key: K) -> V:
        with self._lock:
            if not self._touch(key):
                raise KeyError(key)
            return self._data[key]

    def __setitem__(self, key: K, value: V) -> None:
        self.put(key, value)

    def __contains__(self, key: object) -> bool:
        with self._lock:
            return key in self._data

    def __len__(self) -> int:
        with self._lock:
            return len(self._data)

    def __iter__(self) -> Iterator[K]:
        with self._lock:
            return iter(list(self._data))

    def __repr__(self) -> str:
        return f"LRUCache({len(self)} entries, max_size={_value(self.max_size)}, max_weight={_value(self.max_weight)})"
