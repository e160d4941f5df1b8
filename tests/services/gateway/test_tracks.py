"""TrackStore's input-stream seqs: what the gateway numbers never reads as a restart."""

from __future__ import annotations

from dataclasses import replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.common.robots import RobotLimit
from services.gateway.tracks import StaleSeqError, TrackStore

from .conftest import estimate

seqs = st.lists(st.integers(0, 50), max_size=30)


@given(seen=seqs, posted=st.lists(st.booleans(), max_size=10))
def test_a_numbered_seq_is_past_every_seq_since_the_last_run_began(seen, posted):
    """Scans seen on the bus (any order, 0 starting a run) interleaved with numbered posts: a
    service reads a seq at or below its last as a replay, so each number must pass them all."""
    store = TrackStore(10)
    run: list[int] = []
    for i, seq in enumerate(seen):
        store.saw_scan("r", seq)
        run = [seq] if seq == 0 else [*run, seq]
        if i < len(posted) and posted[i]:
            number = store.next_seq("r", "scan", None)
            assert number > max(run)
            store.saw_scan("r", number)  # the post went out (publish_numbered notes it)
            run.append(number)


@given(seen=st.lists(st.integers(1, 50), min_size=1, max_size=10), stale=st.integers(1, 50))
def test_a_given_seq_behind_the_stream_is_refused_and_changes_nothing(seen, stale):
    store = TrackStore(10)
    for seq in seen:
        store.saw_odometry("r", seq)
    if stale > max(seen):
        assert store.next_seq("r", "odom", stale) == stale
        return
    stream = "the odom stream of robot 'r'"
    with pytest.raises(StaleSeqError, match=f"seq {stale} does not move {stream}"):
        store.next_seq("r", "odom", stale)
    assert store.next_seq("r", "odom", None) == max(seen) + 1
    assert store.next_seq("r", "odom", 0) == 0  # a new run, on purpose


def test_scans_follow_the_last_pose_until_a_scan_is_seen():
    store = TrackStore(10)
    store.add_pose(estimate("r", 40, 1.0, 0.0, 0.0))
    assert store.next_seq("r", "scan", None) == 41
    assert store.next_seq("r", "odom", None) == 0  # odometry has no pose to follow
    store.saw_scan("r", 41)
    store.saw_scan("r", 3)  # a late copy of an earlier scan lowers nothing
    assert store.next_seq("r", "scan", None) == 42


def test_a_seq_is_used_only_once_the_post_went_out():
    """Numbering alone records nothing: a post whose put failed leaves its seq to the next
    one, so the services see no gap in the robot's stream."""
    store = TrackStore(10)
    store.saw_odometry("r", 6)
    assert store.next_seq("r", "odom", None) == 7
    assert store.next_seq("r", "odom", None) == 7  # the first put failed: 7 again
    store.saw_odometry("r", 7)
    assert store.next_seq("r", "odom", None) == 8


def test_a_robot_over_the_limit_gets_no_seq():
    refused: list[str] = []
    store = TrackStore(10, RobotLimit(1, lambda robot, _first: refused.append(robot)))
    assert store.next_seq("a", "scan", None) == 0
    assert store.next_seq("b", "scan", 5) is None
    assert refused == ["b"] and not store.known("b")


def test_replayed_stream_restarts_the_cache(client, publish_poses):
    publish_poses("r1", [(10.0, 0.0, 0.0, 0.0), (11.0, 1.0, 0.0, 0.0)])
    publish_poses("r1", [(10.0, 9.0, 0.0, 0.0)], seq0=0)
    robots = client.get("/api/v1/robots").json()["robots"]
    (r1,) = [r for r in robots if r["robot_id"] == "r1"]
    assert r1["restarts"] == 1 and r1["poses_cached"] == 1 and r1["last_pose"]["x_m"] == 9.0


def test_another_run_of_the_tracker_restarts_the_cache_even_with_seqs_going_on():
    """The gateway missed the first poses of a new run (it restarted): the run token says so,
    where the seqs do not; an unknown run (0) keeps the cache, and a late pose of the run
    replaced is dropped."""
    store = TrackStore(10)
    for seq, run in ((1, 11), (2, 11), (3, 0), (7, 22), (8, 22), (4, 11), (9, 0)):
        store.add_pose(replace(estimate("r", seq, 0.1 * seq, float(seq), 0.0), run=run))
    assert [e.seq for e in store.estimates("r")] == [7, 8, 9]  # 4: late, of the run replaced
    assert [r.restarts for r in store.robots()] == [1]


def test_a_retired_robots_track_goes_and_frees_its_place():
    refused: list[tuple[str, bool]] = []
    store = TrackStore(10, RobotLimit(1, lambda robot, first: refused.append((robot, first))))
    store.saw_scan("a", 4)
    store.saw_odometry("a", 9)
    assert store.next_seq("b", "scan", None) is None
    assert store.forget("a") == {"poses_cached": 0, "scans_seen": 1}
    assert store.forget("a") is None and not store.known("a")
    assert store.next_seq("b", "scan", None) == 0  # the place is free
    store.forget("b")
    assert store.next_seq("a", "scan", None) == 0  # a new run of its own: numbered from 0
    assert store.next_seq("b", "scan", None) is None
    assert refused == [("b", True), ("b", True)]  # reported again after the retire
