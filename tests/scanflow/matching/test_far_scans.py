"""Outdoor scans: the `campus` world seen by a 181-beam, 180-deg lidar reaching 80 m. Its walls
are 15-70 m away, so neighbouring returns lie 0.3-1.4 m apart, further than any radius tuned on
indoor scans; every matcher must still use them (`scanflow.matching.surface`)."""

import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.matching import match
from scanflow.sim import get_world, static_scan

ANGLES = np.radians(np.arange(-90.0, 90.5, 1.0))
RANGE_M = 80.0
# Stops on the lawn, each with the next scan's motion from it (0.5-1 m, a few degrees).
STOPS = [
    (Pose2D(20.0, 10.0, 0.1), Pose2D(0.8, 0.05, math.radians(4.0))),
    (Pose2D(60.0, 12.0, 1.4), Pose2D(0.6, -0.03, math.radians(-6.0))),
    (Pose2D(84.0, 40.0, 2.9), Pose2D(1.0, 0.0, math.radians(2.0))),
    (Pose2D(40.0, 54.0, -2.0), Pose2D(0.5, 0.1, math.radians(8.0))),
]
GUESS_ERROR = Pose2D(0.04, -0.03, math.radians(1.0))


def campus_scan(pose: Pose2D, seed: int) -> np.ndarray:
    segments = get_world("campus").segments
    return static_scan(segments, pose, ANGLES, RANGE_M, 0.01, np.random.default_rng(seed))


@pytest.mark.parametrize("method", ["icp", "plicp", "gn", "lm", "ndt", "csm", "csm+plicp"])
@pytest.mark.parametrize("stop", range(len(STOPS)))
def test_far_sparse_scans_are_matched(method: str, stop: int) -> None:
    base, motion = STOPS[stop]
    target = campus_scan(base, 2 * stop)
    source = campus_scan(base * motion, 2 * stop + 1)
    assert np.median(np.hypot(*target.T)) > 20.0  # mostly far returns: the case at hand
    r = match(source, target, motion * GUESS_ERROR, method=method)
    err = r.pose.relative_to(motion)
    assert r.ok, f"{r.status}: {r.message}"
    assert err.translation_norm() < 0.05 and abs(err.theta) < math.radians(0.2)


@pytest.mark.parametrize("method", ["gn", "lm", "gn+plicp", "icp", "plicp", "ndt"])
@pytest.mark.parametrize("far", [[3000.0], [300.0] * 20])
def test_far_returns_off_the_map_do_not_freeze_the_heading(method: str, far: list[float]) -> None:
    """A room scan with one return 3 km away (or 20 at 300 m, a bright target outdoors): the
    rotation's scale came from all the points, about 100 m, so gn and lm found every rotation
    unconstrained, never turned from the guess's 0.1 rad and said ok (a fuzzing audit). Scaled
    by the points on the field, they turn: every method ends where it does without them."""
    from scanflow.frontend import insert_scan
    from scanflow.maps.matching_map import MatchingMap
    from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams

    rng = np.random.default_rng(3)
    segments = get_world("rooms").segments
    angles = np.radians(np.arange(0.0, 360.0, 1.0))
    at = Pose2D(7.0, 2.6, 0.4)
    target = MatchingMap(OccupancyGrid(OccupancyParams(resolution_m=0.05)))
    insert_scan(target, static_scan(segments, at, angles, 12.0, 0.005, rng), Pose2D())
    room = static_scan(segments, at, angles, 12.0, 0.005, rng)
    bearings = np.linspace(-0.3, 0.3, len(far))
    source = np.vstack((room, np.column_stack((far * np.cos(bearings), far * np.sin(bearings)))))
    guess = Pose2D(0.05, -0.03, 0.1)
    clean, r = (match(points, target, guess, method=method) for points in (room, source))
    assert r.ok, f"{r.status}: {r.message}"
    moved = r.pose.relative_to(clean.pose)
    assert moved.translation_norm() < 0.005 and abs(moved.theta) < math.radians(0.05), r.pose
    if method != "icp":  # (point-to-point against one scan's cell means: 0.9 deg off here)
        assert r.pose.translation_norm() < 0.03 and abs(r.pose.theta) < math.radians(0.5)
