"""simulate(SimConfig): seeded runs, consistent frames, odometry, and true motion distortion."""

from __future__ import annotations

import math
from itertools import islice

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.sim import ConstantVelocityTrajectory, SimConfig, simulate
from scanflow.sim.run import MAX_DURATION_S

QUIET = {"range_noise_m": 0.0, "dropout_prob": 0.0, "odom_scale_error": 0.0, "odom_yaw_noise": 0.0}


def _frames(config, trajectory=None, count=5):
    return list(islice(simulate(config, trajectory), count))


def test_same_seed_same_run_other_seed_other_run():
    config = SimConfig(duration_s=1.0, seed=7)
    a, b = _frames(config), _frames(config)
    c = _frames(SimConfig(duration_s=1.0, seed=8))
    for fa, fb in zip(a, b, strict=True):
        np.testing.assert_array_equal(fa.scan.ranges_m, fb.scan.ranges_m)
        assert [o.pose for o in fa.odometry] == [o.pose for o in fb.odometry]
    assert not np.array_equal(a[-1].scan.ranges_m, c[-1].scan.ranges_m, equal_nan=True)


def test_frame_fields_are_consistent():
    config = SimConfig(duration_s=1.0, beams=720, fov_deg=270, rate_hz=20, dropout_prob=0.1)
    previous_end = -math.inf
    for frame in _frames(config, count=10):
        scan = frame.scan
        assert scan.beam_count == 720 and not scan.beam_times_assumed
        assert scan.scan_duration_s == pytest.approx(1 / 20)
        assert scan.time_offsets_s[-1] == pytest.approx(0.75 / 20, rel=1e-2)  # 270 of 360 deg
        assert frame.true_beam_poses.shape == (720, 3)
        assert frame.true_points.shape == (scan.valid_count, 2)
        assert 0 < scan.dropped_count < 720
        np.testing.assert_allclose(frame.true_beam_poses[0], frame.true_pose.to_array())
        stamps = [o.stamp_s for o in frame.odometry]
        assert stamps == sorted(stamps) and stamps[0] > previous_end - 1e-12
        assert stamps[-1] >= scan.end_stamp_s  # odometry covers the sweep
        previous_end = stamps[-1]


def test_noise_free_odometry_equals_truth_and_drift_accumulates():
    trajectory = ConstantVelocityTrajectory(Pose2D(2.5, 2.0, 0.0), 0.5, 0.3)
    exact = _frames(SimConfig(duration_s=2.0, **QUIET), trajectory, count=20)
    for frame in exact:
        for sample in frame.odometry:
            truth = trajectory.pose_at(sample.stamp_s)[0]
            np.testing.assert_allclose(sample.pose.to_array(), truth, atol=1e-9)
    drifting = _frames(
        SimConfig(duration_s=2.0, odom_scale_error=0.05, odom_yaw_noise=0.0), trajectory, count=20
    )
    last = drifting[-1].odometry[-1]
    truth = trajectory.pose_at(last.stamp_s)[0]
    start = trajectory.pose_at(0.0)[0]
    travelled = np.hypot(*(truth[:2] - start[:2]))
    assert np.hypot(*(last.pose.to_array()[:2] - truth[:2])) > 0.01 * travelled


def _analytic_beam_motion(v_mps, w_rps, dt_s):
    """Sensor pose at beam time dt relative to the sweep start, for a constant twist (v, 0, w)."""
    phi = w_rps * dt_s
    if w_rps == 0:
        return v_mps * dt_s, np.zeros_like(dt_s), phi
    return v_mps * np.sin(phi) / w_rps, v_mps * (1 - np.cos(phi)) / w_rps, phi


@pytest.mark.parametrize(("v_mps", "w_rps"), [(1.0, 0.0), (0.0, math.pi), (1.0, math.pi)])
def test_distortion_matches_the_motion_during_the_sweep(v_mps, w_rps):
    trajectory = ConstantVelocityTrajectory(Pose2D(7.5, 2.0, 0.4), v_mps, w_rps)
    config = SimConfig(duration_s=0.3, fov_deg=360, **QUIET)
    for frame in _frames(config, trajectory, count=3):
        scan = frame.scan
        measured = scan.points()  # where each beam lands if the sensor had not moved
        dt = scan.time_offsets_s[scan.valid_mask]
        x, y, phi = _analytic_beam_motion(v_mps, w_rps, dt)
        c, s = np.cos(phi), np.sin(phi)
        expected = np.column_stack(
            (
                x + c * measured[:, 0] - s * measured[:, 1],
                y + s * measured[:, 0] + c * measured[:, 1],
            )
        )
        np.testing.assert_allclose(frame.true_points, expected, atol=1e-9)
        displacement = np.linalg.norm(frame.true_points - measured, axis=1)
        if w_rps == 0:
            np.testing.assert_allclose(displacement, v_mps * dt, atol=1e-9)
        elif v_mps == 0:
            ranges = np.linalg.norm(measured, axis=1)
            np.testing.assert_allclose(
                displacement, 2 * ranges * np.abs(np.sin(phi / 2)), atol=1e-9
            )
        assert displacement[-1] > displacement[0]


def test_ranges_agree_with_walls_under_pure_rotation():
    # Spinning at (2.5, 2.0) in a 5 m x 4 m room: each beam's range is the distance to the room's
    # walls along its world direction at its own firing time.
    trajectory = ConstantVelocityTrajectory(Pose2D(2.5, 2.0, 0.0), 0.0, math.pi)
    config = SimConfig(duration_s=0.1, fov_deg=360, beams=360, **QUIET)
    frame = _frames(config, trajectory, count=1)[0]
    scan = frame.scan
    world_angle = scan.angles_rad + math.pi * scan.time_offsets_s
    c, s = np.cos(world_angle), np.sin(world_angle)
    with np.errstate(divide="ignore"):
        to_x = np.where(c > 0, 2.5 / c, np.where(c < 0, -2.5 / c, np.inf))
        to_y = np.where(s > 0, 2.0 / s, np.where(s < 0, -2.0 / s, np.inf))
    expected = np.minimum(to_x, to_y)
    # beams through the doors or at the pillar see further or nearer; compare the rest
    clear = np.abs(scan.ranges_m - expected) < 1e-3
    assert clear.mean() > 0.8
    np.testing.assert_allclose(scan.ranges_m[clear], expected[clear], rtol=1e-5)


def test_bad_config_names_the_field():
    with pytest.raises(ValueError, match="beams"):
        SimConfig(beams=50)
    with pytest.raises(ValueError, match="max_speed_mps"):
        SimConfig(max_speed_mps=3.0)
    # The tour is laid out in advance: a day would take minutes and most of a GB to build.
    for duration_s in (0.0, float("nan"), MAX_DURATION_S + 1.0):
        with pytest.raises(ValueError, match=r"SimConfig\.duration_s"):
            SimConfig(duration_s=duration_s)
    assert SimConfig(duration_s=MAX_DURATION_S).duration_s == MAX_DURATION_S


def test_a_negative_seed_is_refused_naming_the_field():
    """numpy's SeedSequence takes no negative seed: refused by the config, not by the first
    frame deep inside numpy."""
    with pytest.raises(ValueError, match=r"SimConfig\.seed"):
        SimConfig(seed=-1)


def test_odometry_velocity_carries_the_scale_error_of_its_poses_sideways_too():
    """A holonomic base sliding sideways: its odometry poses travel (1 + e) times as far, so
    the velocity reported with them is (1 + e) times the true vy, as vx is."""
    slide = ConstantVelocityTrajectory(Pose2D(7.5, 2.0, 0.3), 0.2, 0.0, vy_mps=0.4)
    config = SimConfig(duration_s=0.5, odom_scale_error=0.1, odom_yaw_noise=0.0)
    samples = [s for frame in simulate(config, slide) for s in frame.odometry]
    poses = np.array([s.pose.to_array() for s in samples])
    stamps = np.array([s.stamp_s for s in samples])
    speed = np.hypot(*np.diff(poses[:, :2], axis=0).T) / np.diff(stamps)
    np.testing.assert_allclose(speed, 1.1 * math.hypot(0.2, 0.4), rtol=1e-9)
    for s in samples:
        assert s.velocity == pytest.approx((1.1 * 0.2, 1.1 * 0.4, 0.0), abs=1e-12)
