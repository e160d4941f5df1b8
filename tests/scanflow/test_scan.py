"""LaserScan and Odometry: validity masking, dropped counts, field errors, timing, points."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scanflow.geometry import Pose2D
from scanflow.scan import MAX_MOUNT_M, LaserScan, Odometry, ScanError


def make_scan(ranges, **fields) -> LaserScan:
    defaults = {"angle_min_rad": -math.pi / 2, "angle_increment_rad": math.pi / 180}
    return LaserScan(ranges_m=np.asarray(ranges, dtype=np.float32), **(defaults | fields))


def test_invalid_beams_are_masked_and_counted() -> None:
    ranges = [1.0, math.nan, math.inf, -1.0, 0.0, 0.05, 10.0, 12.0, 9.99]
    scan = make_scan(ranges, range_min_m=0.1, range_max_m=10.0)
    expected = [True, False, False, False, False, False, False, False, True]
    np.testing.assert_array_equal(scan.valid_mask, expected)
    assert scan.valid_count == 2 and scan.dropped_count == 7
    assert scan.beam_count == len(ranges)
    np.testing.assert_allclose(np.hypot(*scan.points().T), [1.0, 9.99], rtol=1e-6)
    assert scan.points(valid_only=False).shape == (len(ranges), 2)


@given(arrays(np.float32, st.integers(1, 200), elements=st.floats(-5, 50, width=32)))
def test_mask_agrees_with_the_rule(ranges: np.ndarray) -> None:
    scan = make_scan(ranges, range_min_m=0.2, range_max_m=30.0)
    rule = [r > 0 and 0.2 <= r < 30.0 for r in ranges.tolist()]
    np.testing.assert_array_equal(scan.valid_mask, rule)
    assert scan.valid_count + scan.dropped_count == ranges.size


def test_no_return_beams_follow_rep_117() -> None:
    ranges = [1.0, math.nan, math.inf, -math.inf, -1.0, 0.0, 0.05, 10.0, 12.0, 9.99]
    scan = make_scan(ranges, range_min_m=0.1, range_max_m=10.0)
    expected = [False, False, True, False, False, False, False, True, True, False]
    np.testing.assert_array_equal(scan.no_return_mask, expected)
    assert scan.no_return_count == 3 and scan.dropped_count == 8
    unbounded = make_scan(ranges, range_min_m=0.1)  # range_max_m = +inf: only +inf is no return
    np.testing.assert_array_equal(unbounded.no_return_mask, np.isposinf(ranges))
    assert unbounded.valid_count == 4


SPECIAL_RANGES = st.sampled_from([math.nan, math.inf, -math.inf, 0.0, 0.2, 30.0])


@given(
    arrays(np.float32, st.integers(1, 200), elements=st.floats(-5, 50, width=32) | SPECIAL_RANGES),
    st.sampled_from([30.0, math.inf]),
)
def test_every_beam_is_valid_no_return_or_error(ranges: np.ndarray, range_max_m: float) -> None:
    scan = make_scan(ranges, range_min_m=0.2, range_max_m=range_max_m)
    no_return = [r >= range_max_m for r in ranges.tolist()]  # NaN compares False
    np.testing.assert_array_equal(scan.no_return_mask, no_return)
    assert not (scan.valid_mask & scan.no_return_mask).any()
    error = ~(scan.valid_mask | scan.no_return_mask)
    assert all(math.isnan(r) or r < 0.2 for r in ranges[error].tolist())


@pytest.mark.parametrize(
    ("fields", "field_name"),
    [
        ({"beam_time_offsets_s": np.zeros(3)}, "beam_time_offsets_s"),
        ({"intensities": np.zeros(5)}, "intensities"),
        ({"angle_min_rad": math.nan}, "angle_min_rad"),
        ({"angle_increment_rad": math.inf}, "angle_increment_rad"),
        ({"stamp_s": math.nan}, "stamp_s"),
        ({"range_min_m": -1.0}, "range_min_m"),
        ({"range_max_m": math.nan}, "range_max_m"),
        ({"range_min_m": 5.0, "range_max_m": 4.0}, "range_max_m"),
        ({"scan_duration_s": -0.1}, "scan_duration_s"),
        ({"robot_id": ""}, "robot_id"),
        ({"seq": -1}, "seq"),
        ({"beam_time_offsets_s": [0.0, 0.2, 0.1, 0.3]}, "beam_time_offsets_s"),
        ({"beam_time_offsets_s": [0.0, math.nan, 0.1, 0.3]}, "beam_time_offsets_s"),
        # Not numbers at all: named, not numpy's bare "could not convert".
        ({"intensities": ["x"] * 4}, "intensities must be numbers"),
        ({"beam_time_offsets_s": ["t"] * 4}, "beam_time_offsets_s must be numbers"),
        ({"angle_min_rad": "left"}, "angle_min_rad must be a number"),
        ({"range_max_m": "far"}, "range_max_m must be numbers"),
        ({"range_max_m": [10.0, 20.0]}, "range_max_m must be one number"),
        ({"range_max_m": np.array([10.0])}, "range_max_m must be one number"),
        ({"angle_increment_rad": 1e300}, "angle_increment_rad must be at most a turn"),
        ({"seq": 1.7}, "seq must be an integer"),
        ({"seq": True}, "seq must be an integer"),
    ],
)
def test_inconsistent_fields_raise_naming_the_field(fields: dict, field_name: str) -> None:
    with pytest.raises(ScanError, match=field_name):
        make_scan([1.0, 2.0, 3.0, 4.0], **fields)


def test_ranges_must_be_numbers() -> None:
    with pytest.raises(ScanError, match="ranges_m must be numbers"):
        LaserScan(["a", "b"], 0.0, 0.1)  # type: ignore[arg-type]


def test_ranges_must_be_one_dimensional() -> None:
    with pytest.raises(ScanError, match="ranges_m"):
        make_scan(np.ones((2, 3)))


def test_uniform_time_offsets_from_duration() -> None:
    scan = make_scan(np.ones(4), stamp_s=10.0, scan_duration_s=0.1)
    assert scan.beam_times_assumed
    np.testing.assert_allclose(scan.time_offsets_s, [0.0, 0.025, 0.05, 0.075])
    assert scan.end_stamp_s == pytest.approx(10.075)


def test_measured_offsets_are_used() -> None:
    offsets = [0.0, 0.01, 0.03, 0.04]
    scan = make_scan(np.ones(4), stamp_s=2.0, beam_time_offsets_s=offsets)
    assert not scan.beam_times_assumed
    np.testing.assert_array_equal(scan.time_offsets_s, offsets)
    assert scan.end_stamp_s == pytest.approx(2.04)


def test_zero_duration_means_simultaneous_beams() -> None:
    scan = make_scan(np.ones(5), stamp_s=3.0)
    np.testing.assert_array_equal(scan.time_offsets_s, np.zeros(5))
    assert scan.end_stamp_s == 3.0


@given(
    arrays(np.float32, st.integers(1, 100), elements=st.floats(0.125, 40, width=32)),
    st.floats(-math.pi, math.pi),
    st.floats(1e-4, 0.1),
)
def test_points_are_polar_to_cartesian(ranges: np.ndarray, angle_min: float, inc: float) -> None:
    scan = make_scan(ranges, angle_min_rad=angle_min, angle_increment_rad=inc)
    pts = scan.points()
    i = np.arange(ranges.size)
    r = ranges.astype(np.float64)
    np.testing.assert_allclose(pts[:, 0], r * np.cos(angle_min + i * inc), atol=1e-9)
    np.testing.assert_allclose(pts[:, 1], r * np.sin(angle_min + i * inc), atol=1e-9)


def test_with_ranges_keeps_layout_and_timing() -> None:
    scan = make_scan(np.ones(3), stamp_s=4.0, scan_duration_s=0.3, robot_id="r1", seq=7)
    other = scan.with_ranges([2.0, math.nan, 3.0])
    assert (other.stamp_s, other.scan_duration_s, other.robot_id, other.seq) == (4.0, 0.3, "r1", 7)
    assert other.dropped_count == 1
    np.testing.assert_array_equal(other.angles_rad, scan.angles_rad)


def test_odometry_validation() -> None:
    odom = Odometry(1.5, Pose2D(1, 2, 3), velocity=(0.5, 0, 0.1), robot_id="r")
    assert odom.velocity == (0.5, 0.0, 0.1)
    with pytest.raises(ScanError, match="stamp_s"):
        Odometry(math.nan, Pose2D())
    with pytest.raises(ScanError, match="pose"):
        Odometry(0.0, (1, 2, 3))  # type: ignore[arg-type]
    with pytest.raises(ScanError, match="velocity"):
        Odometry(0.0, Pose2D(), velocity=(1.0, 2.0))  # type: ignore[arg-type]
    with pytest.raises(ScanError, match=r"velocity\[2\]"):
        Odometry(0.0, Pose2D(), velocity=(1.0, 2.0, math.inf))
    with pytest.raises(ScanError, match="robot_id"):
        Odometry(0.0, Pose2D(), robot_id="")
    # 1.7e308 m was taken, and deskewing then gave non-finite points (a fuzzing audit).
    with pytest.raises(ScanError, match=r"pose must lie within \+-1e\+09 m"):
        Odometry(0.0, Pose2D(0.0, -1.7e308, 0.0))
    with pytest.raises(ScanError, match="velocity must be 3 numbers"):
        Odometry(0.0, Pose2D(), velocity=5)  # type: ignore[arg-type]
    with pytest.raises(ScanError, match=r"velocity\[0\] must be a number"):
        Odometry(0.0, Pose2D(), velocity=("a", 0.0, 0.0))  # type: ignore[arg-type]
    for seq in (-1, 2.5):
        with pytest.raises(ScanError, match="seq must be"):
            Odometry(0.0, Pose2D(), seq=seq)  # type: ignore[arg-type]


def test_ranges_are_held_contiguous_and_writable_whatever_comes_in() -> None:
    """A read-only array (decoded from the wire) or a strided one is copied, so the deskew
    kernels see one array type and compile nothing new on a service's first scan."""
    read_only = np.full(8, 2.0, dtype=np.float32)
    read_only.flags.writeable = False
    strided = np.full(16, 3.0, dtype=np.float32)[::2]
    for incoming in (read_only, strided):
        ranges = make_scan(incoming).ranges_m
        assert ranges.flags.c_contiguous and ranges.flags.writeable
        np.testing.assert_array_equal(ranges, incoming)
    fitting = np.full(8, 4.0, dtype=np.float32)
    assert make_scan(fitting).ranges_m is fitting


def test_robot_points_apply_the_mount() -> None:
    scan = LaserScan(np.array([1.0, np.nan, 2.0], np.float32), 0.0, math.pi / 2, range_max_m=10.0)
    np.testing.assert_allclose(scan.robot_points(), scan.points())
    mounted = dataclasses.replace(scan, mount=Pose2D(0.5, 0.0, math.pi / 2))
    np.testing.assert_allclose(mounted.robot_points(), [[0.5, 1.0], [0.5, -2.0]], atol=1e-12)
    assert mounted.with_ranges(mounted.ranges_m).mount == mounted.mount
    with pytest.raises(ScanError, match="mount"):
        LaserScan(np.ones(3, np.float32), 0.0, 0.1, mount=(0.5, 0.0, 0.0))


@pytest.mark.parametrize("mount", [Pose2D(MAX_MOUNT_M * 1.01, 0.0, 0.0), Pose2D(0.0, -250.0, 0.0)])
def test_a_mount_far_from_the_robot_is_refused(mount: Pose2D) -> None:
    """Millimetres for metres, or a wrong transform: refused by name, never searched."""
    with pytest.raises(ScanError, match=r"mount .* beyond \+-100 m"):
        LaserScan(np.ones(3, np.float32), 0.0, 0.1, mount=mount)
    assert LaserScan(np.ones(3, np.float32), 0.0, 0.1, mount=Pose2D(99.0, -99.0, 3.0)).mount.x == 99
