"""Samples Zenoh delivered twice. Some topologies copy a sample onto two routes (a peer
connected to two routers, routers in one peer subnetwork): the copy carries the same
timestamp, and to a service it would be a seq that does not advance, which restarts the
robot's run and wipes its map. Every put of a scanflow service carries a timestamp of its
session (unique, increasing), so a sample whose timestamp was already seen on its key is a
copy. Samples without a timestamp (a robot's own client publishing) are never judged."""

from __future__ import annotations

import threading
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import Any

PER_KEY = 64  # copies arrive within moments: the last few timestamps of each key suffice
MAX_KEYS = 4096  # keys remembered (robots x streams); the least recently used goes first


class SeenSamples:
    """The timestamps of the last PER_KEY samples on each of at most MAX_KEYS keys."""

    def __init__(self, per_key: int = PER_KEY, max_keys: int = MAX_KEYS) -> None:
        if per_key < 1 or max_keys < 1:
            raise ValueError(f"per_key and max_keys must be >= 1, got {per_key}, {max_keys}")
        self._per_key = per_key
        self._max_keys = max_keys
        self._seen: OrderedDict[str, tuple[deque[Any], set[Any]]] = OrderedDict()
        self._lock = threading.Lock()  # callbacks run on several Zenoh threads

    def first(self, key: str, timestamp: Any) -> bool:
        """False when a sample with `timestamp` came on `key` already (a copy); True for a new
        one, or one without a timestamp."""
        if timestamp is None:
            return True
        with self._lock:
            entry = self._seen.get(key)
            if entry is None:
                entry = self._seen[key] = (deque(), set())
                if len(self._seen) > self._max_keys:
                    self._seen.popitem(last=False)
            else:
                self._seen.move_to_end(key)
            order, seen = entry
            if timestamp in seen:
                return False
            order.append(timestamp)
            seen.add(timestamp)
            if len(order) > self._per_key:
                seen.discard(order.popleft())
            return True

    def forget(self, which: Callable[[str], bool]) -> int:
        """Drop the timestamps of every key `which(key)` is true of (a retired robot's); how
        many keys went."""
        with self._lock:
            gone = [key for key in self._seen if which(key)]
            for key in gone:
                del self._seen[key]
            return len(gone)
