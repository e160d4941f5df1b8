"""The bounded hand-off from a service's worker to one sender thread that does the Zenoh puts.

A reliable BLOCK put waits while a subscriber or the link is slow (backpressure); done on the
worker, that wait stops the service's own work (the matcher's puts took ~6 % of its time on
freiburg-079). The sender thread waits instead, with the GIL released, while the worker goes
on with the next message; one FIFO keeps every key's order; a full outbox blocks the worker.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

_POLL_S = 0.1
_log = logging.getLogger("scanflow.outbox")


class Outbox:
    """Bounded FIFO of (publisher, payload, put options), sent in order by one daemon thread."""

    def __init__(
        self, maxsize: int, give_up_at: Callable[[], float], name: str = "outbox"
    ) -> None:
        """`give_up_at()`: the monotonic time past which a full outbox refuses a payload
        (math.inf while the service runs: it blocks; a stopping service's drain deadline)."""
        if maxsize < 1:
            raise ValueError(f"outbox size must be >= 1, got {maxsize}")
        self._queue: queue.Queue[tuple[Any, bytes, dict[str, Any]] | None] = queue.Queue(maxsize)
        self._give_up_at = give_up_at
        self.send_s = 0.0  # time the sender spent in puts (blocked by slow subscribers)
        self.failed = 0  # puts Zenoh refused (session closing)
        self.refused = 0  # payloads offered past the stop's deadline with the outbox full
        self._thread = threading.Thread(target=self._send, name=name, daemon=True)
        self._thread.start()

    def put(self, publisher: Any, payload: bytes, **options: Any) -> bool:
        """Queue `payload` for `publisher` (sent as `publisher.put(payload, **options)`),
        blocking while the outbox is full; False (counted in `refused`) only when there is
        still no room past `give_up_at()` (a stopping service whose drain ran out of time: what
        it drained before that still goes out)."""
        item = (publisher, payload, options)
        while True:
            wait_s = min(_POLL_S, self._give_up_at() - time.monotonic())
            try:
                if wait_s > 0.0:
                    self._queue.put(item, timeout=wait_s)
                else:  # past the deadline: room now or never, at no cost per payload
                    self._queue.put_nowait(item)
                return True
            except queue.Full:
                if wait_s <= 0.0:
                    self.refused += 1
                    return False

    def depth(self) -> int:
        """How many puts wait for the sender thread now."""
        return self._queue.qsize()

    def close(self, timeout_s: float) -> int:
        """Send what is queued (at most `timeout_s`), then end the sender; what was left."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self._queue.put(None, timeout=_POLL_S)
                break
            except queue.Full:
                if time.monotonic() > deadline:
                    break
        self._thread.join(max(0.0, deadline - time.monotonic()))
        return self._queue.qsize()

    def _send(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            publisher, payload, options = item
            t0 = time.perf_counter()
            try:
                publisher.put(payload, **options)
            except Exception:  # a refused put must not end the sender
                self.failed += 1
                _log.warning("put failed (%d so far)", self.failed, exc_info=True)
            self.send_s += time.perf_counter() - t0
