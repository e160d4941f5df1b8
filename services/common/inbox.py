"""The bounded hand-off from Zenoh callback threads to a service's single worker thread.

A full inbox blocks the callback: Zenoh then stops reading the link and, because publishers
use BLOCK congestion control, the publisher waits. That is backpressure, never a drop.
"""

from __future__ import annotations

import queue
import threading
from typing import Any

_POLL_S = 0.1


class Inbox:
    """A bounded FIFO of (kind, item) pairs that refuses to lose items while running."""

    def __init__(self, maxsize: int, stop: threading.Event) -> None:
        if maxsize < 1:
            raise ValueError(f"queue_size must be >= 1, got {maxsize}")
        self._queue: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize)
        self._stop = stop
        self.high_water = 0

    def put(self, kind: str, item: Any) -> bool:
        """Block until there is room; False only if the service is stopping."""
        while not self._stop.is_set():
            try:
                self._queue.put((kind, item), timeout=_POLL_S)
            except queue.Full:
                continue
            self.high_water = max(self.high_water, self._queue.qsize())
            return True
        return False

    def offer(self, kind: str, item: Any) -> bool:
        """Enqueue without waiting; False when the inbox is full."""
        try:
            self._queue.put_nowait((kind, item))
        except queue.Full:
            return False
        self.high_water = max(self.high_water, self._queue.qsize())
        return True

    def get(self, timeout_s: float = _POLL_S) -> tuple[str, Any] | None:
        """The next item, or None after `timeout_s` without one."""
        try:
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def take_all(self) -> list[tuple[str, Any]]:
        """Empty the inbox now and return what it held, oldest first."""
        items = []
        while True:
            try:
                items.append(self._queue.get_nowait())
            except queue.Empty:
                return items

    def depth(self) -> int:
        """How many items wait in the inbox now."""
        return self._queue.qsize()
