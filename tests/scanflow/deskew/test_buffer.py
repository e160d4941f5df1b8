"""OdometryBuffer: ordering, bounds, coverage and interpolation of odometry samples."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from scanflow.deskew import ConstantVelocityModel, DeskewError, OdometryBuffer
from scanflow.geometry import Pose2D


def test_out_of_order_and_duplicate_samples_give_the_same_buffer(
    circle_pose: Callable[[float], Pose2D],
):
    stamps = np.arange(0.0, 1.0, 0.02)
    ordered, shuffled = OdometryBuffer(), OdometryBuffer()
    for t in stamps:
        ordered.add(t, circle_pose(t))
    rng = np.random.default_rng(0)
    for t in rng.permutation(stamps):
        shuffled.add(t, Pose2D(9.0, 9.0, 1.0))  # wrong pose first ...
    for t in rng.permutation(stamps):
        assert shuffled.add(t, circle_pose(t))  # ... replaced by the later arrival
    assert shuffled.replaced_count == stamps.size
    np.testing.assert_array_equal(shuffled.stamps_s, ordered.stamps_s)
    times = np.linspace(0.05, 0.9, 50)
    for a, b in zip(ordered.poses_at(times), shuffled.poses_at(times), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_interpolation_is_shortest_arc_across_pi():
    buffer = OdometryBuffer()
    buffer.add(0.0, Pose2D(0.0, 0.0, math.pi - 0.1))
    buffer.add(0.1, Pose2D(1.0, 0.0, -math.pi + 0.1))
    x, _, theta = buffer.poses_at(np.array([0.05]))
    assert x[0] == pytest.approx(0.5)
    assert abs(abs(theta[0]) - math.pi) < 1e-9


def test_bounded_by_age_and_old_samples_dropped():
    buffer = OdometryBuffer(max_age_s=1.0)
    for t in np.arange(0.0, 5.0, 0.01):
        buffer.add(t, Pose2D(t, 0.0, 0.0))
    assert buffer.stamps_s[0] >= 4.99 - 1.0 - 1e-9
    assert not buffer.add(1.0, Pose2D())
    assert buffer.dropped_count == 1


def test_extrapolation_limited_by_margin_and_gaps_refused():
    buffer = OdometryBuffer(extrapolation_margin_s=0.02, max_gap_s=0.2)
    for t in (0.0, 0.1, 0.2, 0.6, 0.7):
        buffer.add(t, Pose2D(t, 0.0, 0.0))
    assert buffer.coverage_gap(-0.01, 0.15) is None
    for t in (-0.01, 0.71):  # extrapolated along the end segments
        np.testing.assert_allclose(buffer.poses_at(np.array([t]))[0], [t])
    assert "before the oldest" in buffer.coverage_gap(-0.05, 0.1)
    assert "after the newest" in buffer.coverage_gap(0.6, 0.75)
    assert "gap of 0.4000 s" in buffer.coverage_gap(0.15, 0.65)
    with pytest.raises(DeskewError, match="after the newest"):
        buffer.poses_at(np.array([0.8]))
    assert "at least two" in OdometryBuffer().coverage_gap(0.0, 0.1)


def test_a_sweep_ending_or_starting_on_a_sample_needs_no_segment_beyond_it():
    buffer = OdometryBuffer(max_gap_s=0.2)
    for t in (0.0, 0.1, 0.6, 0.7, 0.8):
        buffer.add(t, Pose2D(t, 0.0, 0.0))
    # The 0.5 s gap lies after the sweep [0, 0.1] and before [0.6, 0.8]: neither bridges it.
    assert buffer.coverage_gap(0.0, 0.1) is None
    assert buffer.coverage_gap(0.6, 0.8) is None
    assert buffer.coverage_gap(0.1, 0.1) is None
    np.testing.assert_allclose(buffer.poses_at(np.array([0.0, 0.1]))[0], [0.0, 0.1])
    assert "gap of 0.5000 s" in buffer.coverage_gap(0.05, 0.1000001)
    assert "gap of 0.5000 s" in buffer.coverage_gap(0.0999999, 0.6)


def test_buffer_keeps_growing_correctly_past_its_initial_capacity(
    circle_pose: Callable[[float], Pose2D],
):
    buffer = OdometryBuffer(max_age_s=100.0)
    stamps = np.arange(0.0, 20.0, 0.01)
    for t in stamps[::-1][:50]:  # some arrive late
        buffer.add(t, circle_pose(t))
    for t in stamps:
        buffer.add(t, circle_pose(t))
    assert len(buffer) == stamps.size
    x, y, theta = buffer.poses_at(stamps[::97])
    truth = np.array([circle_pose(t).to_array() for t in stamps[::97]])
    np.testing.assert_allclose(np.column_stack((x, y, theta)), truth, atol=1e-9)


def test_bad_settings_and_stamps_name_the_field():
    with pytest.raises(DeskewError, match="max_age_s"):
        OdometryBuffer(max_age_s=0.0)
    with pytest.raises(DeskewError, match="stamp_s"):
        OdometryBuffer().add(math.nan, Pose2D())
    with pytest.raises(DeskewError, match="max_horizon_s"):
        ConstantVelocityModel(max_horizon_s=-1.0)


def test_poses_at_no_time_is_empty_and_a_non_finite_time_is_refused() -> None:
    """No times, no poses (not numpy's zero-size error); a NaN time is named, never answered
    with a NaN pose."""
    from scanflow.scan import Odometry

    buffer = OdometryBuffer()
    for t in (0.0, 0.1, 0.2):
        buffer.add_odometry(Odometry(stamp_s=t, pose=Pose2D(t, 0.0, 0.0)))
    x, y, theta = buffer.poses_at([])
    assert x.shape == y.shape == theta.shape == (0,)
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(DeskewError, match="times_s must be finite"):
            buffer.poses_at([0.12, bad])
