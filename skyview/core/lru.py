"""A small least-recently-used cache, bounded by a count and shared safely between threads: the solvers of
a process (`skyview.solver.pipeline`), the pair databases it has mapped (`skyview.identify.angle`), a
catalog's magnitude cuts (`GuideCatalog.brighter_than`). The viewer makes and uses them on several threads."""

from __future__ import annotations

import threading
from typing import Callable, Hashable

_MISSING = object()


class LRU:
    """At most `maxsize` values by key; a value read or stored becomes the newest, the oldest goes first."""

    def __init__(self, maxsize: int):
        self.maxsize = int(maxsize)
        self._d: dict = {}
        self._lock = threading.Lock()

    def get(self, key: Hashable, default=None):
        with self._lock:
            value = self._d.pop(key, _MISSING)
            if value is _MISSING:
                return default
            self._d[key] = value
            return value

    def put(self, key: Hashable, value) -> None:
        with self._lock:
            self._d.pop(key, None)
            while self._d and len(self._d) >= self.maxsize:
                self._d.pop(next(iter(self._d)))
            self._d[key] = value

    def get_or_make(self, key: Hashable, make: Callable[[], object]):
        """The value kept for `key`, or make() kept (made outside the lock: two threads asking at once may
        both make it; the later one is kept)."""
        value = self.get(key, _MISSING)
        if value is _MISSING:
            value = make()
            self.put(key, value)
        return value

    def pop(self, key: Hashable, default=None):
        with self._lock:
            return self._d.pop(key, default)

    def clear(self) -> None:
        with self._lock:
            self._d.clear()

    def __len__(self) -> int:
        return len(self._d)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._d
