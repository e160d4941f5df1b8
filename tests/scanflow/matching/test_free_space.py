import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.matching.free_space import free_space_test


def test_a_scan_against_itself_has_no_conflict(room, caster) -> None:
    scan = caster(room, Pose2D(0.5, -0.5, 0.2))
    test = free_space_test(scan, scan, 0.2)
    assert test.tested > 0.9 * len(scan) and test.conflicts == 0 and test.share == 0.0


def test_points_pulled_towards_the_sensor_conflict(room, caster) -> None:
    scan = caster(room, Pose2D(0.5, -0.5, 0.2))
    test = free_space_test(0.8 * scan, scan, 0.2)  # every point >= 0.2 m nearer (ranges > 1 m)
    assert test.tested > 0.9 * len(scan) and test.share > 0.99


def test_points_behind_the_surface_or_within_the_margin_do_not_conflict(room, caster) -> None:
    scan = caster(room, Pose2D(0.5, -0.5, 0.2))
    unit = scan / np.linalg.norm(scan, axis=1, keepdims=True)
    assert free_space_test(scan + 0.5 * unit, scan, 0.2).conflicts == 0
    assert free_space_test(scan - 0.15 * unit, scan, 0.2).conflicts == 0


def test_bearings_without_target_returns_are_not_tested(room, caster) -> None:
    scan = caster(room, Pose2D())
    front = scan[scan[:, 0] > 0.5]  # bearings within +-80 deg
    behind = Pose2D(0.0, 0.0, math.pi).transform_points(front)  # all where the target is blind
    assert free_space_test(0.5 * behind, front, 0.2).tested == 0


def test_a_negative_margin_is_refused() -> None:
    with pytest.raises(ValueError, match=r"margin_m must be >= 0, got -0\.1"):
        free_space_test(np.zeros((3, 2)), np.ones((3, 2)), -0.1)
