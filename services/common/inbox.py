"""The bounded hand-off from Zenoh callback threads to a service's single worker thread.

A full inbox blocks the callback: Zenoh then stops reading the link and, because publishers
use BLOCK congestion control, the publisher waits. That is backpressure, never a drop. Only
`close` (once the worker has drained it at a stop) makes it refuse, and a refused item is
never half taken: closing and inserting exclude each other.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any


class Inbox:
    """A bounded FIFO of (kind, item) pairs that loses nothing until it is closed."""

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError(f"queue_size must be >= 1, got {maxsize}")
        self._maxsize = maxsize
        self._items: deque[tuple[str, Any]] = deque()
        self._changed = threading.Condition()
        self._closed = False
        self.high_water = 0

    def put(self, kind: str, item: Any) -> bool:
        """Block until there is room; False only once the inbox is closed."""
        with self._changed:
            while len(self._items) >= self._maxsize and not self._closed:
                self._changed.wait()
            return self._append(kind, item)

    def offer(self, kind: str, item: Any) -> bool:
        """Enqueue without waiting; False when the inbox is full or closed."""
        with self._changed:
            return len(self._items) < self._maxsize and self._append(kind, item)

    def _append(self, kind: str, item: Any) -> bool:
        if self._closed:
            return False
        self._items.append((kind, item))
        self.high_water = max(self.high_water, len(self._items))
        self._changed.notify_all()
        return True

    def get(self, timeout_s: float = 0.1) -> tuple[str, Any] | None:
        """The next item, or None after `timeout_s` without one."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while not self._items:
                left_s = deadline - time.monotonic()
                if left_s <= 0.0:
                    return None
                self._changed.wait(left_s)
            item = self._items.popleft()
            self._changed.notify_all()  # room for a blocked producer
            return item

    def close(self) -> list[tuple[str, Any]]:
        """Refuse from now on (blocked producers return False) and hand back what was left,
        oldest first; closing again returns nothing."""
        with self._changed:
            self._closed = True
            left = list(self._items)
            self._items.clear()
            self._changed.notify_all()
            return left

    def depth(self) -> int:
        """How many items wait in the inbox now."""
        with self._changed:
            return len(self._items)
