"""Map server pieces without a network: insertion, trajectory, snapshots, shards."""

from __future__ import annotations

import numpy as np
from scanflow.geometry import Pose2D
from scanflow.maps.export import load_npz, save_npz
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.wire import MapInsertMessage, PoseEstimateMessage

from services.mapserver.robot import RobotMap
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
    np.testing.assert_array_equal(again.map.grid.log_odds, robot.map.grid.log_odds)
    np.testing.assert_array_equal(again.trajectory.poses, robot.trajectory.poses)
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind


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


def test_shards_split_robots_and_a_robot_list_wins():
    robots = [f"robot{i}" for i in range(40)]
    first = {r for r in robots if owns(r, "0/2", [])}
    second = {r for r in robots if owns(r, "1/2", [])}
    assert first | second == set(robots) and not first & second and first and second
    assert owns("x", "1/2", ["x"]) and not owns("y", "0/1", ["x"])
