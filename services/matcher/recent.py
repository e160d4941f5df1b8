"""A robot's last inserts, kept by its matcher to send again to a map server that missed some.

A map server finds a missed insert by the chain of `MapInsertMessage.previous_seq` (a link to
the router that dropped, a map server restarted from a snapshot a few seconds old) and asks
for what it lacks (services.common.resend).
"""

from __future__ import annotations

import threading
from collections import deque

from services.common.resend import FIRST


class RecentInserts:
    """The last `capacity` encoded inserts of one robot's run, with the chain's last seq."""

    def __init__(self, capacity: int) -> None:
        self._kept: deque[tuple[int, int, bytes]] = deque(maxlen=capacity)  # seq, previous
        self._lock = threading.Lock()  # the worker adds while the query thread reads
        self.last_seq: int | None = None  # the run's last insert (None: none yet, or unknown)

    def add(self, seq: int, previous_seq: int | None, payload: bytes) -> None:
        """Keep the insert of `seq` (encoded as `payload`) that followed `previous_seq`."""
        with self._lock:
            self._kept.append((seq, FIRST if previous_seq is None else previous_seq, payload))
            self.last_seq = seq

    def between(self, after: int, through: int) -> list[bytes]:
        """The inserts after seq `after` through seq `through`, in order; LookupError naming
        what is kept when they are not all here."""
        with self._lock:
            kept = list(self._kept)
        start = next((i for i, (_, previous, _) in enumerate(kept) if previous == after), None)
        end = next((i for i, (seq, _, _) in enumerate(kept) if seq == through), None)
        if start is None or end is None or end < start:
            span = f"seqs {kept[0][0]}..{kept[-1][0]}" if kept else "none"
            raise LookupError(
                f"the inserts after seq {after} through {through} are not all kept here "
                f"(the last {len(kept)} inserts: {span})"
            )
        return [payload for _, _, payload in kept[start : end + 1]]
