"""A bounded cache of things made from files, valid while the files are unchanged."""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Any, Generic, TypeVar

__all__ = ["StampCache", "file_stamp"]

V = TypeVar("V")


def file_stamp(path: Path) -> tuple[int, int, int] | None:
    """(size, modification time in ns, inode) of ``path``, None when it does not exist: what
    changes when a file is appended to, rewritten or replaced.

    Parameters
    ----------
    path : Path

    Returns
    -------
    tuple of int or None
    """
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns, st.st_ino


class StampCache(Generic[V]):
    """Least-recently-used values by key, each kept with the stamp it was made for.

    Parameters
    ----------
    max_items : int
        Values kept at most.
    max_bytes : int, optional
        Total ``size`` of the values kept at most (the least recently used go first).
    size : callable, optional
        The size of a value in bytes (default: 0, only ``max_items`` bounds the cache).
    """

    def __init__(self, max_items: int, max_bytes: int | None = None, size: Callable[[Any], int] | None = None):
        self.max_items = max_items
        self.max_bytes = max_bytes
        self._size = size or (lambda _v: 0)
        self._items: OrderedDict[Hashable, tuple[Hashable, V, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key: Hashable, stamp: Hashable, make: Callable[[], V]) -> V:
        """The value of ``key`` made for ``stamp``; ``make()`` makes it when missing or stale.

        Parameters
        ----------
        key : hashable
        stamp : hashable
            What the value depends on (e.g. :func:`file_stamp` of its files).
        make : callable
            Makes the value (outside the cache's lock).

        Returns
        -------
        The value.
        """
        with self._lock:
            hit = self._items.get(key)
            if hit is not None and hit[0] == stamp:
                self._items.move_to_end(key)
                return hit[1]
        value = make()
        n = self._size(value)
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= old[2]
            if self.max_bytes is None or n <= self.max_bytes:
                self._items[key] = (stamp, value, n)
                self._bytes += n
            while len(self._items) > self.max_items or (self.max_bytes is not None and self._bytes > self.max_bytes):
                _k, (_s, _v, dropped) = self._items.popitem(last=False)
                self._bytes -= dropped
        return value
