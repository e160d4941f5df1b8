"""The map server service: snapshots, replays, resends and whole maps taken from a matcher."""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from scanflow import keys
from scanflow.config import BackendSettings, MapServerSettings, ZenohSettings
from scanflow.geometry import Pose2D
from scanflow.maps.export import npz_arrays, npz_bytes
from scanflow.wire import MapInsertMessage, MapRedrawMessage, MapStateMessage, PoseEstimateMessage

from services.common.launch import free_port
from services.common.zsession import open_session
from services.mapserver.keyframes import Keyframes
from services.mapserver.robot import RobotMap
from services.mapserver.service import MapServer
from services.mapserver.snapshot import load_snapshots

from ..conftest import stats_failures_while


def test_a_snapshot_that_cannot_be_written_is_named_and_the_others_still_are(
    tmp_path, caplog, insert, pose
):
    server = MapServer(MapServerSettings(data_dir=str(tmp_path)),
                       ZenohSettings(mode="peer", connect=[]))
    try:
        for robot_id in ("a", "b"):
            server.handle("insert", replace(insert(0), robot_id=robot_id))
            server.handle("pose", replace(pose(0), robot_id=robot_id))
        (tmp_path / "a.snapshot.npz").mkdir()  # the file cannot be replaced
        server.snapshot()
        assert server.shell.counters.get("snapshots_failed") == 1
        assert server.shell.counters.get("snapshots") == 1
        assert "robot a: snapshot not written" in caplog.text
        assert (tmp_path / "b.snapshot.npz").is_file()
        server.snapshot()  # tried again, still failing, still not fatal
        assert server.shell.counters.get("snapshots_failed") == 2
    finally:
        server.shell.close(flush_s=0.0)


@pytest.mark.parametrize("first", ["insert", "pose"])
def test_a_replay_after_a_restart_from_the_snapshot_replaces_the_resumed_run(
    tmp_path, first, insert, pose, tracker_map
):
    """The map server resumed a robot from its snapshot, then the source starts again from seq 0
    (`scanflow up` run twice on one data dir): the new run replaces the old map and path,
    whichever stream shows it first (an audit saw both runs' paths and maps merged)."""
    settings = (MapServerSettings(data_dir=str(tmp_path)), ZenohSettings(mode="peer", connect=[]))
    server = MapServer(*settings)
    try:
        for seq in range(3):
            at = Pose2D(5.0 + seq, 0.0, 0.0)
            server.handle("insert", insert(seq, at))
            server.handle("pose", pose(seq, at))
        server.snapshot()
    finally:
        server.shell.close(flush_s=0.0)
    server = MapServer(*settings)
    try:
        robot = server.robots["r"]
        assert robot.last_seq == 2 and len(robot.trajectory.poses) == 3
        updates = {"insert": insert(0, Pose2D()), "pose": pose(0, Pose2D())}
        second = "pose" if first == "insert" else "insert"
        server.handle(first, updates[first])
        server.handle(second, updates[second])
        robot = server.robots["r"]
        assert robot.trajectory.poses.tolist() == [[0.0, 0.0, 0.0]]
        assert robot.last_seq == 0 and robot.last_insert_seq == 0
        np.testing.assert_array_equal(robot.map.grid.log_odds,
                                      tracker_map([0]).log_odds)
    finally:
        server.shell.close(flush_s=0.0)


@pytest.mark.parametrize("run_b", [11, 22])
def test_a_replay_ending_where_the_run_it_replaced_was_saved_is_saved_too(
    tmp_path, insert, pose, run_b
):
    """A replay (same run token, seqs back) or a new run (another token) replaces run A, whose
    snapshot moves aside; the new run, ending at A's saved (revision, seq), is snapshotted
    still (an audit found only `.previous` on disk, and the robot gone after a restart)."""
    settings = (MapServerSettings(data_dir=str(tmp_path)), ZenohSettings(mode="peer", connect=[]))
    server = MapServer(*settings)
    try:
        for run in (11, run_b):
            for seq in range(3):
                at = Pose2D(1.0 + seq, 0.0, 0.0)
                server.handle("insert", replace(insert(seq, at), run=run))
                server.handle("pose", replace(pose(seq, at), run=run))
            server.snapshot()
    finally:
        server.shell.close(flush_s=0.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "r.snapshot.npz", "r.snapshot.npz.previous"
    ]
    server = MapServer(*settings)
    try:
        assert server.robots["r"].last_seq == 2 and server.robots["r"].run == run_b
    finally:
        server.shell.close(flush_s=0.0)


@pytest.mark.parametrize("first", ["insert", "pose"])
def test_a_new_run_first_seen_past_its_start_replaces_the_resumed_run(
    tmp_path, caplog, first, insert, pose, tracker_map
):
    """Restarted from the snapshot of run A (seqs 0..2), the map server first sees the robot's
    new run B at seq 5, past A's seqs: the run token says it is a new run (seqs alone merged
    A's map and path with B's, asking the matcher for B's "inserts 3 and 4" after A's 2).
    B's earlier inserts are asked for from its first; a late message of A is dropped."""
    caplog.set_level(logging.INFO)
    settings = (MapServerSettings(data_dir=str(tmp_path)), ZenohSettings(mode="peer", connect=[]))
    server = MapServer(*settings)
    try:
        for seq in range(3):
            at = Pose2D(5.0 + seq, 0.0, 0.0)
            server.handle("insert", replace(insert(seq, at), run=11))
            server.handle("pose", replace(pose(seq, at), run=11))
        server.snapshot()
    finally:
        server.shell.close(flush_s=0.0)
    server = MapServer(*settings)
    run_b = [replace(insert(seq, Pose2D(0.1 * seq, 0.0, 0.0)), run=22,
                     previous_seq=seq - 1 if seq else None) for seq in range(6)]
    asked = []

    def matcher(selector: str, timeout_s: float):  # the matcher's RecentInserts.between
        asked.append(selector.split("?")[1])
        return [m.encode() for m in run_b[:5]], []

    server.shell.get = matcher
    try:
        assert server.robots["r"].run == 11
        updates = {"insert": run_b[5], "pose": replace(pose(5, Pose2D(0.5, 0.0, 0.0)), run=22)}
        second = "pose" if first == "insert" else "insert"
        server.handle(first, updates[first])
        server.handle(second, updates[second])
        server.handle("pose", replace(pose(3, Pose2D(8.0, 0.0, 0.0)), run=11))  # late, of A
        robot = server.robots["r"]
        assert asked == ["after=-1;through=4"] and robot.run == 22
        assert robot.trajectory.poses.tolist() == [[0.5, 0.0, 0.0]]
        assert robot.last_seq == 5 and robot.last_insert_seq == 5
        np.testing.assert_array_equal(robot.map.grid.log_odds, tracker_map(range(6)).log_odds)
        counters = server.shell.counters
        assert counters.get("runs_replaced") == 1 and counters.get("ended_run_dropped") == 1
        assert "inserts_lost" not in counters.snapshot()
        assert "robot r: a new run of its tracker at seq 5" in caplog.text
        # The run replaced is kept aside, a map file with its path (a run replaced by mistake:
        # a matcher that could not resume in time and started a map of its own).
        with np.load(tmp_path / "r.snapshot.npz.previous") as kept:
            assert kept["poses"][:, 0].tolist() == [5.0, 6.0, 7.0] and int(kept["run"]) == 11
        server.snapshot()
        assert [s.run for s in load_snapshots(tmp_path)[0]] == [22]
    finally:
        server.shell.close(flush_s=0.0)


def test_inserts_missed_that_no_matcher_sends_again_are_counted_and_named(tmp_path, caplog, insert):
    """No matcher answers the resend query (an isolated session): the gap is logged with its
    seqs and counted, and the insert that showed it still goes in."""
    server = MapServer(
        MapServerSettings(data_dir=str(tmp_path), resend_timeout_s=0.2),
        ZenohSettings(mode="peer", connect=[]),
    )
    try:
        server.handle("insert", insert(0))
        server.handle("insert", replace(insert(2), previous_seq=0))  # chained: no query
        assert "inserts_lost" not in server.shell.counters.snapshot()
        server.handle("insert", replace(insert(9), previous_seq=5))
        robot = server.robots["r"]
        assert robot.last_insert_seq == 9 and robot.map.revision == 3
        assert server.shell.counters.get("inserts_lost") == 1
        assert "inserts after seq 2 through 5 never came" in caplog.text
    finally:
        server.shell.close(flush_s=0.0)


def test_a_resend_query_that_fails_loses_the_gap_not_the_insert(tmp_path, caplog, insert) -> None:
    """The side session cannot open (no router) or the query is refused: the gap is counted
    and named with the reason, and the insert that showed it still goes in."""
    server = MapServer(MapServerSettings(data_dir=str(tmp_path)),
                       ZenohSettings(mode="peer", connect=[]))

    def unreachable(selector: str, timeout_s: float):
        raise RuntimeError("cannot open a Zenoh session")

    server.shell.get = unreachable
    try:
        server.handle("insert", insert(0))
        server.handle("insert", replace(insert(4), previous_seq=2))
        assert server.robots["r"].last_insert_seq == 4
        assert server.shell.counters.get("inserts_lost") == 1
        assert "the query failed: cannot open a Zenoh session" in caplog.text
    finally:
        server.shell.close(flush_s=0.0)


def test_a_late_pose_of_a_run_never_seen_does_not_replace_the_live_run(
    tmp_path, insert, pose
) -> None:
    """Poses travel apart from the inserts: a map server that first hears of the robot at a
    run change sees run B's first insert, then a late pose of run A, which it never knew.
    That pose is held, not taken for a new run (B would have been dropped from then on); a
    restart keeps the runs it replaced, so their late messages stay dropped."""
    settings = (MapServerSettings(data_dir=str(tmp_path)), ZenohSettings(mode="peer", connect=[]))
    server = MapServer(*settings)
    try:
        server.handle("insert", replace(insert(0), run=22))
        server.handle("pose", replace(pose(40, Pose2D(9.0, 0.0, 0.0)), run=11))  # late, of A
        for seq in range(5):
            at = Pose2D(0.1 * seq, 0.0, 0.0)
            server.handle("pose", replace(pose(seq, at), run=22))
            if seq:
                server.handle("insert", replace(insert(seq, at), run=22, previous_seq=seq - 1))
        robot = server.robots["r"]
        assert robot.run == 22 and robot.last_insert_seq == 4 and robot.last_seq == 4
        np.testing.assert_allclose(robot.trajectory.poses[:, 0], 0.1 * np.arange(5))
        assert server.shell.counters.get("poses_held") == 1
        server.handle("insert", replace(insert(0), run=33))  # a replay: run C
        server.handle("pose", replace(pose(0), run=33))
        assert robot.ended_runs == [22] and server.robots["r"].run == 33
        server.snapshot()
    finally:
        server.shell.close(flush_s=0.0)
    server = MapServer(*settings)
    try:
        server.handle("pose", replace(pose(5, Pose2D(8.0, 0.0, 0.0)), run=22))  # late, of B
        robot = server.robots["r"]
        assert robot.run == 33 and server.shell.counters.get("ended_run_dropped") == 1
        assert robot.trajectory.poses.tolist() == [[0.0, 0.0, 0.0]]
    finally:
        server.shell.close(flush_s=0.0)


def test_a_robot_localising_on_a_prior_map_starts_a_new_run_with_its_poses(
    tmp_path, pose
) -> None:
    """A tracker that puts nothing in the map (SCANFLOW_FRONTEND_UPDATE_MAP=false) sends only
    poses: where the map's run put nothing in it, a pose of another run starts that run (held
    for an insert, it would never go in)."""
    server = MapServer(MapServerSettings(data_dir=str(tmp_path)),
                       ZenohSettings(mode="peer", connect=[]))
    try:
        for seq in range(3):
            server.handle("pose", replace(pose(seq, Pose2D(5.0 + seq, 0.0, 0.0)), run=11))
        for seq in range(2):
            server.handle("pose", replace(pose(seq, Pose2D(0.1 * seq, 0.0, 0.0)), run=22))
        server.handle("pose", replace(pose(3, Pose2D(8.0, 0.0, 0.0)), run=11))  # late
        robot = server.robots["r"]
        assert robot.run == 22 and robot.trajectory.poses[:, 0].tolist() == [0.0, 0.1]
        counters = server.shell.counters
        assert counters.get("runs_replaced") == 1 and counters.get("ended_run_dropped") == 1
        assert "poses_held" not in counters.snapshot()
    finally:
        server.shell.close(flush_s=0.0)


@pytest.mark.parametrize(
    ("answer", "why"),
    [
        ([(3, 0, 0)], "1 came, not the chain"),  # (seq, previous_seq, run)
        ([(3, 0, 9), (4, 3, 9)], "of another run of its tracker"),  # it started anew meanwhile
    ],
)
def test_a_resend_that_stops_short_or_is_of_another_run_is_a_loss_counted(
    tmp_path, caplog, insert, answer, why
) -> None:
    """A chain of inserts that stops short of the gap's end is not taken (a matcher whose
    back end culled some of the missing inserts sends its whole map instead), nor one of
    another run."""
    server = MapServer(MapServerSettings(data_dir=str(tmp_path)),
                       ZenohSettings(mode="peer", connect=[]))
    asked = []

    def matcher(selector: str, timeout_s: float):
        asked.append(selector)
        return [replace(insert(s), previous_seq=p, run=r).encode() for s, p, r in answer], []

    server.shell.get = matcher
    try:
        server.handle("insert", insert(0))
        server.handle("insert", replace(insert(5), previous_seq=4))
        robot = server.robots["r"]
        assert len(asked) == 1 and asked[0].endswith("r/map/resend?after=0;through=4")
        assert robot.last_insert_seq == 5 and robot.map.revision == 2
        assert server.shell.counters.get("inserts_lost") == 1
        assert why in caplog.text
    finally:
        server.shell.close(flush_s=0.0)


def state_server(tmp_path, answer: bytes) -> tuple[MapServer, list[str]]:
    """A map server whose resend queries get `answer` (as a matcher past its recent inserts
    and without a back end would give)."""
    server = MapServer(MapServerSettings(data_dir=str(tmp_path)),
                       ZenohSettings(mode="peer", connect=[]))
    asked: list[str] = []

    def matcher(selector: str, timeout_s: float):
        asked.append(selector)
        return [answer], []

    server.shell.get = matcher
    return server, asked


def test_a_matchers_whole_map_stands_in_for_the_inserts_it_no_longer_keeps(
    tmp_path, caplog, insert, pose, tracker_map
):
    """The map server missed inserts 3..8, and the matcher keeps only its last few: it sends
    its map (inserts 0..10) and path (scans 0..11) instead. The map and the path become the
    matcher's; inserts and poses of the scans they hold, still on their way, are skipped;
    later ones go on as before, and a replay from seq 0 still restarts the robot."""
    path = np.column_stack((0.1 * np.arange(12), np.zeros(12), np.zeros(12)))
    state = MapStateMessage(
        "r", 11, 10, npz_bytes(npz_arrays(tracker_map([0, 2, 3, 5, 8, 9, 10]))),
        0.1 * np.arange(12), path,
    )
    server, asked = state_server(tmp_path, state.encode())
    try:
        for seq in (0, 2):
            server.handle("insert", replace(insert(seq, Pose2D(0.1 * seq, 0.0, 0.0)),
                                            previous_seq=None if seq == 0 else 0))
        for seq in (0, 1, 12):  # the pose subscriber runs ahead of the inserts' one
            server.handle("pose", pose(seq, Pose2D(5.0, 5.0, 0.0)))
        server.handle("insert", replace(insert(9, Pose2D(0.1 * 9, 0.0, 0.0)), previous_seq=8))
        robot = server.robots["r"]
        assert len(asked) == 1 and asked[0].endswith("r/map/resend?after=2;through=8")
        assert server.shell.counters.get("map_states_taken") == 1
        assert "inserts_lost" not in server.shell.counters.snapshot()
        assert "took its whole map (every insert through seq 10)" in caplog.text
        np.testing.assert_array_equal(robot.map.grid.log_odds,
                                      tracker_map([0, 2, 3, 5, 8, 9, 10]).log_odds)
        assert robot.last_insert_seq == 10 and robot.map.revision == 3
        # The matcher's path, then the pose of scan 12 that came before it.
        np.testing.assert_array_equal(robot.trajectory.poses[:12], path)
        assert robot.trajectory.poses[12].tolist() == [5.0, 5.0, 0.0]
        server.handle("insert", replace(insert(10, Pose2D(0.1 * 10, 0.0, 0.0)), previous_seq=9))
        assert server.shell.counters.get("inserts_held") == 2  # 9 (that asked) and 10
        server.handle("insert", replace(insert(12, Pose2D(0.1 * 12, 0.0, 0.0)), previous_seq=10))
        np.testing.assert_array_equal(robot.map.grid.log_odds,
                                      tracker_map([0, 2, 3, 5, 8, 9, 10, 12]).log_odds)
        assert len(asked) == 1
        server.handle("insert", insert(0))  # a replay
        assert robot.last_insert_seq == 0 and robot.held is None
    finally:
        server.shell.close(flush_s=0.0)


@pytest.mark.parametrize(
    ("answer", "reason"),
    [
        (MapStateMessage("r", 6, 6, b"", np.zeros(0), np.zeros((0, 3))).encode(),
         "not one of 'r' through 8"),
        (MapStateMessage("q", 9, 9, b"", np.zeros(0), np.zeros((0, 3))).encode(),
         "a map of robot 'q' through insert 9 came"),
        (MapStateMessage("r", 9, 9, b"junk", np.zeros(0), np.zeros((0, 3))).encode(),
         "the matcher's map of r: not a readable .npz"),
        (MapStateMessage("r", 9, 9, b"", np.zeros(0), np.zeros((0, 3)), run=4).encode(),
         "the matcher's map of r is of another run"),
        (b"\x93not a message", "not valid msgpack"),
    ],
    ids=["short", "another robot", "broken map", "another run", "junk"],
)
def test_a_map_state_that_does_not_fit_is_a_loss_named_not_taken(
    tmp_path, caplog, answer: bytes, reason: str, insert
) -> None:
    server, _ = state_server(tmp_path, answer)
    try:
        server.handle("insert", insert(0))
        server.handle("insert", replace(insert(9), previous_seq=8))
        robot = server.robots["r"]
        assert server.shell.counters.get("inserts_lost") == 1
        assert "map_states_taken" not in server.shell.counters.snapshot()
        assert reason in caplog.text
        assert robot.last_insert_seq == 9 and robot.map.revision == 2 and robot.held is None
    finally:
        server.shell.close(flush_s=0.0)


def test_a_whole_map_with_keyframes_replaces_the_kept_ones_and_holds_redraws_before_it(
    tmp_path, insert, redraw, tracker_map,
) -> None:
    """With loop closure the matcher's whole map carries its keyframes: they replace the kept
    ones, a redraw it holds that comes after it is skipped, and the next redraw, naming
    those keyframes and one inserted since, is followed."""
    kept = Keyframes()
    for seq in (0, 3, 7):
        kept.add(insert(seq, Pose2D(0.1 * seq, 0.0, 0.0)))
    state = MapStateMessage(
        "r", 9, 9, npz_bytes(npz_arrays(tracker_map([0, 3, 5, 7, 9]))), 0.1 * np.arange(10),
        np.zeros((10, 3)), kept.message("r"),
    )
    server = MapServer(MapServerSettings(data_dir=str(tmp_path)),
                       ZenohSettings(mode="peer", connect=[]),
                       backend_settings=BackendSettings(loop_closure=True))
    server.shell.get = lambda selector, timeout_s: ([state.encode()], [])
    try:
        server.handle("insert", insert(0))
        server.handle("insert", replace(insert(9, Pose2D(0.1 * 9, 0.0, 0.0)), previous_seq=8))
        robot = server.robots["r"]
        assert robot.keyframes is not None and robot.keyframes.seqs == [0, 3, 7]
        assert robot.last_insert_seq == 9
        server.handle("insert", redraw([0, 3, 7], [Pose2D()] * 3, np.zeros((8, 3)), 7))
        assert server.shell.counters.get("redraws_held") == 1
        server.handle("insert", replace(insert(10, Pose2D(1.0, 0.0, 0.0)), previous_seq=9))
        assert robot.keyframes.seqs == [0, 3, 7, 10]
        server.handle("insert", redraw([0, 3, 7, 10], [Pose2D()] * 4, np.zeros((11, 3)), 10))
        assert server.shell.counters.get("redrawn") == 1
        assert "errors.insert" not in server.shell.counters.snapshot()
    finally:
        server.shell.close(flush_s=0.0)


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.second_lane
def test_a_redraw_the_map_server_cannot_follow_is_counted_and_the_map_kept(launcher, bus, start):
    """A map server without loop closure (a misconfigured deployment) refuses the matcher's
    redraw, naming the setting, and keeps serving the map it had."""
    start("mapserver")
    insert_key = keys.map_key("robot", "insert")
    scan = MapInsertMessage("robot", 0, 0.0, Pose2D(), np.array([[2.0, 0.0], [2.0, 0.5]]),
                            np.zeros((0, 2)))
    bus.put(insert_key, scan.encode())
    bus.put(keys.pose("robot"), PoseEstimateMessage(
        "robot", 0, 0.0, Pose2D(), np.eye(3), "tracked", "gn", 1, 1.0).encode())
    bus.put(insert_key, MapRedrawMessage(
        "robot", 0, Pose2D(0.5, 0.0, 0.0), np.array([0]), np.array([[0.5, 0.0, 0.0]]),
        np.zeros(1), np.array([[0.5, 0.0, 0.0]])).encode())
    bus.wait_until(
        lambda: bus.stats("mapserver").counters.get("errors.insert", 0) == 1, 30.0,
        "the redraw refused",
    )
    # The pose comes on a key of its own: it may be handled after the redraw.
    bus.wait_until(lambda: bus.stats("mapserver").gauges.get("seq.robot/pose.last") == 0,
                   10.0, "the pose handled")
    (path,) = bus.get(keys.trajectory("robot"))
    np.testing.assert_array_equal(path.poses, [[0.0, 0.0, 0.0]])
    # The error is counted just before it is logged: wait for the line too.
    bus.wait_until(lambda: "keeps no keyframes" in launcher.log_text("mapserver"), 10.0,
                   "the refusal in the map server's log")


def test_map_queries_are_not_held_up_while_the_matcher_sends_inserts_again(
    tmp_path, insert
) -> None:
    """Asking the matcher for missed inserts waits up to resend_timeout_s (a whole map can take
    seconds to build and send): the lock the map, trajectory and resume queries take is free
    meanwhile, and the robot's map holds everything taken before the gap."""
    server = MapServer(MapServerSettings(data_dir=str(tmp_path)),
                       ZenohSettings(mode="peer", connect=[]))
    free_while_asked = []

    def slow_matcher(selector: str, timeout_s: float):
        free_while_asked.append(server.lock.acquire(blocking=False))
        if free_while_asked[-1]:
            assert server.robots["r"].last_insert_seq == 0  # what a query reads meanwhile
            server.lock.release()
        return [replace(insert(3), previous_seq=0).encode()], []

    server.shell.get = slow_matcher
    try:
        server.handle("insert", insert(0))
        server.handle("insert", replace(insert(4), previous_seq=3))
        assert free_while_asked == [True]
        robot = server.robots["r"]
        assert robot.last_insert_seq == 4 and robot.map.revision == 3
        assert server.shell.counters.get("inserts_resent") == 1
    finally:
        server.shell.close(flush_s=0.0)


def test_stats_gathered_while_robots_are_admitted_do_not_fail(tmp_path) -> None:
    """The stats queryable runs on a Zenoh thread while the worker admits robots: the per-robot
    gauges it gathers must not trip over the robots' dict growing (the stats query would go
    unanswered)."""
    server = MapServer(MapServerSettings(data_dir=str(tmp_path), max_robots=100_000),
                       ZenohSettings(mode="peer", connect=[]))
    robot = server.robots.setdefault("r0", RobotMap("r0", server.new_grid))
    try:
        failures = stats_failures_while(
            server.shell.stats, lambda i: server.robots.__setitem__(f"r{i}", robot)
        )
    finally:
        server.shell.close(flush_s=0.0)
    assert failures == []


def test_a_bad_prior_map_stops_the_start_with_one_line_naming_it(tmp_path, monkeypatch) -> None:
    """As the matcher does: `mapserver: prior_map: ...` and exit, not a traceback."""
    from services.mapserver.service import main

    for name in [n for n in os.environ if n.startswith("SCANFLOW_")]:
        monkeypatch.delenv(name)
    monkeypatch.setenv("SCANFLOW_FRONTEND_PRIOR_MAP", str(tmp_path / "none.npz"))
    with pytest.raises(SystemExit, match=r"^mapserver: prior_map: no file at "):
        main()


def test_an_insert_the_network_delivers_twice_does_not_restart_the_robot(tmp_path, insert) -> None:
    """Two routes can copy a sample. The copy of insert 1 is a seq that does not advance, a
    replay to the map server, which restarted the robot and wiped the map it held; the copy
    carries the original's timestamp and is dropped."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
    server = MapServer(MapServerSettings(data_dir=str(tmp_path)), ZenohSettings(connect=[endpoint]))
    client = open_session(ZenohSettings(connect=[endpoint]))
    server.shell.start(install_signals=False)
    worker = threading.Thread(target=server.shell.run, args=(server.handle, server.idle))
    worker.start()
    try:
        publisher = client.declare_publisher(keys.map_key("r", "insert"))
        deadline = time.monotonic() + 30.0
        while "r" not in server.robots:  # until the subscription has reached the router
            publisher.put(insert(0).encode(), timestamp=client.new_timestamp())
            assert time.monotonic() < deadline, "the map server never took insert 0"
            time.sleep(0.05)
        stamp = client.new_timestamp()
        for _ in range(2):
            publisher.put(replace(insert(1, Pose2D(0.5, 0.0, 0.0)), previous_seq=0).encode(),
                          timestamp=stamp)
        publisher.put(replace(insert(2, Pose2D(1.0, 0.0, 0.0)), previous_seq=1).encode(),
                      timestamp=client.new_timestamp())
        while server.robots["r"].last_insert_seq != 2:
            assert time.monotonic() < deadline, "insert 2 never came"
            time.sleep(0.05)
        assert server.robots["r"].map.revision >= 3  # 0, 1, 2: nothing wiped it
        assert server.shell.counters.get("duplicates.insert") == 1
    finally:
        server.shell.stop()
        worker.join(10.0)
        server.shell.close(flush_s=0.0)
        client.close()
        router.close()


def test_a_retired_robots_map_path_and_snapshot_files_go_and_its_place_is_free(
    tmp_path, insert, pose
) -> None:
    """SCANFLOW_MAPSERVER_MAX_ROBOTS=1: a second robot is refused until the first is retired;
    the retire drops its map, path and keyframes and deletes its snapshot files, so a restart
    on the same data directory does not bring it back."""
    settings = MapServerSettings(data_dir=str(tmp_path), max_robots=1, keyframes_per_file=1)
    loop_closure = BackendSettings.model_construct(loop_closure=True)
    server = MapServer(settings, ZenohSettings(mode="peer", connect=[]), None, loop_closure)
    try:
        for seq in range(3):
            at = Pose2D(0.1 * seq, 0.0, 0.0)
            previous = None if seq == 0 else seq - 1
            server.handle("insert", replace(insert(seq, at), robot_id="a", previous_seq=previous))
            server.handle("pose", replace(pose(seq, at), robot_id="a"))
        server.handle("insert", replace(insert(0), robot_id="b"))
        assert list(server.robots) == ["a"]  # b refused
        server.snapshot()
        assert (tmp_path / "a.snapshot.npz").is_file() and (tmp_path / "a.keyframes").is_dir()
        revision = server.robots["a"].map.revision
        dropped = server.retire("a")
        assert dropped.known and dropped.counts == {
            "map_revision": revision, "poses": 3, "keyframes": 3, "snapshot_files": 4}
        assert server.robots == {} and list(tmp_path.iterdir()) == []
        server.handle("insert", replace(insert(0), robot_id="b"))
        assert list(server.robots) == ["b"]  # the place is free
        assert server.retire("nobody").counts == {"snapshot_files": 0}
        assert not server.retire("nobody").known
    finally:
        server.shell.close(flush_s=0.0)
    again = MapServer(settings, ZenohSettings(mode="peer", connect=[]), None, loop_closure)
    try:
        assert "a" not in again.robots
    finally:
        again.shell.close(flush_s=0.0)
