"""Simulated wheel odometry: exact without errors, scaled arcs, and a yaw bias that random-walks."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scanflow.geometry import Pose2D
from scanflow.sim import ConstantVelocityTrajectory, get_world, odometry_poses, tour_trajectory


def _wrapped(angles: np.ndarray) -> np.ndarray:
    return (np.asarray(angles) + math.pi) % (2 * math.pi) - math.pi


def test_without_errors_odometry_is_the_true_tour() -> None:
    tour = tour_trajectory(get_world("loop"), 20.0, seed=4)
    stamps = np.arange(0.0, 20.0, 0.02)
    odometry = odometry_poses(tour, stamps, np.random.default_rng(0))
    truth = tour.pose_at(stamps)
    np.testing.assert_allclose(odometry[:, :2], truth[:, :2], atol=1e-9)
    np.testing.assert_allclose(_wrapped(odometry[:, 2] - truth[:, 2]), 0.0, atol=1e-9)


def test_one_stamp_or_none_gives_the_truth_there() -> None:
    line = ConstantVelocityTrajectory(Pose2D(1.0, 2.0, 0.5), 1.0, 0.2)
    one = odometry_poses(line, np.array([3.0]), np.random.default_rng(0), 0.1, 0.1)
    np.testing.assert_allclose(one, line.pose_at(3.0))
    assert odometry_poses(line, np.zeros(0), np.random.default_rng(0)).shape == (0, 3)


@settings(max_examples=40, deadline=None)
@given(
    v=st.floats(0.0, 2.0),
    w=st.floats(-2.0, 2.0).filter(lambda w: w == 0.0 or abs(w) > 1e-3),
    scale_error=st.floats(-0.2, 0.2),
    theta=st.floats(-math.pi, math.pi),
)
def test_a_scale_error_turns_an_arc_into_the_arc_of_a_scaled_speed(
    arc_pose: Callable[..., NDArray[np.float64]],
    v: float,
    w: float,
    scale_error: float,
    theta: float,
) -> None:
    """Constant (v, w) measured with every translation scaled by (1 + e) is constant
    ((1 + e) v, w): the same turn on a circle of (1 + e) times the radius."""
    start = Pose2D(0.5, -1.0, theta)
    stamps = np.linspace(2.0, 6.0, 101)
    odometry = odometry_poses(
        ConstantVelocityTrajectory(start, v, w), stamps, np.random.default_rng(1), scale_error
    )
    # Starting from the truth at stamps[0], on the arc of the scaled speed.
    first = Pose2D.from_array(ConstantVelocityTrajectory(start, v, w).pose_at(stamps[0])[0])
    want = arc_pose(first, (1.0 + scale_error) * v, w, stamps - stamps[0])
    np.testing.assert_allclose(odometry[:, :2], want[:, :2], atol=1e-7)
    np.testing.assert_allclose(_wrapped(odometry[:, 2] - want[:, 2]), 0.0, atol=1e-9)


def test_a_scale_error_scales_sideways_motion_too() -> None:
    """A holonomic base sliding sideways (vy only): odometry travels (1 + e) times as far."""
    start = Pose2D(1.0, -2.0, 0.6)
    slide = ConstantVelocityTrajectory(start, 0.0, 0.0, vy_mps=0.8)
    stamps = np.linspace(0.0, 3.0, 61)
    odometry = odometry_poses(slide, stamps, np.random.default_rng(0), 0.1)
    left = np.array([-math.sin(0.6), math.cos(0.6)])
    want = np.array([1.0, -2.0]) + 1.1 * 0.8 * stamps[:, None] * left
    np.testing.assert_allclose(odometry[:, :2], want, atol=1e-9)
    np.testing.assert_allclose(odometry[:, 2], 0.6, atol=1e-12)


def test_headings_are_wrapped_to_minus_pi_pi() -> None:
    spin = ConstantVelocityTrajectory(Pose2D(), 0.0, 3.0)
    odometry = odometry_poses(spin, np.arange(0.0, 10.0, 0.02), np.random.default_rng(0), 0.0, 0.3)
    assert odometry[:, 2].min() >= -math.pi and odometry[:, 2].max() < math.pi
    assert np.ptp(odometry[:, 2]) > 6.0  # it really turned many times


def test_the_yaw_bias_random_walk_grows_the_heading_error_as_t_to_the_3_halves() -> None:
    """A bias b(t) random-walking at sigma per sqrt(s) gives a heading error int_0^T b dt of
    variance sigma^2 T^3 / 3; translation errors follow from the heading alone."""
    sigma, duration_s, dt_s = 0.01, 4.0, 0.02
    straight = ConstantVelocityTrajectory(Pose2D(0.0, 0.0, 0.0), 1.0, 0.0)
    stamps = np.arange(0.0, duration_s + dt_s / 2, dt_s)
    finals = np.array([
        odometry_poses(straight, stamps, np.random.default_rng(seed), 0.0, sigma)[-1, 2]
        for seed in range(600)
    ])
    expected_std = sigma * math.sqrt(duration_s**3 / 3.0)
    assert abs(finals.mean()) < 0.15 * expected_std
    assert finals.std() == pytest.approx(expected_std, rel=0.12)
    same = odometry_poses(straight, stamps, np.random.default_rng(599), 0.0, sigma)[-1, 2]
    assert same == finals[-1]  # the rng decides the walk


def test_positions_follow_the_biased_heading_at_the_true_speed() -> None:
    straight = ConstantVelocityTrajectory(Pose2D(1.0, 1.0, 0.0), 1.0, 0.0)
    stamps = np.arange(0.0, 3.0, 0.01)
    odometry = odometry_poses(straight, stamps, np.random.default_rng(8), 0.0, 0.05)
    steps = np.diff(odometry[:, :2], axis=0)
    np.testing.assert_allclose(np.hypot(*steps.T), 0.01, rtol=1e-3)  # no scale error: 1 m/s
    direction = np.arctan2(steps[:, 1], steps[:, 0])
    mid_heading = odometry[:-1, 2] + 0.5 * _wrapped(np.diff(odometry[:, 2]))
    np.testing.assert_allclose(_wrapped(direction - mid_heading), 0.0, atol=1e-6)
