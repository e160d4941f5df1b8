"""Pair the scans the matcher inserted (`map/insert`) with the poses it published, by seq.

The matcher publishes a scan's insert before its pose, on one session, and the map server reads
both through one subscriber, so an insert normally waits only until its pose arrives. Inserts
overtaken by a later pose never get theirs: they are counted, not silently dropped.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

from scanflow.wire import DeskewedScanMessage, PoseEstimateMessage


@dataclass
class Pairing:
    """Inserted scans waiting for their pose (at most `limit`, oldest evicted and counted)."""

    limit: int
    scans: OrderedDict[int, DeskewedScanMessage] = field(default_factory=OrderedDict)
    scans_without_pose: int = 0
    scans_evicted: int = 0

    def add_scan(self, scan: DeskewedScanMessage) -> None:
        self.scans[scan.seq] = scan
        while len(self.scans) > self.limit:
            self.scans.popitem(last=False)
            self.scans_evicted += 1

    def match_pose(self, pose: PoseEstimateMessage) -> DeskewedScanMessage | None:
        """The inserted scan of `pose.seq`, if the matcher inserted it; older waiting scans
        are dropped and counted (their poses will not come any more)."""
        while self.scans:
            seq = next(iter(self.scans))
            if seq >= pose.seq:
                break
            self.scans.popitem(last=False)
            self.scans_without_pose += 1
        return self.scans.pop(pose.seq, None)

    def clear(self) -> None:
        self.scans.clear()
