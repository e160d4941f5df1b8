"""Ray casting against wall segments, and static scans in the sensor's frame."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.sim import cast_rays, static_scan


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


def test_a_ray_aimed_at_a_wall_corner_stops_there():
    """Two walls meeting at a corner: a ray aimed at the joint must not slip out between them
    (in floating point the corner can fall just past the end of both segments)."""
    from scanflow.sim import get_world

    walls = get_world("corridor").segments
    rng = np.random.default_rng(0)
    origins = rng.uniform((0.5, 0.2), (39.5, 1.8), (2000, 2))
    corners = np.array([(0.0, 0.0), (40.0, 0.0), (40.0, 2.0), (0.0, 2.0)])
    for corner in corners:
        to = corner - origins
        distance = cast_rays(origins, np.arctan2(to[:, 1], to[:, 0]), walls, 100.0)
        np.testing.assert_array_less(distance, np.hypot(to[:, 0], to[:, 1]) + 1e-9)
