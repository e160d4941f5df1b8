"""Thread-safe counters and per-robot sequence-gap tracking, reported in service stats, and
how often a repeated warning is logged."""

from __future__ import annotations

import threading
from collections import defaultdict
from dataclasses import dataclass

LOG_FIRST = 10  # a repeated warning: logged the first LOG_FIRST times, then every LOG_EVERY-th
LOG_EVERY = 100


def worth_logging(n: int) -> bool:
    """Whether the n-th (from 1) occurrence of a repeated warning is logged: a faulty source
    sending bad messages all day must not flood the log (the count goes in the stats)."""
    return n <= LOG_FIRST or n % LOG_EVERY == 0


class Counters:
    """Named monotonically increasing counts, safe to bump from Zenoh callback threads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, int] = defaultdict(int)

    def add(self, name: str, amount: int = 1) -> int:
        """Add `amount` to the named count; its new value."""
        with self._lock:
            self._counts[name] += amount
            return self._counts[name]

    def get(self, name: str) -> int:
        """The named count; 0 for one never added to."""
        with self._lock:
            return self._counts.get(name, 0)

    def snapshot(self) -> dict[str, int]:
        """A copy of every count, by name."""
        with self._lock:
            return dict(self._counts)


@dataclass
class RobotSeq:
    """What one robot's stream looked like: last seq seen, messages, missed and restarts."""

    last_seq: int = -1
    received: int = 0
    missed: int = 0
    restarts: int = 0


class SeqTracker:
    """Counts gaps in per-robot (per-stream) sequence numbers: nothing missed goes unreported.

    A seq lower than or equal to the last one is a restart of the stream (a replay or a
    restarted publisher): it is counted and tracking continues from it.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._streams: dict[str, RobotSeq] = {}

    def observe(self, stream: str, seq: int) -> int:
        """Record `seq` on `stream`; return how many seqs were skipped just before it."""
        with self._lock:
            state = self._streams.setdefault(stream, RobotSeq())
            gap = 0
            if state.last_seq >= 0 and seq <= state.last_seq:
                state.restarts += 1
            elif state.last_seq >= 0:
                gap = seq - state.last_seq - 1
            state.missed += gap
            state.received += 1
            state.last_seq = seq
            return gap

    def resume(self, stream: str, last_seq: int) -> None:
        """Continue a stream from `last_seq` (e.g. read from a snapshot after a restart)."""
        with self._lock:
            self._streams.setdefault(stream, RobotSeq()).last_seq = last_seq

    def is_restart(self, stream: str, seq: int) -> bool:
        """True when `seq` does not move the stream forward (a replay or restarted publisher)."""
        with self._lock:
            state = self._streams.get(stream)
            return state is not None and 0 <= seq <= state.last_seq

    def last_seq(self, stream: str) -> int:
        """The stream's last seq (seen or resumed from); -1 for a stream not seen."""
        with self._lock:
            state = self._streams.get(stream)
            return -1 if state is None else state.last_seq

    def forget_robot(self, robot_id: str) -> bool:
        """Drop every stream of the robot (named `<robot>/<kind>`); whether it had any."""
        head = f"{robot_id}/"
        with self._lock:
            gone = [name for name in self._streams if name.startswith(head)]
            for name in gone:
                del self._streams[name]
            return bool(gone)

    def snapshot(self) -> dict[str, dict[str, int]]:
        """last_seq, received, missed and restarts of every stream, by stream name."""
        with self._lock:
            return {
                name: {
                    "last_seq": s.last_seq,
                    "received": s.received,
                    "missed": s.missed,
                    "restarts": s.restarts,
                }
                for name, s in self._streams.items()
            }
