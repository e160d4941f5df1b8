"""Map server pieces without a network: insertion, trajectory, snapshots, shards."""

from __future__ import annotations

import io
from dataclasses import replace

import numpy as np
import pytest
from scanflow.config import BackendSettings, MapServerSettings, ZenohSettings
from scanflow.geometry import Pose2D
from scanflow.maps.export import grid_from_npz, load_npz, npz_arrays, npz_bytes, save_npz
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.wire import MapInsertMessage, MapRedrawMessage, MapStateMessage, PoseEstimateMessage

from services.mapserver import replies
from services.mapserver.keyframes import Keyframes
from services.mapserver.robot import RobotMap
from services.mapserver.service import MapServer
from services.mapserver.snapshot import load_snapshots, save_snapshot
from services.matcher.shard import owns


def new_robot(snap=None, params: OccupancyParams | None = None) -> RobotMap:
    return RobotMap("r", lambda: OccupancyGrid(params or OccupancyParams()), snap)


def insert(seq: int, at: Pose2D | None = None) -> MapInsertMessage:
    pts = np.array([[2.0, 0.0], [2.0, 1.0], [1.5, -1.0]])
    return MapInsertMessage("r", seq, 0.1 * seq, at or Pose2D(), pts, np.zeros((0, 2)))


def pose(seq: int, at: Pose2D | None = None) -> PoseEstimateMessage:
    at = at or Pose2D()
    return PoseEstimateMessage("r", seq, 0.1 * seq, at, np.eye(3), "tracked", "gn", 1, 1.0)


def test_robot_map_inserts_at_the_insert_pose_and_notices_the_change():
    at = Pose2D(0.3, -0.2, 0.4)
    robot = new_robot()
    robot.apply(pose(2, at))  # a pose without an inserted scan changes no cell
    assert robot.take_change(0.5) is None and robot.map.revision == 0
    robot.insert(insert(3, at))
    assert robot.map.revision == 1 and robot.state == (1, 2)
    notice = robot.take_change(1.0)
    assert notice.min_x_m < at.x < notice.max_x_m and robot.take_change(2.0) is None
    moved = new_robot()
    moved.insert(insert(3, Pose2D(5.0, 0.0, 0.0)))  # the pose in the message is what counts
    assert moved.map.grid.extent != robot.map.grid.extent


def test_robot_map_uses_the_given_params_and_a_reset_keeps_them():
    robot = new_robot(params=OccupancyParams(resolution_m=0.1))
    robot.insert(insert(0))
    robot.apply(pose(0))
    robot.reset()
    assert robot.map.grid.resolution_m == 0.1 and robot.map.revision == 0


def test_a_reset_returns_to_the_starting_map_a_prior_one_included():
    prior = new_robot()
    prior.insert(insert(0, Pose2D(1.0, 2.0, 0.3)))
    robot = RobotMap("r", lambda: prior.map.grid)
    assert robot.map.revision == prior.map.revision == 1
    robot.insert(insert(1))
    robot.apply(pose(1))
    robot.reset()
    assert robot.map.grid is prior.map.grid and robot.last_seq == -1


def test_snapshot_round_trip(tmp_path):
    robot = new_robot()
    for seq in range(3):
        robot.insert(insert(seq, Pose2D(0.1 * seq, 0.0, 0.0)))
        robot.apply(pose(seq, Pose2D(0.1 * seq, 0.0, 0.0)))
    save_snapshot(tmp_path, robot.snapshot())
    (snap,), skipped = load_snapshots(tmp_path)
    again = new_robot(snap)
    assert again.last_seq == 2 and again.state == robot.state and skipped == []
    assert again.last_insert_seq == 2  # the next insert names its predecessor: checked
    np.testing.assert_array_equal(again.map.grid.log_odds, robot.map.grid.log_odds)
    np.testing.assert_array_equal(again.trajectory.poses, robot.trajectory.poses)
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind


def test_the_odometry_pose_of_the_paths_end_is_kept_resumed_and_reset(tmp_path):
    """A restarted matcher predicts its next scan from the path's end by the odometry since:
    the map server keeps the last estimate's odometry pose (through a snapshot), gives it with
    the path when the path ends there, and forgets it on a replay."""
    robot = new_robot()
    robot.insert(insert(0))
    robot.apply(replace(pose(0), odom_pose=Pose2D(5.0, 1.0, 0.5)))
    assert replies.resume(robot).odom_pose == Pose2D(5.0, 1.0, 0.5)
    save_snapshot(tmp_path, robot.snapshot())
    (snap,), _ = load_snapshots(tmp_path)
    again = new_robot(snap)
    assert replies.resume(again).odom_pose == Pose2D(5.0, 1.0, 0.5)
    again.apply(pose(1))  # an estimate without odometry: nothing to go on from
    assert replies.resume(again).odom_pose is None
    robot.apply(replace(pose(1), odom_pose=Pose2D(6.0, 1.0, 0.5)))
    robot.trajectory.append(9.0, Pose2D())  # a path that ends elsewhere (a taken state)
    assert robot.odom_at_path_end() is None
    robot.reset()
    assert robot.last_odom is None


def test_a_snapshot_is_one_file_that_loads_as_a_map(tmp_path):
    robot = new_robot()
    robot.insert(insert(0))
    robot.apply(pose(0))
    save_snapshot(tmp_path, robot.snapshot())
    (path,) = tmp_path.iterdir()  # map and trajectory together: no crash can split them
    assert path.name == "r.snapshot.npz"
    np.testing.assert_array_equal(load_npz(path).log_odds, robot.map.grid.log_odds)


def test_an_unreadable_snapshot_is_skipped_and_named_not_a_crash(tmp_path):
    robot = new_robot()
    robot.insert(insert(0))
    robot.apply(pose(0))
    save_snapshot(tmp_path, robot.snapshot())
    (tmp_path / "s.snapshot.npz").write_bytes(b"not a zip file")
    save_npz(robot.map.grid, tmp_path / "m.snapshot.npz")  # a map without a trajectory
    snaps, skipped = load_snapshots(tmp_path)
    assert [s.robot_id for s in snaps] == ["r"]
    assert len(skipped) == 2 and "robot m" in skipped[0] and "robot s" in skipped[1]


@pytest.mark.parametrize("cut", [0, 0.5, -10])
def test_a_snapshot_cut_short_is_skipped_and_named_not_a_crash(tmp_path, cut):
    """A disk that filled or a kill mid-copy: the map server starts without that robot (an
    audit saw it exit 1 on a BadZipFile, a crash loop under `restart: unless-stopped`)."""
    robot = kept_robot(range(5))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    path = tmp_path / "r.snapshot.npz"
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * cut) if cut >= 0 else cut])
    snaps, skipped = load_snapshots(tmp_path)
    assert snaps == [] and len(skipped) == 1 and "robot r: snapshot not loaded" in skipped[0]


def test_a_chunk_cut_short_costs_the_keyframes_not_the_map(tmp_path):
    robot = kept_robot(range(5))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    chunk = next((tmp_path / "r.keyframes").iterdir())
    chunk.write_bytes(chunk.read_bytes()[:100])
    (snap,), skipped = load_snapshots(tmp_path)
    assert snap.keyframes is None and snap.last_seq == 4
    assert len(skipped) == 1 and "keyframes not loaded" in skipped[0], skipped


def test_shards_split_robots_and_a_robot_list_wins():
    robots = [f"robot{i}" for i in range(40)]
    first = {r for r in robots if owns(r, "0/2", [])}
    second = {r for r in robots if owns(r, "1/2", [])}
    assert first | second == set(robots) and not first & second and first and second
    assert owns("x", "1/2", ["x"]) and not owns("y", "0/1", ["x"])


def redraw(seqs: list[int], poses: list[Pose2D], path: np.ndarray, seq: int) -> MapRedrawMessage:
    return MapRedrawMessage(
        "r", seq, Pose2D(0.1, 0.0, 0.02), np.array(seqs, dtype=np.int64),
        np.array([p.to_array() for p in poses]).reshape(-1, 3),
        0.1 * np.arange(len(path)), path,
    )


def test_a_redraw_redraws_the_kept_keyframes_at_their_new_poses_and_takes_the_path():
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    robot.insert(insert(0, Pose2D()))
    robot.apply(pose(0))
    robot.apply(pose(1))
    robot.insert(insert(2, Pose2D(1.0, 0.0, 0.0)))
    robot.take_change(0.0)
    moved = [Pose2D(0.0, 0.5, 0.0), Pose2D(1.0, 0.5, 0.1)]
    path = np.array([[0.0, 0.5, 0.0], [0.5, 0.5, 0.05], [1.0, 0.5, 0.1]])
    revision = robot.map.revision
    robot.redraw(redraw([0, 2], moved, path, 2), OccupancyParams())
    want = new_robot()
    for seq, at in zip((0, 2), moved, strict=True):
        want.insert(insert(seq, at))
    np.testing.assert_array_equal(robot.map.grid.log_odds, want.map.grid.log_odds)
    assert robot.map.grid.extent == want.map.grid.extent
    assert robot.map.revision == revision + 1  # a new revision, never an old one again
    assert robot.take_change(1.0) is not None  # the whole map changed
    np.testing.assert_array_equal(robot.trajectory.poses, path)
    resume = replies.resume(robot)  # what a restarted matcher resumes from: all redrawn
    served = resume.keyframes
    assert served is not None and served.seqs.tolist() == [0, 2]
    np.testing.assert_allclose(served.poses, [p.to_array() for p in moved], atol=1e-12)
    np.testing.assert_array_equal(resume.poses, path)
    assert resume.revision == robot.map.revision
    with np.load(io.BytesIO(resume.map_npz)) as data:
        drawn = grid_from_npz(data, "the resume's map")
    np.testing.assert_array_equal(drawn.log_odds, want.map.grid.log_odds)
    robot.apply(pose(2, Pose2D(9.0, 9.0, 0.0)))  # the redraw's path already holds scan 2
    robot.apply(pose(3, Pose2D(1.5, 0.5, 0.1)))
    assert len(robot.trajectory) == 4 and robot.last_seq == 3
    np.testing.assert_allclose(robot.trajectory.poses[-1], [1.5, 0.5, 0.1], atol=1e-12)


def test_a_redraw_that_does_not_fit_is_refused_and_changes_nothing():
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    robot.insert(insert(0))
    robot.insert(insert(2, Pose2D(1.0, 0.0, 0.0)))
    before = robot.map.grid.log_odds.copy(), robot.map.revision
    wrong = redraw([0, 3], [Pose2D(), Pose2D()], np.zeros((3, 3)), 3)
    with pytest.raises(ValueError, match=r"differ from keyframe 1 on \(seq 3 vs 2\)"):
        robot.redraw(wrong, OccupancyParams())
    with pytest.raises(ValueError, match="names 1 keyframes, this map server holds 2"):
        robot.redraw(redraw([0], [Pose2D()], np.zeros((1, 3)), 0), OccupancyParams())
    unkept = new_robot()
    with pytest.raises(ValueError, match="SCANFLOW_BACKEND_LOOP_CLOSURE is off here"):
        unkept.redraw(redraw([], [], np.zeros((0, 3)), 0), OccupancyParams())
    assert replies.resume(unkept).keyframes is None  # the matcher names why
    np.testing.assert_array_equal(robot.map.grid.log_odds, before[0])
    assert robot.map.revision == before[1] and len(robot.keyframes) == 2


def test_snapshots_keep_the_keyframes_so_a_restart_can_follow_the_next_redraw(tmp_path):
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    robot.insert(insert(0))
    robot.insert(MapInsertMessage(
        "r", 4, 0.4, Pose2D(1.0, 0.0, 0.2), np.array([[3.0, 0.5]]), np.array([[0.0, 9.0]]),
        Pose2D(0.2, 0.0, 0.1),
    ))
    robot.apply(pose(4))
    robot.redraw(redraw([0, 4], [Pose2D(), Pose2D(1.0, 0.1, 0.2)], np.zeros((5, 3)), 4),
                 OccupancyParams())
    save_snapshot(tmp_path, robot.snapshot())
    (snap,), skipped = load_snapshots(tmp_path)
    assert skipped == [] and snap.redrawn_seq == 4
    resumed = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), snap, keep_keyframes=True)
    assert resumed.keyframes.seqs == [0, 4]
    loop_closure_off = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), snap)
    assert loop_closure_off.keyframes is None  # not kept (nor grown) while the setting is off
    for got, want in zip(resumed.keyframes.nodes, robot.keyframes.nodes, strict=True):
        assert (got.stamp_s, got.mount) == (want.stamp_s, want.mount)
        np.testing.assert_array_equal(got.points, want.points)
        np.testing.assert_array_equal(got.no_return, want.no_return)
    again = redraw([0, 4], [Pose2D(0.0, 0.2, 0.0), Pose2D(1.0, 0.3, 0.2)], np.zeros((5, 3)), 4)
    robot.redraw(again, OccupancyParams())
    resumed.redraw(again, OccupancyParams())
    np.testing.assert_array_equal(resumed.map.grid.log_odds, robot.map.grid.log_odds)


def test_broken_keyframes_cost_the_keyframes_not_the_map_naming_why(tmp_path):
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    robot.insert(insert(0))
    robot.apply(pose(0))
    save_snapshot(tmp_path, robot.snapshot())
    path = next(tmp_path.iterdir())
    with np.load(path) as data:
        arrays = dict(data)
    arrays["keyframes_hit_counts"] = np.array([7])
    np.savez(path, **arrays)
    (snap,), skipped = load_snapshots(tmp_path)
    assert snap.keyframes is None and snap.last_seq == 0
    assert "hit_counts must be >= 0 and add up to the rows of hits" in skipped[0]


def test_poses_of_later_scans_that_came_before_the_redraw_are_kept():
    """Poses and inserts come on two subscribers: the redraw of scan 2 may come after the
    pose of scan 3 (already in the new frame)."""
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    robot.insert(insert(0))
    robot.apply(pose(0))
    robot.insert(insert(2, Pose2D(1.0, 0.0, 0.0)))
    robot.apply(pose(1))
    robot.apply(pose(2, Pose2D(1.0, 0.5, 0.0)))
    robot.apply(pose(3, Pose2D(1.5, 0.5, 0.0)))  # before the redraw of scan 2
    path = np.array([[0.0, 0.5, 0.0], [0.5, 0.5, 0.0], [1.0, 0.5, 0.0]])
    robot.redraw(redraw([0, 2], [Pose2D(0.0, 0.5, 0.0), Pose2D(1.0, 0.5, 0.0)], path, 2),
                 OccupancyParams())
    np.testing.assert_array_equal(robot.trajectory.poses, [*path, [1.5, 0.5, 0.0]])
    np.testing.assert_allclose(robot.trajectory.stamps_s, [0.0, 0.1, 0.2, 0.3])


def kept_robot(seqs: range) -> RobotMap:
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    for seq in seqs:
        robot.insert(MapInsertMessage(
            "r", seq, 0.1 * seq, Pose2D(0.1 * seq, 0.0, 0.0), np.full((2, 2), 1.0 + seq),
            np.full((1, 2), 5.0 + seq), Pose2D(0.2, 0.0, 0.01 * seq),
        ))
    robot.apply(pose(seqs[-1]))
    return robot


def assert_same_keyframes(got, want) -> None:
    assert got.seqs == want.seqs and got.poses == want.poses
    for a, b in zip(got.nodes, want.nodes, strict=True):
        assert (a.stamp_s, a.mount) == (b.stamp_s, b.mount)
        assert a.points.tobytes() == b.points.tobytes()
        assert a.no_return.tobytes() == b.no_return.tobytes()


def test_keyframe_scans_are_written_once_by_chunks_and_read_back(tmp_path):
    """11 keyframes, 4 to a file: two files, written by the first snapshot and left as they
    are by the next (a scan never changes); the snapshot holds the last three's scans."""
    robot = kept_robot(range(0, 22, 2))
    save_snapshot(tmp_path, robot.snapshot(), 4)
    chunks = sorted((tmp_path / "r.keyframes").iterdir())
    assert [p.name.split("-", 1)[1] for p in chunks] == ["4-000000.npz", "4-000001.npz"]
    written = [p.stat().st_mtime_ns for p in chunks]
    robot.keyframes.moved(np.array([[0.0, 0.1 * k, 0.0] for k in range(11)]))  # a redraw
    save_snapshot(tmp_path, robot.snapshot(), 4)
    assert [p.stat().st_mtime_ns for p in chunks] == written
    (snap,), skipped = load_snapshots(tmp_path)
    assert skipped == []
    assert_same_keyframes(snap.keyframes, robot.keyframes)
    with np.load(tmp_path / "r.snapshot.npz") as data:
        assert int(data["keyframes_stored"]) == 8 and data["keyframes_hit_counts"].size == 3


def test_a_new_run_writes_its_own_chunks_and_drops_the_old_ones(tmp_path):
    robot = kept_robot(range(10, 16))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    old = set((tmp_path / "r.keyframes").iterdir())
    assert len(old) == 3
    for seq in range(5):  # the stream started again: the seqs went back
        robot.insert(insert(seq))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    new = set((tmp_path / "r.keyframes").iterdir())
    assert len(new) == 2 and not new & old
    (snap,), _ = load_snapshots(tmp_path)
    assert snap.keyframes.seqs == [0, 1, 2, 3, 4]
    assert_same_keyframes(snap.keyframes, robot.keyframes)


def test_a_lost_chunk_costs_the_keyframes_not_the_map(tmp_path):
    robot = kept_robot(range(5))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    next((tmp_path / "r.keyframes").iterdir()).unlink()
    (snap,), skipped = load_snapshots(tmp_path)
    assert snap.keyframes is None and snap.last_seq == 4
    np.testing.assert_array_equal(snap.grid.log_odds, robot.map.grid.log_odds)
    assert len(skipped) == 1 and "keyframes not loaded" in skipped[0], skipped
    assert "cannot follow this run's redraws" in skipped[0]


def test_another_file_size_writes_new_files_and_drops_the_old(tmp_path):
    """SCANFLOW_MAPSERVER_KEYFRAMES_PER_FILE changed between two restarts of the same run."""
    robot = kept_robot(range(9))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    save_snapshot(tmp_path, robot.snapshot(), 3)
    names = sorted(p.name.split("-", 1)[1] for p in (tmp_path / "r.keyframes").iterdir())
    assert names == ["3-000000.npz", "3-000001.npz", "3-000002.npz"]
    (snap,), skipped = load_snapshots(tmp_path)
    assert skipped == []
    assert_same_keyframes(snap.keyframes, robot.keyframes)


def test_a_snapshot_written_before_chunks_still_loads(tmp_path):
    """Files from before the chunks hold every scan inline, and no `stored` or `run`."""
    robot = kept_robot(range(3))
    save_snapshot(tmp_path, robot.snapshot())
    path = tmp_path / "r.snapshot.npz"
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files if k not in ("keyframes_stored", "keyframes_run")}
    np.savez_compressed(path, **arrays)
    (snap,), skipped = load_snapshots(tmp_path)
    assert skipped == []
    assert_same_keyframes(snap.keyframes, robot.keyframes)


def test_a_new_run_on_a_resumed_map_starts_the_kept_keyframes_afresh(tmp_path):
    """The robot's seqs start again at 0 on a map resumed from a snapshot: its tracker keeps
    only the new run's keyframes, and so does the map server (still strictly increasing, so
    the snapshot and the keyframes query keep working)."""
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    for seq in (3, 7):
        robot.insert(insert(seq))
    robot.apply(pose(7))
    save_snapshot(tmp_path, robot.snapshot())
    (snap,), _ = load_snapshots(tmp_path)
    resumed = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), snap, keep_keyframes=True)
    resumed.insert(insert(0))
    resumed.apply(pose(0))
    assert resumed.keyframes.seqs == [0]
    save_snapshot(tmp_path, resumed.snapshot())
    assert replies.resume(resumed).keyframes.seqs.tolist() == [0]


def test_a_region_apart_from_the_map_has_no_cells_and_bad_bounds_are_named():
    robot = new_robot()
    robot.insert(insert(0))
    inside = replies.region(robot, (0.0, -1.0, 2.5, 1.5))
    assert inside.occupancy.size > 0
    for far in ((1000.0, 1000.0, 1001.0, 1001.0), (-900.0, -900.0, -899.0, -899.0),
                (1000.0, 0.0, 1001.0, 0.5)):
        assert replies.region(robot, far).occupancy.shape == (0, 0)
    with pytest.raises(ValueError, match="must be finite"):
        replies.region(robot, (float("nan"), 0.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="x0 <= x1"):
        replies.region(robot, (2.0, 0.0, 1.0, 1.0))


def test_a_snapshot_file_whose_name_is_no_robot_id_is_skipped(tmp_path):
    """Written by something else (or before ids were checked): never served as a robot."""
    robot = new_robot()
    robot.insert(insert(0))
    robot.apply(pose(0))
    save_snapshot(tmp_path, robot.snapshot())
    (tmp_path / "r.snapshot.npz").rename(tmp_path / "*.snapshot.npz")
    snaps, skipped = load_snapshots(tmp_path)
    assert snaps == [] and "robot *" in skipped[0] and "invalid" in skipped[0]


def test_a_snapshot_that_cannot_be_written_is_named_and_the_others_still_are(tmp_path, caplog):
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
def test_a_replay_after_a_restart_from_the_snapshot_replaces_the_resumed_run(tmp_path, first):
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


def test_inserts_missed_that_no_matcher_sends_again_are_counted_and_named(tmp_path, caplog):
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


def test_a_resend_query_that_fails_loses_the_gap_not_the_insert(tmp_path, caplog) -> None:
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


def test_culled_inserts_go_into_the_map_but_not_into_the_kept_keyframes():
    """An insert the back end culled as a keyframe changes the map as any other, but it is not
    kept: the redraw that names the keyframes only fits."""
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    want = new_robot()
    for message in (insert(0), replace(insert(1, Pose2D(0.1, 0.0, 0.0)), keyframe=False),
                    insert(2, Pose2D(1.0, 0.0, 0.0))):
        robot.insert(message)
        want.insert(message)
    np.testing.assert_array_equal(robot.map.grid.log_odds, want.map.grid.log_odds)
    assert robot.keyframes is not None and robot.keyframes.seqs == [0, 2]
    path = np.zeros((3, 3))
    robot.redraw(redraw([0, 2], [Pose2D(), Pose2D(1.0, 0.0, 0.0)], path, 2), OccupancyParams())
    assert robot.map.revision == want.map.revision + 1


def test_a_resend_that_stops_short_is_a_loss_counted(tmp_path, caplog) -> None:
    """A chain of inserts that stops short of the gap's end is not taken: a matcher whose
    back end culled some of the missing inserts sends its whole map instead."""
    server = MapServer(MapServerSettings(data_dir=str(tmp_path)),
                       ZenohSettings(mode="peer", connect=[]))
    asked = []

    def matcher(selector: str, timeout_s: float):
        asked.append(selector)
        return [replace(insert(3), previous_seq=0).encode()], []

    server.shell.get = matcher
    try:
        server.handle("insert", insert(0))
        server.handle("insert", replace(insert(5), previous_seq=4))
        robot = server.robots["r"]
        assert len(asked) == 1 and asked[0].endswith("r/map/resend?after=0;through=4")
        assert robot.last_insert_seq == 5 and robot.map.revision == 2
        assert server.shell.counters.get("inserts_lost") == 1
        assert "1 came, not the chain" in caplog.text
    finally:
        server.shell.close(flush_s=0.0)


def tracker_map(seqs: list[int]) -> OccupancyGrid:
    """The map a tracker holds after inserting `insert(seq, at x = 0.1 seq)` for `seqs`."""
    robot = new_robot()
    for seq in seqs:
        robot.insert(insert(seq, Pose2D(0.1 * seq, 0.0, 0.0)))
    return robot.map.grid


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


def test_a_matchers_whole_map_stands_in_for_the_inserts_it_no_longer_keeps(tmp_path, caplog):
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
        (b"\x93not a message", "not valid msgpack"),
    ],
    ids=["short", "another robot", "broken map", "junk"],
)
def test_a_map_state_that_does_not_fit_is_a_loss_named_not_taken(
    tmp_path, caplog, answer: bytes, reason: str
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


def test_a_taken_path_keeps_the_poses_before_a_restarted_trackers_first() -> None:
    """A matcher resumed mid-run holds the path since its restart only: the map server keeps
    its own poses from before that."""
    robot = new_robot()
    for seq in range(5):
        robot.apply(pose(seq, Pose2D(9.0, 0.0, 0.0)))
    path = np.ones((3, 3))
    state = MapStateMessage("r", 4, 3, b"", 0.1 * np.arange(2, 5), path)
    robot.take_state(state, tracker_map([3]), after=1)
    np.testing.assert_array_equal(robot.trajectory.stamps_s, 0.1 * np.arange(5))
    np.testing.assert_array_equal(robot.trajectory.poses[:2], [[9.0, 0.0, 0.0]] * 2)
    np.testing.assert_array_equal(robot.trajectory.poses[2:], path)
    assert [robot.holds(insert(seq)) for seq in range(1, 5)] == [False, True, True, False]
    assert not robot.holds(pose(3))  # poses: the path's seq says
    robot.apply(pose(4))  # the path holds scan 4 already
    robot.apply(pose(5))
    assert len(robot.trajectory) == 6 and robot.trajectory.stamps_s[-1] == 0.5


def test_a_whole_map_with_keyframes_replaces_the_kept_ones_and_holds_redraws_before_it(
    tmp_path,
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
