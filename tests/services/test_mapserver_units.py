"""Map server pieces without a network: pairing by seq, insertion, snapshots, shards."""

from __future__ import annotations

import numpy as np
from scanflow.geometry import Pose2D
from scanflow.maps.export import load_npz, save_npz
from scanflow.maps.occupancy import OccupancyParams
from scanflow.wire import DeskewedScanMessage, PoseEstimateMessage

from services.mapserver.pairing import Pairing
from services.mapserver.robot import RobotMap
from services.mapserver.snapshot import load_snapshots, save_snapshot
from services.matcher.shard import owns


def scan(seq: int, points: np.ndarray | None = None) -> DeskewedScanMessage:
    pts = np.array([[2.0, 0.0], [2.0, 1.0], [1.5, -1.0]]) if points is None else points
    return DeskewedScanMessage("r", seq, 0.1 * seq, pts, "none", True, len(pts), 0)


def pose(seq: int, at: Pose2D | None = None) -> PoseEstimateMessage:
    at = at or Pose2D()
    return PoseEstimateMessage("r", seq, 0.1 * seq, at, np.eye(3), "tracked", "gn", 1, 1.0)


def test_pairing_returns_the_inserted_scan_and_counts_the_orphans():
    pairing = Pairing(limit=10)
    for seq in (1, 2, 4):
        pairing.add_scan(scan(seq))
    assert pairing.match_pose(pose(0)) is None  # not inserted: a pose alone is normal
    assert pairing.match_pose(pose(2)).seq == 2
    assert pairing.scans_without_pose == 1  # scan 1 was overtaken by pose 2
    assert pairing.match_pose(pose(4)).seq == 4
    assert not pairing.scans


def test_pairing_is_bounded():
    pairing = Pairing(limit=3)
    for seq in range(5):
        pairing.add_scan(scan(seq))
    assert list(pairing.scans) == [2, 3, 4] and pairing.scans_evicted == 2


def test_robot_map_inserts_a_paired_scan_and_notices_the_change():
    at = Pose2D(0.3, -0.2, 0.4)
    robot = RobotMap("r", pending_limit=10)
    assert not robot.apply(pose(2, at))  # a pose without an inserted scan changes no cell
    assert robot.take_change(0.5) is None and robot.map.revision == 0
    robot.pairing.add_scan(scan(3))
    assert robot.apply(pose(3, at))
    assert robot.map.revision == 1 and robot.state == (1, 3)
    notice = robot.take_change(1.0)
    assert notice.min_x_m < at.x < notice.max_x_m and robot.take_change(2.0) is None


def test_robot_map_uses_the_given_params_and_a_reset_keeps_them():
    robot = RobotMap("r", pending_limit=10, params=OccupancyParams(resolution_m=0.1))
    robot.pairing.add_scan(scan(0))
    robot.apply(pose(0))
    robot.reset()
    assert robot.map.grid.resolution_m == 0.1 and robot.map.revision == 0


def test_snapshot_round_trip(tmp_path):
    robot = RobotMap("r", pending_limit=10)
    for seq in range(3):
        robot.pairing.add_scan(scan(seq))
        robot.apply(pose(seq, Pose2D(0.1 * seq, 0.0, 0.0)))
    save_snapshot(tmp_path, robot.snapshot())
    (snap,), skipped = load_snapshots(tmp_path)
    again = RobotMap("r", 10, snap)
    assert again.last_seq == 2 and again.state == robot.state and skipped == []
    np.testing.assert_array_equal(again.map.grid.log_odds, robot.map.grid.log_odds)
    np.testing.assert_array_equal(again.trajectory.poses, robot.trajectory.poses)
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind


def test_a_snapshot_is_one_file_that_loads_as_a_map(tmp_path):
    robot = RobotMap("r", pending_limit=10)
    robot.pairing.add_scan(scan(0))
    robot.apply(pose(0))
    save_snapshot(tmp_path, robot.snapshot())
    (path,) = tmp_path.iterdir()  # map and trajectory together: no crash can split them
    assert path.name == "r.snapshot.npz"
    np.testing.assert_array_equal(load_npz(path).log_odds, robot.map.grid.log_odds)


def test_an_unreadable_snapshot_is_skipped_and_named_not_a_crash(tmp_path):
    robot = RobotMap("r", pending_limit=10)
    robot.pairing.add_scan(scan(0))
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
