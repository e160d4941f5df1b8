"""Prediction (odometry increments), motion filter, acceptance checks, TUM trajectory export."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scanflow.frontend import (
    AcceptanceLimits,
    MotionFilter,
    MotionPredictor,
    PredictionSource,
    TrajectoryStore,
    compose_odometry_increment,
    insert_scan,
    load_tum,
    rejection_reason,
    tum_text,
)
from scanflow.geometry import Pose2D
from scanflow.maps.grid import CellBox
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.matching import MatchResult, MatchStatus

coord = st.floats(-50.0, 50.0, allow_nan=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False, exclude_max=True)
poses = st.builds(Pose2D, coord, coord, angle)


def close(a: Pose2D, b: Pose2D, tol: float = 1e-7) -> bool:
    e = a.relative_to(b)
    return e.translation_norm() < tol and abs(e.theta) < tol


@given(poses, poses, poses)
def test_increment_matches_the_seed_formula_in_matrices(map_prev: Pose2D, odom_prev: Pose2D,
                                                        odom_now: Pose2D) -> None:
    expected = map_prev.to_matrix() @ np.linalg.inv(odom_prev.to_matrix()) @ odom_now.to_matrix()
    got = compose_odometry_increment(map_prev, odom_prev, odom_now)
    assert close(got, Pose2D.from_matrix(expected), 1e-6)


@given(poses, poses, poses)
def test_increment_removes_any_fixed_offset_between_frames(offset: Pose2D, odom_prev: Pose2D,
                                                           odom_now: Pose2D) -> None:
    """If map = offset * odom, the prediction is exactly offset * odom_now."""
    got = compose_odometry_increment(offset * odom_prev, odom_prev, odom_now)
    assert close(got, offset * odom_now, 1e-6)


def test_predictor_sources_and_jumps() -> None:
    p = MotionPredictor(max_odom_step_m=1.0, max_odom_step_rad=math.radians(45), cv_horizon_s=1.0)
    assert p.predict(0.0, None).source is PredictionSource.INITIAL
    p.update(0.0, Pose2D(1.0, 0.0, 0.0), Pose2D(10.0, 0.0, math.pi / 2))
    odo = p.predict(0.1, Pose2D(10.0, 0.5, math.pi / 2))  # 0.5 m forward in odometry
    assert odo.source is PredictionSource.ODOMETRY and close(odo.pose, Pose2D(1.5, 0.0, 0.0))
    jumped = p.predict(0.1, Pose2D(30.0, 0.0, 0.0))
    assert jumped.source is PredictionSource.HOLD and "odometry jumped" in jumped.message
    p.update(0.1, Pose2D(1.2, 0.0, 0.0), None)
    cv = p.predict(0.2, None)  # no odometry: the velocity of the last two estimates
    assert cv.source is PredictionSource.CONSTANT_VELOCITY
    assert close(cv.pose, Pose2D(1.4, 0.0, 0.0), 1e-9)
    # The scan without odometry left the chain at the first: 0.9 m forward since then.
    bridged = p.predict(0.2, Pose2D(10.0, 0.9, math.pi / 2))
    assert bridged.source is PredictionSource.ODOMETRY
    assert close(bridged.pose, Pose2D(1.9, 0.0, 0.0), 1e-9)
    far = p.predict(5.0, None)
    assert far.source is PredictionSource.HOLD and close(far.pose, Pose2D(1.2, 0.0, 0.0))
    p.restart(5.0, Pose2D(7.0, 7.0, 0.0), None)  # a whole-map search: the chain is gone
    assert p.predict(5.1, Pose2D(10.0, 1.0, math.pi / 2)).source is not PredictionSource.ODOMETRY


def test_after_a_longer_gap_the_odometry_still_predicts() -> None:
    """A restarted service or a stalled link: 5 s and 5 m of odometry since the last scan is
    motion at 1 m/s, not a jump (an audit saw it dropped, the robot held, and then tracked
    metres off); the same step within 0.1 s, or beyond max_odom_speed_mps, still is one."""
    p = MotionPredictor(3.0, math.radians(120), 1.0, max_odom_speed_mps=5.0,
                        max_odom_turn_rate_rads=math.pi)
    p.update(0.0, Pose2D(1.0, 0.0, 0.0), Pose2D(10.0, 0.0, 0.0))
    bridged = p.predict(5.0, Pose2D(15.0, 0.0, 2.5))  # 5 m and 143 deg in 5 s
    assert bridged.source is PredictionSource.ODOMETRY
    assert close(bridged.pose, Pose2D(6.0, 0.0, 2.5))
    assert p.predict(0.1, Pose2D(15.0, 0.0, 0.0)).source is PredictionSource.HOLD
    glitch = p.predict(5.0, Pose2D(40.0, 0.0, 0.0))  # 30 m in 5 s
    assert glitch.source is PredictionSource.HOLD
    assert "30.00 m / 0.0 deg in 5.00 s" in glitch.message


def test_predictor_rejects_bad_limits() -> None:
    with pytest.raises(ValueError, match="max_odom_step_m"):
        MotionPredictor(0.0, 1.0, 1.0)


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


LIMITS = AcceptanceLimits(
    max_correction_m=0.5, max_correction_rad=math.radians(10), min_score=0.3,
    max_position_std_m=0.2, max_heading_std_rad=math.radians(5), accept_degenerate=True,
)


IDENTITY = Pose2D()


def result(pose: Pose2D = IDENTITY, status: MatchStatus = MatchStatus.OK, score: float = 0.9,
           std_m: float = 0.01) -> MatchResult:
    cov = np.diag([std_m**2, std_m**2, 1e-6])
    return MatchResult(pose, cov, score, 5, status is MatchStatus.OK, status, "gn", "why")


@pytest.mark.parametrize(
    ("res", "needle"),
    [
        (result(), ""),
        (result(status=MatchStatus.DIVERGED), "failed (diverged): why"),
        (result(score=0.1), "score"),
        (result(Pose2D(0.6, 0.0, 0.0)), "max_correction_m"),
        (result(Pose2D(0.0, 0.0, math.radians(11))), "max_correction"),
        (result(std_m=0.3), "position std"),
        (result(status=MatchStatus.DEGENERATE, std_m=50.0), ""),
    ],
)
def test_rejection_reasons(res: MatchResult, needle: str) -> None:
    reason = rejection_reason(res, Pose2D(), LIMITS)
    assert (needle in reason) if needle else reason == ""


def test_degenerate_can_be_refused() -> None:
    strict = AcceptanceLimits(0.5, 0.2, 0.3, 0.2, 0.1, accept_degenerate=False)
    assert "degenerate" in rejection_reason(result(status=MatchStatus.DEGENERATE), Pose2D(), strict)


def test_trajectory_store_grows_and_round_trips_tum(tmp_path: Path) -> None:
    store = TrajectoryStore()
    rng = np.random.default_rng(0)
    rows = rng.uniform(-3, 3, size=(600, 3))
    for i, (x, y, th) in enumerate(rows):
        store.append(1.7e9 + 0.1 * i, Pose2D(x, y, th))
    assert len(store) == 600 and store.poses.shape == (600, 3)
    stamps, loaded = load_tum(store.save_tum(tmp_path / "traj.tum"))
    np.testing.assert_allclose(stamps, store.stamps_s, atol=1e-6)
    np.testing.assert_allclose(loaded[:, :2], rows[:, :2], atol=1e-7)
    np.testing.assert_allclose(np.cos(loaded[:, 2] - store.poses[:, 2]), 1.0, atol=1e-12)


@given(angle)
def test_tum_quaternion_is_a_yaw_rotation(theta: float) -> None:
    fields = [float(v) for v in tum_text(np.array([0.0]), np.array([[1.0, 2.0, theta]])).split()]
    assert fields[3:6] == [0.0, 0.0, 0.0]
    assert math.isclose(fields[6] ** 2 + fields[7] ** 2, 1.0, rel_tol=1e-7)
    assert math.isclose(math.cos(2 * math.atan2(fields[6], fields[7]) - theta), 1.0, abs_tol=1e-9)


def test_tum_shape_error_names_the_field() -> None:
    with pytest.raises(ValueError, match="poses must have shape"):
        tum_text(np.zeros(2), np.zeros((3, 3)))


def test_insert_scan_keeps_points_within_max_range_seen_from_the_pose() -> None:
    pose = Pose2D(1.0, -2.0, math.pi / 2)
    near, far = np.array([[3.0, 0.0]]), np.array([[30.0, 0.0]])
    with_far = MatchingMap(OccupancyGrid(OccupancyParams(max_range_m=10.0)))
    result = insert_scan(with_far, np.vstack([near, far]), pose)
    alone = MatchingMap(OccupancyGrid(OccupancyParams(max_range_m=10.0)))
    insert_scan(alone, near, pose)
    np.testing.assert_array_equal(with_far.grid.log_odds, alone.grid.log_odds)  # far: no ray
    sensor, hit = with_far.grid.world_to_cells(np.array([[1.0, -2.0], [1.0, 1.0]]))
    assert result.touched == CellBox.around(np.array([sensor, hit]))  # the ray, in the map frame
