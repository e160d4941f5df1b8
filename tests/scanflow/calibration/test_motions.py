"""paired_motions + estimate_mount on scans cast in the simulator's rooms: the mount comes back."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scanflow.calibration import estimate_mount, paired_motions
from scanflow.geometry import Pose2D
from scanflow.sim import get_world, static_scan


def sensor_scan(laser: Pose2D, beams: int = 360) -> np.ndarray:
    """Endpoints in the lidar's own frame of a 270 deg scan from `laser` (world), 1 cm noise."""
    angles = np.radians(np.linspace(-135.0, 135.0, beams))
    rng = np.random.default_rng(int(1000 * (laser.x + 2 * laser.y)) % 2**32)
    return static_scan(get_world("rooms").segments, laser, angles, 20.0, 0.01, rng)


def tour(count: int) -> list[Pose2D]:
    """Weaving through the middle room: 0.15 m steps with turns both ways."""
    poses = [Pose2D(6.0, 1.5, 0.3)]
    for k in range(count - 1):
        poses.append(poses[-1] * Pose2D(0.15, 0.0, 0.25 * math.sin(k / 3.0)))
    return poses


@pytest.mark.parametrize(
    "mount", [Pose2D(0.3, -0.1, math.radians(20.0)), Pose2D(-0.25, 0.0, math.pi)],
    ids=["front-right-turned", "rear-facing"],
)
def test_the_mount_of_a_simulated_lidar_comes_back(mount: Pose2D) -> None:
    robot_poses = tour(25)
    scans = [sensor_scan(pose * mount) for pose in robot_poses]
    robot, sensor = paired_motions(scans, robot_poses, mount_guess=mount * Pose2D(0.1, 0.1, 0.1))
    assert len(robot) >= 20  # nearly every pair matched
    found = estimate_mount(robot, sensor)
    assert found.ok, found.message
    error = found.mount.relative_to(mount)
    assert error.translation_norm() < 0.02 and abs(error.theta) < math.radians(0.5)


def test_scans_and_odometry_must_pair_up() -> None:
    with pytest.raises(ValueError, match="odometry poses"):
        paired_motions([np.zeros((5, 2))], [])
