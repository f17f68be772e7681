"""A bounded, thread-safe memo of results a process may ask for again (OpenJTalk's output, an
alignment, a clip's noise): least recently used entries go first once the memo holds more
than ``max_items`` entries or ``max_bytes`` of them (as ``size_of`` counts an entry); the
entry just stored always stays, however large."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

__all__ = ["BoundedMemo"]

V = TypeVar("V")


class BoundedMemo(Generic[V]):
    """``get(key)`` gives the stored value (None when there is none) and marks it used;
    ``put(key, value)`` stores it and drops the least recently used entries beyond the
    bounds. Values are handed out as stored: store read-only arrays, or copy on the way out."""

    def __init__(
        self,
        *,
        max_items: int | None = None,
        max_bytes: int | None = None,
        size_of: Callable[[V], int] | None = None,
    ) -> None:
        if max_bytes is not None and size_of is None:
            raise ValueError("a memo bounded in bytes needs size_of")
        self.max_items, self.max_bytes = max_items, max_bytes
        self._size_of = size_of
        self._entries: OrderedDict[Hashable, tuple[V, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key: Hashable) -> V | None:
        with self._lock:
            entry = self._entries.get(key)
            if entry is None:
                return None
            self._entries.move_to_end(key)
            return entry[0]

    def put(self, key: Hashable, value: V) -> None:
        size = self._size_of(value) if self._size_of is not None else 0
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self._bytes -= old[1]
            self._entries[key] = (value, size)
            self._bytes += size
            while len(self._entries) > 1 and (
                (self.max_items is not None and len(self._entries) > self.max_items)
                or (self.max_bytes is not None and self._bytes > self.max_bytes)
            ):
                self._bytes -= self._entries.popitem(last=False)[1][1]

    def values(self) -> list[V]:
        """The stored values, least recently used first."""
        with self._lock:
            return [value for value, _ in self._entries.values()]

    @property
    def bytes(self) -> int:
        """What ``size_of`` counts for the stored values together."""
        return self._bytes

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self._bytes = 0

    def __len__(self) -> int:
        return len(self._entries)
