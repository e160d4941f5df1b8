"""MotionFilter: when a pose has moved or waited enough for its scan to be inserted."""

from __future__ import annotations

import math

import pytest
from scanflow.frontend import MotionFilter
from scanflow.geometry import Pose2D


def test_motion_filter_thresholds() -> None:
    f = MotionFilter(min_distance_m=0.2, min_angle_rad=math.radians(10), max_interval_s=5.0)
    assert f.should_insert(0.0, Pose2D())
    f.mark_inserted(0.0, Pose2D())
    assert not f.should_insert(1.0, Pose2D(0.1, 0.05, math.radians(5)))
    assert f.should_insert(1.0, Pose2D(0.2, 0.0, 0.0))
    assert f.should_insert(1.0, Pose2D(0.0, 0.0, math.radians(-10.5)))
    assert f.should_insert(5.0, Pose2D())
    with pytest.raises(ValueError, match="min_distance_m"):
        MotionFilter(-1.0, 0.1, 1.0)
