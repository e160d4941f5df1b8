"""estimate_mount: exact on exact motions, tolerant of noise and outliers, honest when the
motions cannot tell the mount."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.calibration import MountStatus, estimate_mount
from scanflow.geometry import Pose2D

mounts = st.builds(
    Pose2D,
    st.floats(-1.0, 1.0),
    st.floats(-1.0, 1.0),
    st.floats(-math.pi, math.pi, exclude_max=True),
)


def drive(count: int, seed: int) -> list[Pose2D]:
    """Robot motions with turns and straight stretches, as a robot between scans."""
    rng = np.random.default_rng(seed)
    return [Pose2D(*rng.normal(0.0, [0.3, 0.05, 0.3])) for _ in range(count)]


def seen_by(mount: Pose2D, robot: list[Pose2D]) -> list[Pose2D]:
    """The lidar's motions B = X^-1 A X."""
    return [mount.inverse() * a * mount for a in robot]


def close(a: Pose2D, b: Pose2D, metres: float, radians: float) -> bool:
    d = a.relative_to(b)
    return d.translation_norm() < metres and abs(d.theta) < radians


@settings(max_examples=60, deadline=None)
@given(mounts, st.integers(0, 10_000))
def test_exact_motions_give_the_mount_exactly(mount: Pose2D, seed: int) -> None:
    robot = drive(30, seed)
    found = estimate_mount(robot, seen_by(mount, robot))
    assert found.ok, found.message
    assert close(found.mount, mount, 1e-6, 1e-6)
    assert found.pairs_used == found.pairs_given == 30 and found.residual_rms_m < 1e-6


def test_noise_moves_it_within_the_reported_uncertainty() -> None:
    mount, rng = Pose2D(0.25, -0.1, math.radians(12.0)), np.random.default_rng(3)
    robot = drive(200, 3)
    noisy = [b * Pose2D(*rng.normal(0.0, [0.005, 0.005, 0.001])) for b in seen_by(mount, robot)]
    found = estimate_mount(robot, noisy)
    d = found.mount.relative_to(mount)
    assert abs(d.x) < 4 * found.std_xy_m[0] and abs(d.y) < 4 * found.std_xy_m[1]
    assert abs(d.theta) < 4 * found.std_yaw_rad
    assert 0 < found.std_xy_m[0] < 0.01 and 0.003 < found.residual_rms_m < 0.03


def test_bad_matches_are_dropped_not_averaged_in() -> None:
    mount = Pose2D(-0.3, 0.05, math.pi)  # a rear-facing lidar
    robot = drive(40, 5)
    sensor = seen_by(mount, robot)
    sensor[3] = sensor[3] * Pose2D(0.0, 0.0, 0.2)  # the rotations disagree: dropped first
    sensor[7] = sensor[7] * Pose2D(0.8, -0.5, 0.0)  # a wrong translation: trimmed
    found = estimate_mount(robot, sensor)
    assert found.ok and found.pairs_used == 38 and found.pairs_given == 40
    assert close(found.mount, mount, 1e-6, 1e-6)


def test_motions_that_cannot_tell_the_mount_say_so() -> None:
    mount = Pose2D(0.2, 0.1, 0.3)
    straight = [Pose2D(0.3, 0.0, 0.0)] * 20
    found = estimate_mount(straight, seen_by(mount, straight))
    assert found.status is MountStatus.NO_TURNING and "drive turns" in found.message
    on_the_spot = [Pose2D(0.0, 0.0, 0.4)] * 20
    # Turning on the spot moves an offset lidar a little: too little to tell its yaw here.
    centred = Pose2D(0.0, 0.0, 0.3)
    assert estimate_mount(on_the_spot, seen_by(centred, on_the_spot)).status is (
        MountStatus.NO_DRIVING
    )
    few = drive(4, 1)
    assert estimate_mount(few, seen_by(mount, few)).status is MountStatus.TOO_FEW_PAIRS
    assert not math.isfinite(estimate_mount(few, few).residual_rms_m)


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match="differ in length"):
        estimate_mount(drive(5, 0), drive(4, 0))
    with pytest.raises(ValueError, match="finite"):
        estimate_mount([Pose2D(math.nan, 0.0, 0.0)], [Pose2D()])


def test_trimming_away_every_turn_is_reported_not_fitted() -> None:
    # Long exact straight stretches and a few noisy turns: the turns' residuals are many times
    # the (straight) median, so trimming drops them and the kept pairs cannot tell t_X.
    mount, rng = Pose2D(0.25, -0.1, math.radians(12.0)), np.random.default_rng(0)
    robot = [Pose2D(0.3, 0.0, 0.0)] * 40 + [Pose2D(0.1, 0.0, 0.3 * (-1) ** k) for k in range(6)]
    sensor = seen_by(mount, robot)
    sensor[40:] = [b * Pose2D(*rng.normal(0.0, [0.03, 0.03, 0.0])) for b in sensor[40:]]
    found = estimate_mount(robot, sensor)
    assert found.status is MountStatus.NO_TURNING, found
    assert "drive turns" in found.message


def test_turning_about_one_point_cannot_tell_the_yaw_and_says_so() -> None:
    """Turning on the spot, or driving arcs of one radius, turns the robot about one point:
    the mount's yaw and position trade off along a whole family (R(phi)^T (t_X - c) fixed),
    however far an offset lidar moves. Before, the lidar's translations passed the driving
    check and an exact fit returned OK, metres and degrees off, with a std of 1e-17."""
    mount = Pose2D(0.3, 0.1, math.radians(20.0))
    turns = np.random.default_rng(0).uniform(0.1, 0.5, 40)
    on_the_spot = [Pose2D(0.0, 0.0, th) for th in turns]
    arcs = [Pose2D(math.sin(th), 1.0 - math.cos(th), th) for th in turns]  # radius 1 m
    for robot in (on_the_spot, arcs):
        found = estimate_mount(robot, seen_by(mount, robot))
        assert found.status is MountStatus.NO_DRIVING, found
        assert "drive straight stretches" in found.message
    # One straight stretch among the arcs breaks the family: the mount is found exactly.
    robot = [*arcs, Pose2D(0.5, 0.0, 0.0)]
    found = estimate_mount(robot, seen_by(mount, robot))
    assert found.ok and close(found.mount, mount, 1e-6, 1e-6)
