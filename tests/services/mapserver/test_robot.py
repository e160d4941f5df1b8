"""A robot's map in the map server: inserts, poses, resets, redraws and taken states."""

from __future__ import annotations

import io
from dataclasses import replace

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.maps.export import grid_from_npz
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.wire import MapStateMessage

from services.mapserver import replies
from services.mapserver.robot import MAX_HELD_POSES, RobotMap
from services.mapserver.snapshot import load_snapshots, save_snapshot


def test_robot_map_inserts_at_the_insert_pose_and_notices_the_change(new_robot, insert, pose):
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


def test_robot_map_uses_the_given_params_and_a_reset_keeps_them(new_robot, insert, pose):
    robot = new_robot(params=OccupancyParams(resolution_m=0.1))
    robot.insert(insert(0))
    robot.apply(pose(0))
    robot.reset()
    assert robot.map.grid.resolution_m == 0.1 and robot.map.revision == 0


def test_a_reset_returns_to_the_starting_map_a_prior_one_included(new_robot, insert, pose):
    prior = new_robot()
    prior.insert(insert(0, Pose2D(1.0, 2.0, 0.3)))
    robot = RobotMap("r", lambda: prior.map.grid)
    assert robot.map.revision == prior.map.revision == 1
    robot.insert(insert(1))
    robot.apply(pose(1))
    robot.reset()
    assert robot.map.grid is prior.map.grid and robot.last_seq == -1


def test_the_odometry_pose_of_the_paths_end_is_kept_resumed_and_reset(
    tmp_path, new_robot, insert, pose
):
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


def test_a_redraw_redraws_the_kept_keyframes_at_their_new_poses_and_takes_the_path(
    new_robot, insert, pose, redraw
):
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


def test_a_redraw_that_does_not_fit_is_refused_and_changes_nothing(new_robot, insert, redraw):
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


def test_poses_of_later_scans_that_came_before_the_redraw_are_kept(insert, pose, redraw):
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


def test_culled_inserts_go_into_the_map_but_not_into_the_kept_keyframes(new_robot, insert, redraw):
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


def test_a_taken_path_keeps_the_poses_before_a_restarted_trackers_first(
    new_robot, insert, pose, tracker_map
) -> None:
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


def test_a_map_resumed_without_its_keyframes_gives_no_keyframes_to_resume_from(
    tmp_path, insert, pose, redraw, kept_robot
):
    """A snapshot whose keyframes could not be read (a lost chunk): its map holds scans no kept
    keyframe has. Keyframes kept from then on used to go in the resume answer, and the restarted
    matcher's first redraw, of those alone, would wipe the rest of the map (here and there)."""
    save_snapshot(tmp_path, kept_robot(range(5)).snapshot(), 2)
    next((tmp_path / "r.keyframes").iterdir()).unlink()
    (snap,), _ = load_snapshots(tmp_path)
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), snap, keep_keyframes=True)
    robot.insert(replace(insert(5), keyframe=True))
    robot.apply(pose(5))
    assert replies.resume(robot).keyframes is None  # the matcher resumes without loop closure
    with pytest.raises(ValueError, match="keeps no keyframes"):
        robot.redraw(redraw([5], [Pose2D()], np.zeros((1, 3)), 5), OccupancyParams())
    robot.reset()  # a new run starts its map afresh: its keyframes are all of it
    robot.insert(insert(0))
    assert replies.resume(robot).keyframes.seqs.tolist() == [0]


def test_a_new_run_starts_the_map_afresh_with_its_held_poses_and_survives_a_snapshot(
    tmp_path, new_robot, insert, pose
):
    """A run's first insert starts the map afresh for it (the run replaced is ended) and
    hands back the poses of that run held so far; the run and the ended ones go into the
    snapshot and the resume answer (a restarted matcher carries the run on); older snapshots
    without them load as unknown."""
    robot = new_robot()
    assert robot.run == 0 and robot.start_run(7) == [] and robot.run == 7
    robot.insert(insert(0))
    robot.apply(pose(0))
    early, late = replace(pose(5), run=9), replace(pose(40), run=3)
    assert robot.hold(early) and robot.hold(late)
    assert robot.start_run(9) == [early] and robot.run == 9 and robot.ended_runs == [7]
    assert robot.map.revision == 0 and len(robot.trajectory.poses) == 0
    assert list(robot.held_poses) == [late]  # a run never shown by an insert stays held
    for _ in range(MAX_HELD_POSES):
        robot.hold(late)
    assert not robot.hold(late) and len(robot.held_poses) == MAX_HELD_POSES
    robot.insert(insert(1))
    robot.apply(pose(1))
    save_snapshot(tmp_path, robot.snapshot())
    (snap,), _ = load_snapshots(tmp_path)
    again = new_robot(snap)
    assert (again.run, again.ended_runs) == (9, [7]) and replies.resume(again).run == 9
    with np.load(tmp_path / "r.snapshot.npz") as data:
        older = {k: data[k] for k in data.files if k not in ("run", "ended_runs")}
    np.savez(tmp_path / "r.snapshot.npz", **older)
    (snap,), skipped = load_snapshots(tmp_path)
    assert (snap.run, snap.ended_runs) == (0, ()) and skipped == []
