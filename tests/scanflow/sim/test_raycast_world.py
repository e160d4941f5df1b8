import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.sim import WORLDS, cast_rays, get_world, static_scan, tour_trajectory


def _square(half_m: float) -> np.ndarray:
    h = half_m
    return np.array([(-h, -h, h, -h), (h, -h, h, h), (h, h, -h, h), (-h, h, -h, -h)], float)


def test_rays_from_centre_of_square_room_hit_at_exact_distances():
    angles = np.linspace(-math.pi, math.pi, 721)
    distance = cast_rays(np.zeros((angles.size, 2)), angles, _square(2.0), 30.0)
    expected = 2.0 / np.maximum(np.abs(np.cos(angles)), np.abs(np.sin(angles)))
    np.testing.assert_allclose(distance, expected, rtol=1e-12)


def test_a_static_scan_is_in_the_sensors_frame_with_misses_left_out():
    pose = Pose2D(0.5, -0.5, 0.7)  # in a 4 m square, walls 1.5 m ahead and 2.5 m behind in x
    angles = np.radians(np.arange(0.0, 360.0, 1.0))
    points = static_scan(_square(2.0), pose, angles, 30.0)
    world = pose.transform_points(points)
    on_wall = np.isclose(np.abs(world).max(axis=1), 2.0, atol=1e-9)
    assert points.shape == (360, 2) and on_wall.all()
    assert len(static_scan(_square(2.0), pose, angles, 1.6)) < 360  # beyond range: left out
    noisy = static_scan(_square(2.0), pose, angles, 30.0, 0.01, np.random.default_rng(1))
    spread = np.linalg.norm(noisy, axis=1) - np.linalg.norm(points, axis=1)
    assert 0.005 < spread.std() < 0.015


def test_off_centre_ray_and_range_limit():
    origins = np.array([[1.0, 0.5], [1.0, 0.5], [0.0, 0.0]])
    angles = np.array([0.0, math.pi, 0.0])
    distance = cast_rays(origins, angles, _square(2.0), range_max_m=1.5)
    assert distance[0] == pytest.approx(1.0)
    assert np.isinf(distance[1])  # the wall 3 m away is beyond range_max_m
    assert np.isinf(distance[2])  # 2 m to the wall, range_max_m is 1.5


def test_unknown_world_names_the_choices():
    with pytest.raises(ValueError, match="world must be one of"):
        get_world("moon")


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
