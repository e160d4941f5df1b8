"""Trajectories: the seeded tours within their limits, and exact piecewise-arc poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scanflow.sim import WORLDS, get_world, tour_trajectory


@pytest.mark.parametrize("name", sorted(WORLDS))
def test_tour_is_collision_free_and_within_limits(name):
    world = get_world(name)
    trajectory = tour_trajectory(world, 40.0, seed=3, max_speed_mps=1.5, max_yaw_rate_dps=180)
    xy = trajectory.knot_poses[:, None, :2]
    a, b = world.segments[:, :2], world.segments[:, 2:]
    ab = b - a
    u = np.clip(((xy - a) * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    clearance = np.linalg.norm(xy - (a + u[..., None] * ab), axis=-1).min()
    assert clearance > 0.2
    speed, yaw_rate = trajectory.twists[:, 0], trajectory.twists[:, 2]
    assert speed.max() <= 1.5 + 1e-9 and speed.min() >= 0.0
    assert np.abs(yaw_rate).max() <= math.radians(180) + 1e-9
    assert speed.max() > 1.0  # it really moves at speed somewhere
    accel = np.abs(np.diff(speed)) / trajectory.step_s
    assert accel.max() <= 1.0 + 1e-6


def test_piecewise_pose_at_is_exact_at_knots_and_continuous():
    trajectory = tour_trajectory(get_world("rooms"), 5.0, seed=0, max_speed_mps=1.5)
    knots = np.arange(trajectory.knot_poses.shape[0]) * trajectory.step_s
    np.testing.assert_allclose(trajectory.pose_at(knots), trajectory.knot_poses, atol=1e-9)
    just_before = trajectory.pose_at(knots[1:] - 1e-9)
    np.testing.assert_allclose(just_before[:, :2], trajectory.knot_poses[1:, :2], atol=1e-8)

