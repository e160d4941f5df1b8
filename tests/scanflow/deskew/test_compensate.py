import dataclasses
import math
from itertools import islice

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.deskew import (
    DEFAULT_REFERENCE,
    NO_RETURN_RANGE_M,
    ConstantVelocityModel,
    DeskewError,
    OdometryBuffer,
    deskew,
    motion_free_reason,
)
from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan, ScanError
from scanflow.sim import ConstantVelocityTrajectory, SimConfig, simulate

QUIET = {"range_noise_m": 0.0, "dropout_prob": 0.0, "odom_scale_error": 0.0, "odom_yaw_noise": 0.0}


def _scan(n=8, duration_s=0.1, stamp_s=1.0, offsets=None, ranges=None, range_max_m=30.0):
    return LaserScan(
        ranges_m=np.full(n, 4.0) if ranges is None else ranges,
        angle_min_rad=-math.pi,
        angle_increment_rad=2 * math.pi / max(n, 1),
        range_max_m=range_max_m,
        stamp_s=stamp_s,
        scan_duration_s=duration_s,
        beam_time_offsets_s=offsets,
    )


def _buffer_from(trajectory, start_s, end_s, rate_hz=50.0):
    buffer = OdometryBuffer()
    for t in np.arange(start_s, end_s, 1.0 / rate_hz):
        buffer.add(t, Pose2D.from_array(trajectory.pose_at(t)[0]))
    return buffer


def test_default_reference_is_the_scan_stamp():
    assert DEFAULT_REFERENCE == "start"


def test_exact_on_simulator_with_noise_free_odometry():
    trajectory = ConstantVelocityTrajectory(Pose2D(7.5, 2.0, 0.0), 1.0, math.pi)
    config = SimConfig(
        duration_s=1.0,
        fov_deg=360,
        range_noise_m=0.02,
        dropout_prob=0.05,
        odom_scale_error=0.0,
        odom_yaw_noise=0.0,
    )
    buffer = OdometryBuffer()
    errors, raw_errors = [], []
    for frame in simulate(config, trajectory):
        for sample in frame.odometry:
            buffer.add_odometry(sample)
        result = deskew(frame.scan, buffer)
        assert result.source_used == "odometry" and not result.times_assumed
        assert result.valid_count == frame.scan.valid_count
        errors.append(np.linalg.norm(result.points - frame.true_points, axis=1))
        raw_errors.append(np.linalg.norm(frame.scan.points() - frame.true_points, axis=1))
    errors = np.concatenate(errors)
    # Only the chord-vs-arc error of linear interpolation remains: v * w * dt^2 / 8.
    assert errors.max() <= 1.0 * math.pi * 0.02**2 / 8 + 1e-9
    assert np.concatenate(raw_errors).mean() > 100 * errors.mean()


MOUNT = Pose2D(0.3, -0.1, math.radians(35.0))


def test_mounted_lidar_is_exact_in_the_robots_frame():
    """A lidar 30 cm off the turning axis: deskewing through the mount recovers the robot-frame
    points; ignoring it (moving sensor-frame beams by the robot's motion) is far off."""
    trajectory = ConstantVelocityTrajectory(Pose2D(7.5, 2.0, 0.0), 0.5, math.pi)
    config = SimConfig(duration_s=1.0, fov_deg=360, mount=MOUNT, **QUIET)
    buffer = OdometryBuffer()
    errors, unmounted_errors = [], []
    for frame in simulate(config, trajectory):
        for sample in frame.odometry:
            buffer.add_odometry(sample)
        assert frame.scan.mount == MOUNT
        result = deskew(frame.scan, buffer)
        assert result.mount == MOUNT
        errors.append(np.linalg.norm(result.points - frame.true_points, axis=1))
        bare = deskew(dataclasses.replace(frame.scan, mount=Pose2D()), buffer)
        unmounted = MOUNT.transform_points(bare.points)
        unmounted_errors.append(np.linalg.norm(unmounted - frame.true_points, axis=1))
    errors = np.concatenate(errors)
    assert errors.max() <= 0.5 * math.pi * 0.02**2 / 8 + 1e-9  # chord vs arc, as unmounted
    assert np.concatenate(unmounted_errors).mean() > 100 * errors.mean()


def test_seed_formula_on_a_hand_computed_case():
    # Two beams: at t=0 from the origin looking along +x, at t=0.1 after moving 0.1 m along +x and
    # turning 90 deg (the segment end pose), beam angle 0. Seed: p_ref = T_ref^-1 * T_beam * p.
    scan = _scan(n=2, ranges=np.array([2.0, 3.0]), offsets=np.array([0.0, 0.1]), stamp_s=0.0)
    scan = LaserScan(
        ranges_m=np.array([2.0, 3.0]),
        angle_min_rad=0.0,
        angle_increment_rad=0.0,
        stamp_s=0.0,
        beam_time_offsets_s=np.array([0.0, 0.1]),
    )
    buffer = OdometryBuffer()
    buffer.add(0.0, Pose2D(0.0, 0.0, 0.0))
    buffer.add(0.1, Pose2D(0.1, 0.0, math.pi / 2))
    start = deskew(scan, buffer, "start")
    np.testing.assert_allclose(start.points, [[2.0, 0.0], [0.1, 3.0]], atol=1e-12)
    end = deskew(scan, buffer, "end")
    # In the end frame (at (0.1, 0) facing +y): first beam's endpoint (2, 0) -> (0, -1.9).
    np.testing.assert_allclose(end.points, [[0.0, -1.9], [3.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(end.ranges_m, [1.9, 3.0])
    np.testing.assert_allclose(end.angles_rad, [-math.pi / 2, 0.0], atol=1e-12)
    middle = deskew(scan, buffer, "middle")
    assert middle.reference_stamp_s == pytest.approx(0.05)


def test_falls_back_to_constant_velocity_then_none():
    trajectory = ConstantVelocityTrajectory(Pose2D(), 1.0, math.pi)
    scan = _scan(n=360, stamp_s=1.0)
    stale = _buffer_from(trajectory, 0.0, 0.5)
    model = ConstantVelocityModel()
    for t in (0.8, 0.9):
        model.update(t, Pose2D.from_array(trajectory.pose_at(t)[0]))
    result = deskew(scan, [stale, model])
    assert result.source_used == "constant_velocity"
    assert "odometry: sweep ends" in result.message
    assert result.times_assumed
    # ground truth for uniform beam times on this circle
    beam_poses = trajectory.pose_at(1.0 + scan.time_offsets_s)
    start = Pose2D.from_array(beam_poses[0])
    truth = np.array(
        [
            start.inverse().transform_points(Pose2D.from_array(p).transform_points(q))[0]
            for p, q in zip(beam_poses, scan.points(), strict=True)
        ]
    )
    np.testing.assert_allclose(result.points, truth, atol=1e-9)
    none = deskew(scan, [stale, ConstantVelocityModel()])
    assert none.source_used == "none"
    assert "constant_velocity: needs two poses" in none.message
    np.testing.assert_allclose(none.points, scan.points())
    assert deskew(scan, None).message == "no pose source covers the sweep: no pose source given"


def test_zero_duration_empty_and_all_invalid_scans_are_reported_not_raised():
    buffer = _buffer_from(ConstantVelocityTrajectory(Pose2D(), 1.0, 0.0), 0.0, 2.0)
    zero = deskew(_scan(duration_s=0.0), buffer)
    assert zero.source_used == "none" and "zero duration" in zero.message
    np.testing.assert_allclose(zero.points, _scan(duration_s=0.0).points())
    invalid = deskew(_scan(ranges=np.full(8, np.nan)), buffer)
    assert invalid.points.shape == (0, 2) and "no valid beams" in invalid.message
    assert invalid.no_return_points.shape == (0, 2)
    open_space = deskew(_scan(ranges=np.full(8, np.inf)), buffer)
    assert open_space.points.shape == (0, 2) and "no valid beams" in open_space.message
    np.testing.assert_allclose(np.hypot(*open_space.no_return_points.T), 30.0)
    empty = deskew(_scan(n=0, ranges=np.zeros(0)), buffer)
    assert empty.beam_count == 0 and empty.source_used == "none"


def test_motion_free_reason_says_when_no_pose_can_move_the_beams():
    """Callers (the deskew service) skip waiting for poses exactly when deskew ignores them."""
    assert "zero duration" in motion_free_reason(_scan(duration_s=0.0))
    assert "no valid beams" in motion_free_reason(_scan(ranges=np.full(8, np.nan)))
    assert "no valid beams" in motion_free_reason(_scan(n=0, ranges=np.zeros(0)))
    assert motion_free_reason(_scan(duration_s=0.1)) is None
    late = np.full(8, 0.01)  # every beam at one instant, but not at the stamp: still moved
    assert motion_free_reason(_scan(duration_s=0.0, offsets=late)) is None


def test_odometry_gap_falls_back_with_the_reason():
    buffer = OdometryBuffer(max_gap_s=0.05)
    for t in (0.9, 0.95, 1.2, 1.25):
        buffer.add(t, Pose2D(t, 0.0, 0.0))
    result = deskew(_scan(stamp_s=1.0), buffer)
    assert result.source_used == "none" and "odometry gap" in result.message


def test_bad_reference_and_bad_beam_times_are_clear_errors():
    with pytest.raises(DeskewError, match="reference must be one of"):
        deskew(_scan(), None, "later")
    with pytest.raises(ScanError, match="non-decreasing"):
        _scan(n=3, offsets=np.array([0.0, 0.2, 0.1]))
    with pytest.raises(ScanError, match="non-finite"):
        _scan(n=3, offsets=np.array([0.0, np.nan, 0.1]))


def test_uniform_offsets_match_the_scan_model():
    from scanflow.deskew.compensate import _time_offsets

    for n, duration in ((360, 0.1), (1, 0.1), (5, 0.0)):
        scan = _scan(n=n, duration_s=duration, ranges=np.full(n, 1.0))
        np.testing.assert_array_equal(_time_offsets(scan), scan.time_offsets_s)


poses = st.builds(
    Pose2D,
    st.floats(-50, 50),
    st.floats(-50, 50),
    st.floats(-math.pi, math.pi),
)
twists = st.tuples(st.floats(-1.5, 1.5), st.floats(-0.3, 0.3), st.floats(-math.pi, math.pi))


@settings(max_examples=60, deadline=None)
@given(poses, st.integers(2, 400), st.floats(0.01, 0.2))
def test_zero_motion_is_the_identity(pose, n, duration_s):
    buffer = OdometryBuffer()
    for t in np.arange(0.9, 1.4, 0.02):
        buffer.add(t, pose)
    scan = _scan(n=n, duration_s=duration_s, ranges=np.linspace(0.5, 20.0, n))
    for reference in ("start", "middle", "end"):
        result = deskew(scan, buffer, reference)
        assert result.source_used == "odometry"
        np.testing.assert_allclose(result.points, scan.points(), atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    poses,
    st.lists(st.sampled_from([1.0, 7.5, 30.0, 45.0, np.inf, np.nan]), min_size=1, max_size=300),
    st.sampled_from([30.0, np.inf]),
)
def test_zero_motion_puts_no_return_beams_along_their_directions(pose, ranges, range_max_m):
    buffer = OdometryBuffer()
    for t in np.arange(0.9, 1.4, 0.02):
        buffer.add(t, pose)
    scan = _scan(n=len(ranges), ranges=np.array(ranges), range_max_m=range_max_m)
    far_m = 30.0 if math.isfinite(range_max_m) else NO_RETURN_RANGE_M
    angles = scan.angles_rad[scan.no_return_mask]
    expected = far_m * np.column_stack((np.cos(angles), np.sin(angles)))
    for reference in ("start", "middle", "end"):
        result = deskew(scan, buffer, reference)
        np.testing.assert_allclose(result.no_return_points, expected, atol=1e-9)
        np.testing.assert_allclose(result.points, scan.points(), atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(poses, twists, st.integers(2, 400))
def test_no_return_beams_move_like_valid_beams_at_range_max(start, twist, n):
    trajectory = ConstantVelocityTrajectory(start, twist[0], twist[2], vy_mps=twist[1])
    buffer = _buffer_from(trajectory, 0.9, 1.3)
    no_return = np.arange(n) % 3 == 0
    ranges = np.where(no_return, np.inf, np.linspace(0.5, 20.0, n))
    misses = deskew(_scan(n=n, ranges=ranges), buffer)
    # The same beams as valid returns at exactly range_max_m (30 m) land where they did.
    at_max = _scan(n=n, ranges=np.where(no_return, 30.0, ranges), range_max_m=np.inf)
    hits = deskew(at_max, buffer)
    assert misses.source_used == hits.source_used == "odometry"
    np.testing.assert_array_equal(misses.no_return_points, hits.points[no_return])
    np.testing.assert_array_equal(misses.points, hits.points[~no_return])


@settings(max_examples=60, deadline=None)
@given(poses, twists, st.integers(2, 400))
def test_end_equals_start_moved_by_the_relative_pose(start, twist, n):
    trajectory = ConstantVelocityTrajectory(start, twist[0], twist[2], vy_mps=twist[1])
    buffer = _buffer_from(trajectory, 0.9, 1.3)
    scan = _scan(n=n, ranges=np.linspace(0.5, 20.0, n))
    at_start = deskew(scan, buffer, "start")
    at_end = deskew(scan, buffer, "end")
    x, y, theta = buffer.relative_poses(np.array([scan.end_stamp_s]), scan.stamp_s)
    end_in_start = Pose2D(x[0], y[0], theta[0])
    np.testing.assert_allclose(
        end_in_start.inverse().transform_points(at_start.points), at_end.points, atol=1e-9
    )


def test_cli_style_run_reports_sources(tmp_path):
    config = SimConfig(duration_s=0.5, **QUIET)
    buffer = OdometryBuffer()
    used = set()
    for frame in islice(simulate(config), 5):
        for sample in frame.odometry:
            buffer.add_odometry(sample)
        used.add(deskew(frame.scan, buffer).source_used)
    assert used == {"odometry"}


@settings(max_examples=60, deadline=None)
@given(poses, poses, st.integers(2, 400), st.sampled_from(("start", "middle", "end")))
def test_zero_motion_puts_a_mounted_scan_at_its_mount(pose, mount, n, reference):
    buffer = OdometryBuffer()
    for t in np.arange(0.9, 1.4, 0.02):
        buffer.add(t, pose)
    ranges = np.where(np.arange(n) % 5 == 0, np.inf, np.linspace(0.5, 20.0, n))
    scan = dataclasses.replace(_scan(n=n, ranges=ranges), mount=mount)
    bare = deskew(dataclasses.replace(scan, mount=Pose2D()), buffer, reference)
    for result in (deskew(scan, buffer, reference), deskew(scan, None, reference)):
        np.testing.assert_allclose(result.points, mount.transform_points(scan.points()), atol=1e-9)
        np.testing.assert_allclose(
            result.no_return_points, mount.transform_points(bare.no_return_points), atol=1e-6
        )
        # Ranges and bearings are the sensor's, wherever it sits on the robot.
        np.testing.assert_allclose(result.ranges_m, bare.ranges_m, atol=1e-9)
