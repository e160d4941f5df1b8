"""Poses along a closed-form arc, shared by the deskew buffer and velocity-model tests."""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
from scanflow.geometry import Pose2D, se2_exp


def _circle_pose(t: float) -> Pose2D:
    return Pose2D(*se2_exp([[1.0 * t, 0.0, math.pi * t]])[0])


@pytest.fixture
def circle_pose() -> Callable[[float], Pose2D]:
    """The pose at time t on an arc at 1 m/s turning pi rad/s, starting at the origin."""
    return _circle_pose
