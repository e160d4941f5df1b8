"""Fan-out of bus events (poses, map changes) from Zenoh threads to asyncio stream clients."""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass, field
from typing import Any

Event = tuple[str, str, dict[str, Any]]  # (robot id, event name, JSON-ready data)


@dataclass(eq=False)
class Subscription:
    """One stream client's bounded queue; when full, the oldest event is dropped and counted."""

    robot_id: str | None
    loop: asyncio.AbstractEventLoop
    queue: asyncio.Queue[Event]
    dropped: int = field(default=0)

    def offer(self, event: Event) -> None:
        """Runs on the client's event loop."""
        if self.queue.full():
            self.queue.get_nowait()
            self.dropped += 1
        self.queue.put_nowait(event)


class EventHub:
    """Thread-safe publish to every subscription of a robot (or of all robots)."""

    def __init__(self, queue_len: int) -> None:
        self.queue_len = queue_len
        self._lock = threading.Lock()
        self._subs: set[Subscription] = set()

    def subscribe(self, robot_id: str | None) -> Subscription:
        """Call from the event loop that will read the subscription's queue."""
        sub = Subscription(robot_id, asyncio.get_running_loop(), asyncio.Queue(self.queue_len))
        with self._lock:
            self._subs.add(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        """Stop handing events to `sub`; one already gone is no error."""
        with self._lock:
            self._subs.discard(sub)

    @property
    def clients(self) -> int:
        """How many stream clients are subscribed now."""
        with self._lock:
            return len(self._subs)

    def publish(self, robot_id: str, name: str, data: dict[str, Any]) -> None:
        """Hand the event to each interested client's loop (callable from any thread)."""
        with self._lock:
            targets = [s for s in self._subs if s.robot_id in (None, robot_id)]
        for sub in targets:
            try:
                sub.loop.call_soon_threadsafe(sub.offer, (robot_id, name, data))
            except RuntimeError:  # the client's loop has closed: it is going away
                self.unsubscribe(sub)
