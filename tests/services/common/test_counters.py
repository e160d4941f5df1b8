"""Counters from many threads, and the seq tracker's gaps and restarts."""

from __future__ import annotations

import threading

from hypothesis import given
from hypothesis import strategies as st

from services.common.counters import Counters, SeqTracker


def test_counters_from_many_threads():
    counters = Counters()

    def bump():
        for _ in range(1000):
            counters.add("x")

    threads = [threading.Thread(target=bump) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert counters.snapshot() == {"x": 4000}


@given(st.lists(st.integers(0, 50), min_size=1, max_size=60))
def test_seq_tracker_counts_every_missing_seq(seqs):
    tracker = SeqTracker()
    expected_missed = expected_restarts = 0
    last = -1
    for seq in seqs:
        if last >= 0 and seq <= last:
            expected_restarts += 1
        elif last >= 0:
            expected_missed += seq - last - 1
        last = seq
        tracker.observe("r/scan", seq)
    snap = tracker.snapshot()["r/scan"]
    assert snap == {
        "last_seq": seqs[-1],
        "received": len(seqs),
        "missed": expected_missed,
        "restarts": expected_restarts,
    }


def test_seq_tracker_resume_counts_the_gap_after_a_restart():
    tracker = SeqTracker()
    tracker.resume("r/pose", 9)
    assert tracker.is_restart("r/pose", 3)
    assert tracker.observe("r/pose", 15) == 5


def test_a_retired_robots_streams_are_forgotten_and_the_others_kept():
    tracker = SeqTracker()
    for stream in ("r/scan", "r/odom", "r2/scan", "rr/scan"):
        tracker.observe(stream, 4)
    assert tracker.forget_robot("r")
    assert sorted(tracker.snapshot()) == ["r2/scan", "rr/scan"]
    assert tracker.last_seq("r/scan") == -1
    assert not tracker.forget_robot("r")  # nothing left of it
