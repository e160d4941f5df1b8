"""Map server test helpers, as fixtures: a robot's map, and the messages a tracker sends it."""

from __future__ import annotations

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.wire import MapInsertMessage, MapRedrawMessage, PoseEstimateMessage

from services.mapserver.robot import RobotMap


def new_robot(snap=None, params: OccupancyParams | None = None) -> RobotMap:
    return RobotMap("r", lambda: OccupancyGrid(params or OccupancyParams()), snap)


def insert(seq: int, at: Pose2D | None = None) -> MapInsertMessage:
    pts = np.array([[2.0, 0.0], [2.0, 1.0], [1.5, -1.0]])
    return MapInsertMessage("r", seq, 0.1 * seq, at or Pose2D(), pts, np.zeros((0, 2)))


def pose(seq: int, at: Pose2D | None = None) -> PoseEstimateMessage:
    at = at or Pose2D()
    return PoseEstimateMessage("r", seq, 0.1 * seq, at, np.eye(3), "tracked", "gn", 1, 1.0)


def redraw(seqs: list[int], poses: list[Pose2D], path: np.ndarray, seq: int) -> MapRedrawMessage:
    return MapRedrawMessage(
        "r", seq, Pose2D(0.1, 0.0, 0.02), np.array(seqs, dtype=np.int64),
        np.array([p.to_array() for p in poses]).reshape(-1, 3),
        0.1 * np.arange(len(path)), path,
    )


def kept_robot(seqs: range) -> RobotMap:
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    for seq in seqs:
        robot.insert(MapInsertMessage(
            "r", seq, 0.1 * seq, Pose2D(0.1 * seq, 0.0, 0.0), np.full((2, 2), 1.0 + seq),
            np.full((1, 2), 5.0 + seq), Pose2D(0.2, 0.0, 0.01 * seq),
        ))
    robot.apply(pose(seqs[-1]))
    return robot


def tracker_map(seqs: list[int]) -> OccupancyGrid:
    """The map a tracker holds after inserting `insert(seq, at x = 0.1 seq)` for `seqs`."""
    robot = new_robot()
    for seq in seqs:
        robot.insert(insert(seq, Pose2D(0.1 * seq, 0.0, 0.0)))
    return robot.map.grid


@pytest.fixture(name="new_robot")
def new_robot_fixture():
    """`new_robot` (above), for the tests of this folder."""
    return new_robot


@pytest.fixture(name="insert")
def insert_fixture():
    """`insert` (above), for the tests of this folder."""
    return insert


@pytest.fixture(name="pose")
def pose_fixture():
    """`pose` (above), for the tests of this folder."""
    return pose


@pytest.fixture(name="redraw")
def redraw_fixture():
    """`redraw` (above), for the tests of this folder."""
    return redraw


@pytest.fixture(name="kept_robot")
def kept_robot_fixture():
    """`kept_robot` (above), for the tests of this folder."""
    return kept_robot


@pytest.fixture(name="tracker_map")
def tracker_map_fixture():
    """`tracker_map` (above), for the tests of this folder."""
    return tracker_map
