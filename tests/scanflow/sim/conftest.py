"""Closed-form motion on an arc, the independent truth the simulator tests compare against."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.geometry import Pose2D

ArcPose = Callable[[Pose2D, float, float, NDArray[np.float64]], NDArray[np.float64]]


def arc_poses(start: Pose2D, v: float, w: float, t: NDArray[np.float64]) -> NDArray[np.float64]:
    """Poses (N, 3) after t seconds from `start` at forward speed v and turn rate w (headings
    not wrapped): a circle of radius v / w, or a line when w is 0."""
    t = np.asarray(t, dtype=np.float64)
    th = start.theta + w * t
    if w == 0.0:
        return np.column_stack((start.x + v * t * math.cos(start.theta),
                                start.y + v * t * math.sin(start.theta), th))
    r = v / w
    return np.column_stack((start.x + r * (np.sin(th) - math.sin(start.theta)),
                            start.y - r * (np.cos(th) - math.cos(start.theta)), th))


@pytest.fixture(scope="session")
def arc_pose() -> ArcPose:
    return arc_poses
