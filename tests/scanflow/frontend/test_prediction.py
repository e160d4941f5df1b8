"""Prediction: odometry increments, jumps, and the constant-velocity and hold fallbacks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scanflow.frontend import MotionPredictor, PredictionSource, compose_odometry_increment
from scanflow.geometry import Pose2D

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
