"""ConstantVelocityModel: arcs predicted from the twist between the last two poses."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from scanflow.deskew import ConstantVelocityModel, DeskewError
from scanflow.geometry import Pose2D, se2_exp, se2_log


def test_se2_log_inverts_exp_including_small_angles():
    twists = np.array([[1.0, 0.2, 0.5], [0.3, -0.1, 1e-9], [0.0, 0.0, -3.0], [2.0, 0.0, 0.0]])
    np.testing.assert_allclose(se2_log(se2_exp(twists)), twists, atol=1e-12)


def test_constant_velocity_model_predicts_arcs_exactly(
    circle_pose: Callable[[float], Pose2D],
):
    model = ConstantVelocityModel()
    assert "has 0" in model.coverage_gap(0.0, 0.1)
    model.update(0.0, circle_pose(0.0))
    assert "has 1" in model.coverage_gap(0.0, 0.1)
    model.update(0.1, circle_pose(0.1))
    np.testing.assert_allclose(model.twist, [1.0, 0.0, math.pi], atol=1e-12)
    times = np.linspace(0.1, 0.2, 11)
    predicted = np.column_stack(model.poses_at(times))
    truth = np.array([circle_pose(t).to_array() for t in times])
    np.testing.assert_allclose(predicted, truth, atol=1e-12)
    assert "max_horizon_s" in model.coverage_gap(0.1, 0.9)


def test_constant_velocity_model_resets_when_time_goes_backwards():
    model = ConstantVelocityModel()
    model.update(1.0, Pose2D())
    model.update(1.1, Pose2D(0.1, 0.0, 0.0))
    model.update(0.5, Pose2D())
    gap = model.coverage_gap(0.5, 0.6)
    assert "time went backwards" in gap
    model.update(0.6, Pose2D(0.1, 0.0, 0.0))
    assert model.coverage_gap(0.6, 0.7) is None


def test_constant_velocity_model_skips_a_pose_too_close_in_time():
    """Two estimates a microsecond and 5 cm apart are not 50 km/s of motion."""
    model = ConstantVelocityModel()
    model.update(1.0, Pose2D())
    model.update(1.1, Pose2D(0.1, 0.0, 0.0))
    model.update(1.100001, Pose2D(0.15, 0.0, 0.0))
    np.testing.assert_allclose(model.twist, [1.0, 0.0, 0.0], atol=1e-9)
    model.update(1.2, Pose2D(0.25, 0.0, 0.0))  # the baseline is the last kept pose, 1.1 s
    np.testing.assert_allclose(model.twist, [1.5, 0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize(("step", "named"), [(Pose2D(6.0, 0.0, 0.0), "60 m/s"),
                                            (Pose2D(0.0, 0.0, 1.5), "15 rad/s")])
def test_constant_velocity_model_refuses_an_implausible_twist(step, named):
    model = ConstantVelocityModel()
    model.update(0.0, Pose2D())
    model.update(0.1, step)
    assert model.twist is None
    assert named in model.coverage_gap(0.1, 0.2)
    with pytest.raises(DeskewError, match="max_speed_mps"):
        model.poses_at([0.15])
    model.update(0.2, step * Pose2D(0.1, 0.0, 0.0))  # plausible again: predicts again
    assert model.coverage_gap(0.2, 0.25) is None


def test_constant_velocity_model_settings_are_checked():
    for bad in ({"min_interval_s": 0.0}, {"max_speed_mps": math.nan},
                {"max_turn_rate_rads": -1.0}):
        with pytest.raises(DeskewError, match=next(iter(bad))):
            ConstantVelocityModel(**bad)


def test_poses_at_no_time_is_empty_and_a_non_finite_time_is_refused() -> None:
    """As the odometry buffer: no times, no poses; a NaN time is named, not predicted."""
    model = ConstantVelocityModel()
    model.update(0.0, Pose2D(0.0, 0.0, 0.0))
    model.update(0.1, Pose2D(0.1, 0.0, 0.01))
    x, y, theta = model.poses_at([])
    assert x.shape == y.shape == theta.shape == (0,)
    for bad in (math.nan, math.inf):
        with pytest.raises(DeskewError, match="times_s must be finite"):
            model.poses_at([0.12, bad])
