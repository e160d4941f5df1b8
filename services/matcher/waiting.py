"""A robot met mid-stream while its resume query is out: its scans since, and the operators'
poses sent meanwhile, in the order they came (each pose applies to the scans after it)."""

from __future__ import annotations

from collections import deque

from scanflow.geometry import Pose2D
from scanflow.wire import DeskewedScanMessage

MAX_SCANS_WAITING = 1024  # per robot waiting for the map server's answer (~6 MB at 360 beams)


class Waiting:
    """The scans and operators' poses of resume query number `ask`, in arrival order; at most
    `capacity` scans (the oldest go first; a pose before them stays, it applies to the rest)."""

    def __init__(
        self, ask: int, first: DeskewedScanMessage, capacity: int = MAX_SCANS_WAITING
    ) -> None:
        self.ask = ask
        self.capacity = capacity
        self._items: deque[DeskewedScanMessage | Pose2D] = deque([first])
        self.scans = 1  # how many of the items are scans

    def hold(self, scan: DeskewedScanMessage) -> int:
        """Keep `scan` after the others; the number of older scans dropped to make room (0, 1)."""
        dropped = 0
        if self.scans >= self.capacity:
            pose = None  # of the poses before the next scan that stays, the last
            while isinstance(item := self._items.popleft(), Pose2D):
                pose = item
            self.scans -= 1
            dropped = 1
            while self._items and isinstance(head := self._items[0], Pose2D):
                pose = head
                self._items.popleft()
            if pose is not None:
                self._items.appendleft(pose)
        self._items.append(scan)
        self.scans += 1
        return dropped

    def place(self, pose: Pose2D) -> None:
        """An operator's pose: the robot is there at the next scan to come (it replaces one
        sent since the last scan)."""
        if self._items and not isinstance(self._items[-1], DeskewedScanMessage):
            self._items.pop()
        self._items.append(pose)

    def next(self) -> DeskewedScanMessage | Pose2D | None:
        """The oldest scan or pose still waiting (taken out), None when none is left."""
        if not self._items:
            return None
        item = self._items.popleft()
        if isinstance(item, DeskewedScanMessage):
            self.scans -= 1
        return item

    def last_pose(self) -> Pose2D | None:
        """The last operator's pose still waiting (None: none sent meanwhile)."""
        for item in reversed(self._items):
            if isinstance(item, Pose2D):
                return item
        return None
