"""A robot met mid-stream while its resume query is out: its scans since, and the operators'
poses sent meanwhile, in the order they came (each pose applies to the scans after it)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from scanflow.geometry import Pose2D
from scanflow.wire import DeskewedScanMessage

MAX_SCANS_WAITING = 1024  # per robot waiting for the map server's answer (~6 MB at 360 beams)


@dataclass(frozen=True)
class Placed:
    """An operator's pose: where the robot is at the next scan to come. Once that scan is
    lost (dropped while waiting), the pose is anchored to it: its stamp and odometry pose
    (None: it had none), so the scan after it is predicted by the odometry since."""

    pose: Pose2D
    stamp_s: float | None = None
    odom_pose: Pose2D | None = None

    @property
    def anchored(self) -> bool:
        return self.stamp_s is not None

    def lost(self, scan: DeskewedScanMessage) -> Placed:
        """This pose after `scan`, the first scan after it, was lost."""
        return self if self.anchored else Placed(self.pose, scan.stamp_s, scan.odom_pose)


class Waiting:
    """The scans and operators' poses of resume query number `ask`, in arrival order; at most
    `capacity` scans (the oldest go first; a pose before them stays, anchored to the first
    that went)."""

    def __init__(
        self, ask: int, first: DeskewedScanMessage, capacity: int = MAX_SCANS_WAITING,
        placed: Placed | None = None,
    ) -> None:
        """`placed`: an operator's pose sent before `first` (for the robot's first scan)."""
        self.ask = ask
        self.capacity = capacity
        self._items: deque[DeskewedScanMessage | Placed] = deque([first])
        if placed is not None:
            self._items.appendleft(placed)
        self.scans = 1  # how many of the items are scans

    def hold(self, scan: DeskewedScanMessage) -> int:
        """Keep `scan` after the others; the number of older scans dropped to make room (0, 1)."""
        # No two poses are ever next to each other (`place` replaces, this keeps one).
        dropped = 0
        if self.scans >= self.capacity:
            placed = self._take_placed()
            gone = self._items.popleft()  # the oldest scan
            assert isinstance(gone, DeskewedScanMessage)
            placed = placed.lost(gone) if placed is not None else None
            placed = self._take_placed() or placed  # one sent after it is newer
            if placed is not None:
                self._items.appendleft(placed)
            self.scans -= 1
            dropped = 1
        self._items.append(scan)
        self.scans += 1
        return dropped

    def _take_placed(self) -> Placed | None:
        """The pose at the head, taken out, if the head is one."""
        if self._items and isinstance(head := self._items[0], Placed):
            self._items.popleft()
            return head
        return None

    def place(self, pose: Pose2D) -> None:
        """An operator's pose: the robot is there at the next scan to come (it replaces one
        sent since the last scan)."""
        if self._items and isinstance(self._items[-1], Placed):
            self._items.pop()
        self._items.append(Placed(pose))

    def next(self) -> DeskewedScanMessage | Placed | None:
        """The oldest scan or pose still waiting (taken out), None when none is left."""
        if not self._items:
            return None
        item = self._items.popleft()
        if isinstance(item, DeskewedScanMessage):
            self.scans -= 1
        return item

    def last_placed(self) -> Placed | None:
        """The last operator's pose still waiting, as it stands when every scan waiting is
        lost (None: none sent)."""
        after: DeskewedScanMessage | None = None  # the first scan after it
        for item in reversed(self._items):
            if isinstance(item, Placed):
                return item if after is None else item.lost(after)
            after = item
        return None
