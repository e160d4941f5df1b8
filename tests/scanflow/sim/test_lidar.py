"""LidarModel's beam layout and `measure`'s distorted sweep, against closed-form arcs and walls."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.geometry import Pose2D
from scanflow.sim import ConstantVelocityTrajectory, LidarModel, measure

HALF_M = 3.0  # a square room [-3, 3] x [-3, 3]
ROOM = np.array(
    [(-HALF_M, -HALF_M, HALF_M, -HALF_M), (HALF_M, -HALF_M, HALF_M, HALF_M),
     (HALF_M, HALF_M, -HALF_M, HALF_M), (-HALF_M, HALF_M, -HALF_M, -HALF_M)],
    dtype=np.float64,
)


def _assert_same_poses(a: NDArray[np.float64], b: NDArray[np.float64]) -> None:
    """Equal positions and headings equal up to whole turns."""
    np.testing.assert_allclose(a[:, :2], b[:, :2], atol=1e-9)
    turn = (a[:, 2] - b[:, 2] + math.pi) % (2 * math.pi) - math.pi
    np.testing.assert_allclose(turn, 0.0, atol=1e-9)


def _to_square_walls(x: NDArray, y: NDArray, bearing: NDArray) -> NDArray[np.float64]:
    """Distance from (x, y) inside the room along `bearing` to its walls."""
    c, s = np.cos(bearing), np.sin(bearing)
    with np.errstate(divide="ignore"):
        to_x = np.where(c > 0, (HALF_M - x) / c, np.where(c < 0, (-HALF_M - x) / c, np.inf))
        to_y = np.where(s > 0, (HALF_M - y) / s, np.where(s < 0, (-HALF_M - y) / s, np.inf))
    return np.minimum(to_x, to_y)


@pytest.mark.parametrize(
    ("field", "value"),
    [("beams", 179), ("beams", 1441), ("fov_deg", 0.0), ("fov_deg", 361.0), ("rate_hz", 4.9),
     ("rate_hz", 40.1), ("range_max_m", 0.05), ("range_noise_m", -0.01),
     ("dropout_prob", 1.0), ("dropout_prob", -0.1), ("bearing_noise_deg", -0.1),
     ("bearing_noise_deg", 5.1)],
)
def test_lidar_model_refuses_a_bad_field_by_name(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=f"LidarModel.{field} must be"):
        LidarModel(**{field: value})


def test_lidar_model_accepts_its_boundary_values() -> None:
    for fields in ({"beams": 180}, {"beams": 1440}, {"fov_deg": 360.0}, {"rate_hz": 5.0},
                   {"rate_hz": 40.0}, {"range_min_m": 0.0}, {"dropout_prob": 0.0}):
        LidarModel(**fields)


@pytest.mark.parametrize("beams", [180, 360, 1080])
def test_a_full_circle_tiles_the_circle_and_a_partial_fov_ends_on_its_edges(beams: int) -> None:
    full = LidarModel(beams=beams, fov_deg=360.0)
    angles = full.angle_min_rad + full.angle_increment_rad * np.arange(beams)
    assert full.full_circle and angles[0] == -math.pi
    assert angles[-1] + full.angle_increment_rad == pytest.approx(math.pi)
    partial = LidarModel(beams=beams, fov_deg=270.0)
    angles = partial.angle_min_rad + partial.angle_increment_rad * np.arange(beams)
    assert not partial.full_circle
    np.testing.assert_allclose(angles[[0, -1]], np.radians([-135.0, 135.0]), atol=1e-12)


@pytest.mark.parametrize(("fov_deg", "rate_hz"), [(360.0, 10.0), (270.0, 10.0), (90.0, 40.0)])
def test_beam_offsets_follow_the_head_turning_at_the_rate(fov_deg: float, rate_hz: float) -> None:
    lidar = LidarModel(beams=360, fov_deg=fov_deg, rate_hz=rate_hz)
    offsets = lidar.beam_offsets_s
    assert offsets[0] == 0.0 and offsets.shape == (360,)
    # The head sweeps the angle between the first and the last beam at rate_hz turns a second.
    swept_rad = lidar.angle_increment_rad * 359
    assert offsets[-1] == pytest.approx(swept_rad / (2 * math.pi * rate_hz))
    np.testing.assert_allclose(np.diff(offsets), offsets[1], rtol=1e-9)
    assert offsets[-1] < 1.0 / rate_hz


@pytest.mark.parametrize(("v", "w"), [(0.0, 0.0), (1.0, 0.0), (0.0, math.pi), (0.8, -2.0)])
def test_each_beam_is_cast_from_the_pose_at_its_own_time(
    v: float, w: float, arc_pose: Callable[..., NDArray[np.float64]]
) -> None:
    start = Pose2D(0.4, -0.7, 0.3)
    lidar = LidarModel(beams=360, fov_deg=360.0, rate_hz=10.0)
    m = measure(lidar, ConstantVelocityTrajectory(start, v, w), ROOM, 2.0,
                np.random.default_rng(0), seq=7, robot_id="r2")
    times = 2.0 + lidar.beam_offsets_s
    poses = arc_pose(start, v, w, times)
    _assert_same_poses(m.true_beam_poses, poses)
    _assert_same_poses(m.true_pose.to_array()[None], poses[:1])
    angles = lidar.angle_min_rad + lidar.angle_increment_rad * np.arange(360)
    expected = _to_square_walls(poses[:, 0], poses[:, 1], poses[:, 2] + angles)
    np.testing.assert_allclose(m.scan.ranges_m, expected, rtol=1e-6)  # float32 ranges
    scan = m.scan
    assert (scan.stamp_s, scan.seq, scan.robot_id) == (2.0, 7, "r2")
    assert scan.scan_duration_s == pytest.approx(0.1)
    np.testing.assert_array_equal(scan.beam_time_offsets_s, lidar.beam_offsets_s)


def test_true_points_are_the_measured_endpoints_seen_from_the_first_beams_pose() -> None:
    start = Pose2D(-0.5, 0.2, 1.0)
    lidar = LidarModel(beams=360, fov_deg=270.0, rate_hz=5.0, dropout_prob=0.2)
    m = measure(lidar, ConstantVelocityTrajectory(start, 1.0, 1.5), ROOM, 0.5,
                np.random.default_rng(3))
    valid = m.scan.valid_mask
    assert m.true_points.shape == (int(valid.sum()), 2)
    poses = m.true_beam_poses[valid]
    bearing = poses[:, 2] + m.scan.angles_rad[valid]
    r = m.scan.ranges_m[valid].astype(np.float64)
    world = poses[:, :2] + r[:, None] * np.column_stack((np.cos(bearing), np.sin(bearing)))
    assert np.isclose(np.abs(world).max(axis=1), HALF_M, atol=1e-5).all()  # on the walls
    first = m.true_pose
    c, s = math.cos(first.theta), math.sin(first.theta)
    d = world - [first.x, first.y]
    in_first = np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]))
    np.testing.assert_allclose(m.true_points, in_first, atol=1e-5)


def test_a_mounted_lidar_casts_from_the_sensor_and_reports_the_robots_poses() -> None:
    robot = Pose2D(0.5, 0.5, 0.0)
    mount = Pose2D(0.3, 0.1, math.pi / 2)  # the sensor looks left, 0.3 m ahead, 0.1 m left
    lidar = LidarModel(beams=360, fov_deg=360.0)
    m = measure(lidar, ConstantVelocityTrajectory(robot, 0.0, 0.0), ROOM, 0.0,
                np.random.default_rng(0), mount=mount)
    np.testing.assert_allclose(m.true_beam_poses, np.tile(robot.to_array(), (360, 1)))
    assert m.scan.mount == mount
    angles = lidar.angle_min_rad + lidar.angle_increment_rad * np.arange(360)
    expected = _to_square_walls(np.full(360, 0.8), np.full(360, 0.6), math.pi / 2 + angles)
    np.testing.assert_allclose(m.scan.ranges_m, expected, rtol=1e-6)
    # true_points are in the robot's frame: the mount applied to each sensor-frame endpoint.
    r = m.scan.ranges_m.astype(np.float64)
    in_robot = np.column_stack((0.3 - r * np.sin(angles), 0.1 + r * np.cos(angles)))
    np.testing.assert_allclose(m.true_points, in_robot, atol=1e-5)


def test_rays_that_hit_nothing_read_range_max_and_dropouts_read_nan() -> None:
    one_wall = ROOM[1:2]  # only the east wall x = 3
    lidar = LidarModel(beams=360, fov_deg=360.0, range_max_m=10.0, dropout_prob=0.3)
    m = measure(lidar, ConstantVelocityTrajectory(Pose2D(), 0.0, 0.0), one_wall, 0.0,
                np.random.default_rng(5))
    ranges = m.scan.ranges_m
    angles = lidar.angle_min_rad + lidar.angle_increment_rad * np.arange(360)
    dropped = np.isnan(ranges)
    assert 0.2 < dropped.mean() < 0.4
    toward = (np.cos(angles) > 0) & (np.abs(3.0 * np.tan(angles)) <= HALF_M)
    hit = toward & (3.0 / np.cos(angles) < 10.0)
    np.testing.assert_allclose(ranges[hit & ~dropped], 3.0 / np.cos(angles[hit & ~dropped]),
                               rtol=1e-6)
    assert (ranges[~hit & ~dropped] == 10.0).all()
    assert m.scan.no_return_count == int((~hit & ~dropped).sum())


def test_range_noise_has_the_configured_spread_and_the_rng_decides_it() -> None:
    still = ConstantVelocityTrajectory(Pose2D(), 0.0, 0.0)
    lidar = LidarModel(beams=1440, fov_deg=360.0, range_noise_m=0.02)
    clean = measure(LidarModel(beams=1440, fov_deg=360.0), still, ROOM, 0.0,
                    np.random.default_rng(0)).scan.ranges_m
    a = measure(lidar, still, ROOM, 0.0, np.random.default_rng(11)).scan.ranges_m
    b = measure(lidar, still, ROOM, 0.0, np.random.default_rng(11)).scan.ranges_m
    np.testing.assert_array_equal(a, b)
    error = (a - clean).astype(np.float64)
    assert abs(error.mean()) < 0.003 and 0.018 < error.std() < 0.022


def test_bearing_noise_casts_each_beam_off_the_angle_the_scan_reports() -> None:
    """From the room's centre every reported bearing keeps its layout, while each range is the
    wall's distance along a bearing drawn about it (std as configured); none without noise."""
    still = ConstantVelocityTrajectory(Pose2D(), 0.0, 0.0)
    lidar = LidarModel(beams=1440, fov_deg=360.0, bearing_noise_deg=0.3)
    plain = LidarModel(beams=1440, fov_deg=360.0)
    scan = measure(lidar, still, ROOM, 0.0, np.random.default_rng(4)).scan
    assert (scan.angle_min_rad, scan.angle_increment_rad) == (
        plain.angle_min_rad, plain.angle_increment_rad)
    reported = plain.angle_min_rad + plain.angle_increment_rad * np.arange(1440)
    rng = np.random.default_rng(4)
    drawn = reported + rng.normal(0.0, math.radians(0.3), 1440)
    np.testing.assert_allclose(scan.ranges_m, _to_square_walls(0.0, 0.0, drawn), rtol=1e-6)
    assert 0.27 < np.degrees(np.std(drawn - reported)) < 0.33
    exact = measure(plain, still, ROOM, 0.0, np.random.default_rng(4)).scan.ranges_m
    np.testing.assert_allclose(exact, _to_square_walls(0.0, 0.0, reported), rtol=1e-6)
