"""The drop-oldest queue between a live capture thread and the processing loop."""

from __future__ import annotations

import collections
import threading
import time

__all__ = ["DropQueue"]


class DropQueue:
    """A bounded FIFO whose :meth:`put` never blocks: when full, the oldest item is dropped and
    counted (:attr:`dropped`).

    Examples
    --------
    >>> q = DropQueue(2)
    >>> for i in range(5):
    ...     q.put(i)
    >>> q.dropped, q.get(0.1), q.get(0.1), q.get(0.01)
    (3, 3, 4, None)
    """

    def __init__(self, maxsize: int):
        if maxsize < 1:
            raise ValueError(f"DropQueue: maxsize must be >= 1, got {maxsize}")
        self._items: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self.maxsize = int(maxsize)
        self.dropped = 0
        self.closed = False

    def put(self, item) -> None:
        with self._cond:
            while len(self._items) >= self.maxsize:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cond.notify()

    def close(self) -> None:
        """No more items will come: :meth:`get` returns None once the queue is empty."""
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    def get(self, timeout: float | None = None):
        """The oldest item, or None after ``timeout`` seconds (or when closed and empty)."""
        with self._cond:
            end = None if timeout is None else time.monotonic() + timeout
            while not self._items:
                if self.closed:
                    return None
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._cond.wait(left)
            return self._items.popleft()
