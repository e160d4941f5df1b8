"""A robot's wait for the map server's map: scans and operators' poses kept in their order."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from scanflow.geometry import Pose2D
from scanflow.wire import DeskewedScanMessage

from services.matcher.waiting import Waiting

RING = np.column_stack((np.cos(np.linspace(0, 6, 20)), np.sin(np.linspace(0, 6, 20))))


def scan(seq: int) -> DeskewedScanMessage:
    return DeskewedScanMessage("r", seq, 0.1 * seq, RING, "odometry", False, 20, 0)


def drained(waiting: Waiting) -> list[int | Pose2D]:
    """Everything still waiting, oldest first: scans by seq, poses as they are."""
    out: list[int | Pose2D] = []
    while (item := waiting.next()) is not None:
        out.append(item.seq if isinstance(item, DeskewedScanMessage) else item)
    return out


def test_poses_keep_their_place_among_the_scans() -> None:
    waiting = Waiting(1, scan(5))
    waiting.hold(scan(6))
    waiting.place(Pose2D(1.0, 2.0, 0.3))
    waiting.hold(scan(7))
    assert waiting.scans == 3 and waiting.last_pose() == Pose2D(1.0, 2.0, 0.3)
    assert drained(waiting) == [5, 6, Pose2D(1.0, 2.0, 0.3), 7]
    assert waiting.scans == 0 and waiting.last_pose() is None
    waiting.place(Pose2D(4.0, 0.0, 0.0))  # while the last scan is tracked: for the next one
    assert drained(waiting) == [Pose2D(4.0, 0.0, 0.0)]


def test_past_capacity_the_oldest_scan_goes_and_the_last_pose_before_the_next_stays() -> None:
    waiting = Waiting(1, scan(0), capacity=2)
    waiting.place(Pose2D(1.0, 0.0, 0.0))
    waiting.place(Pose2D(2.0, 0.0, 0.0))  # replaces the one before: no scan came between
    assert waiting.hold(scan(1)) == 0
    waiting.place(Pose2D(3.0, 0.0, 0.0))
    assert waiting.hold(scan(2)) == 1  # scan 0 goes; the pose after it stays before scan 1
    assert waiting.hold(scan(3)) == 1  # scan 1 goes; of the poses before scan 2, the last
    assert drained(waiting) == [Pose2D(3.0, 0.0, 0.0), 2, 3]


@given(st.lists(st.one_of(st.integers(0, 9), st.none()), max_size=40), st.integers(1, 6))
def test_the_newest_scans_wait_in_order_each_after_the_last_pose_sent_before_it(
    events: list[int | None], capacity: int
) -> None:
    """Property: whatever comes, the newest `capacity` scans wait, in order, and before each
    the last pose sent before it since the scan before it that still waits (the poses of
    dropped scans' places collapse onto the next that waits)."""
    waiting = Waiting(1, scan(0), capacity)
    sent: list[int | Pose2D] = [0]
    for n, event in enumerate(events, start=1):
        if event is None:
            waiting.hold(scan(n))
            sent.append(n)
        else:
            waiting.place(Pose2D(float(event), 0.0, 0.0))
            sent.append(Pose2D(float(event), 0.0, 0.0))
    seqs = [x for x in sent if isinstance(x, int)]
    expected: list[int | Pose2D] = []
    for x in sent:
        if isinstance(x, int) and x not in seqs[-capacity:]:
            continue
        if isinstance(x, Pose2D) and expected and isinstance(expected[-1], Pose2D):
            expected.pop()
        expected.append(x)
    assert waiting.scans == min(len(seqs), capacity)
    assert drained(waiting) == expected
