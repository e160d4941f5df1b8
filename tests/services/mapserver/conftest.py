"""Map server test helpers, as fixtures: a robot's map, and the messages a tracker sends it."""

from __future__ import annotations

from collections.abc import Callable

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


def _exposed(helper: Callable[..., object]) -> Callable[[], Callable[..., object]]:
    """A fixture named after `helper` that hands the tests of this folder the helper itself."""

    def fixture() -> Callable[..., object]:
        return helper

    fixture.__doc__ = f"`{helper.__name__}` (above), for the tests of this folder."
    return pytest.fixture(name=helper.__name__)(fixture)


# pytest finds fixtures among a conftest's module attributes: one per helper above.
for _helper in (new_robot, insert, pose, redraw, kept_robot, tracker_map):
    globals()[f"{_helper.__name__}_fixture"] = _exposed(_helper)
