"""A robot's wait for the map server's map: scans and operators' poses kept in their order; a
pose whose next scan was lost is anchored to that scan's odometry."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from scanflow.geometry import Pose2D
from scanflow.wire import DeskewedScanMessage

from services.matcher.waiting import Placed, Waiting

RING = np.column_stack((np.cos(np.linspace(0, 6, 20)), np.sin(np.linspace(0, 6, 20))))


def scan(seq: int, odometry: bool = True) -> DeskewedScanMessage:
    odom = Pose2D(float(seq), 0.0, 0.0) if odometry else None
    return DeskewedScanMessage("r", seq, 0.5 * seq, RING, "odometry", False, 20, 0,
                               odom_pose=odom)


def drained(waiting: Waiting) -> list[int | Placed]:
    """Everything still waiting, oldest first: scans by seq, poses as they are."""
    out: list[int | Placed] = []
    while (item := waiting.next()) is not None:
        out.append(item.seq if isinstance(item, DeskewedScanMessage) else item)
    return out


def at(x: float) -> Pose2D:
    return Pose2D(x, 0.0, 0.0)


def test_poses_keep_their_place_among_the_scans() -> None:
    waiting = Waiting(1, scan(5))
    waiting.hold(scan(6))
    waiting.place(at(1.0))
    waiting.hold(scan(7))
    assert waiting.scans == 3
    assert drained(waiting) == [5, 6, Placed(at(1.0)), 7]
    assert waiting.scans == 0 and waiting.last_placed() is None
    waiting.place(at(4.0))  # while the last scan is tracked: for the next one
    assert drained(waiting) == [Placed(at(4.0))]


def test_past_capacity_the_oldest_scan_goes_and_a_pose_before_it_is_anchored_to_it() -> None:
    waiting = Waiting(1, scan(0), capacity=2)
    waiting.place(at(1.0))
    waiting.place(at(2.0))  # replaces the one before: no scan came between
    assert waiting.hold(scan(1)) == 0
    assert waiting.hold(scan(2)) == 1  # scan 0 goes; the pose after it stays before scan 1
    assert waiting.hold(scan(3)) == 1  # scan 1 goes: the robot was at 2 m there
    assert drained(waiting) == [Placed(at(2.0), 0.5, at(1.0)), 2, 3]


def test_when_every_scan_is_lost_the_last_pose_is_anchored_to_the_first_after_it() -> None:
    waiting = Waiting(1, scan(0))
    waiting.place(at(1.0))
    assert waiting.last_placed() == Placed(at(1.0))  # nothing after it: for the next scan
    waiting.hold(scan(1, odometry=False))
    waiting.hold(scan(2))
    assert waiting.last_placed() == Placed(at(1.0), 0.5, None)  # no odometry to carry it on
    before = Placed(at(7.0))  # sent before the wait, whose every scan is lost
    assert Waiting(2, scan(3), placed=before).last_placed() == Placed(at(7.0), 1.5, at(3.0))
    anchored = Placed(at(7.0), 0.0, at(0.0))  # lost before: its anchor stays
    assert Waiting(2, scan(3), placed=anchored).last_placed() == anchored


def test_a_pose_sent_before_the_wait_is_anchored_when_its_first_scans_overflow() -> None:
    """It waits in line before the first scan, so dropping that scan anchors it (a review:
    held outside the wait, it was applied unanchored 25 s late past 1024 scans)."""
    waiting = Waiting(1, scan(0), capacity=2, placed=Placed(at(5.0)))
    waiting.hold(scan(1))
    assert waiting.hold(scan(2)) == 1
    assert drained(waiting) == [Placed(at(5.0), 0.0, at(0.0)), 1, 2]


@given(st.lists(st.one_of(st.integers(0, 9), st.none()), max_size=40), st.integers(1, 6))
def test_the_newest_scans_wait_in_order_each_after_the_last_pose_sent_before_it(
    events: list[int | None], capacity: int
) -> None:
    """Property: whatever comes, the newest `capacity` scans wait, in order, each after the
    last pose sent since the scan before it that waits; a pose whose next scan went is
    anchored to that scan (the first that went after it)."""
    waiting = Waiting(1, scan(0), capacity)
    sent: list[int | Pose2D] = [0]
    for n, event in enumerate(events, start=1):
        if event is None:
            waiting.hold(scan(n))
            sent.append(n)
        else:
            waiting.place(at(float(event)))
            sent.append(at(float(event)))
    kept = [x for x in sent if isinstance(x, int)][-capacity:]
    expected: list[int | Placed] = []
    pending: Placed | None = None
    for x in sent:
        if isinstance(x, Pose2D):
            pending = Placed(x)
        elif x not in kept:
            pending = None if pending is None else pending.lost(scan(x))
        else:
            expected += [pending, x] if pending is not None else [x]
            pending = None
    expected += [pending] if pending is not None else []
    assert waiting.scans == len(kept)
    assert drained(waiting) == expected
