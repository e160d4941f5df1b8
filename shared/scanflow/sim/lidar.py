"""A rotating 2D lidar with true motion distortion: each beam is cast from the pose at its time."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import IDENTITY, Pose2D, compose_arrays, transform_points_per_pose
from scanflow.scan import LaserScan
from scanflow.sim.raycast import cast_rays
from scanflow.sim.trajectory import Trajectory


@dataclass(frozen=True)
class LidarModel:
    """Beam layout, rotation rate and error model of the simulated sensor (mounted at the robot)."""

    beams: int = 360
    fov_deg: float = 270.0
    rate_hz: float = 10.0
    range_min_m: float = 0.05
    range_max_m: float = 30.0
    range_noise_m: float = 0.0
    dropout_prob: float = 0.0
    # Beams cast this far (std) off the angles the scan reports, as drivers that sort a
    # spinning head's samples into evenly spaced bins report them (an RPLidar's +-0.5 deg).
    bearing_noise_deg: float = 0.0

    def __post_init__(self) -> None:
        checks = (
            ("beams", 180 <= self.beams <= 1440, "in [180, 1440]"),
            ("fov_deg", 0.0 < self.fov_deg <= 360.0, "in (0, 360]"),
            ("rate_hz", 5.0 <= self.rate_hz <= 40.0, "in [5, 40]"),
            ("range_max_m", self.range_max_m > self.range_min_m >= 0.0, "> range_min_m >= 0"),
            ("range_noise_m", self.range_noise_m >= 0.0, ">= 0"),
            ("dropout_prob", 0.0 <= self.dropout_prob < 1.0, "in [0, 1)"),
            ("bearing_noise_deg", 0.0 <= self.bearing_noise_deg <= 5.0, "in [0, 5]"),
        )
        for field, ok, rule in checks:
            if not ok:
                raise ValueError(f"LidarModel.{field} must be {rule}, got {getattr(self, field)!r}")

    @property
    def full_circle(self) -> bool:
        """True for a 360 deg field of view, where the beams tile the circle."""
        return self.fov_deg >= 360.0

    @property
    def angle_min_rad(self) -> float:
        """First beam's angle: -pi for a full circle, else -fov/2 (the fov centred ahead)."""
        return -math.pi if self.full_circle else -math.radians(self.fov_deg) / 2.0

    @property
    def angle_increment_rad(self) -> float:
        """360 deg: beams tile the circle; otherwise both fov edges are beams (like a Hokuyo)."""
        fov_rad = math.radians(self.fov_deg)
        return fov_rad / self.beams if self.full_circle else fov_rad / (self.beams - 1)

    @property
    def beam_offsets_s(self) -> NDArray[np.float64]:
        """Firing time of each beam after the first: the head turns at rate_hz revolutions/s."""
        seconds_per_rad = 1.0 / (2.0 * math.pi * self.rate_hz)
        beams = np.arange(self.beams, dtype=np.float64)
        return beams * (self.angle_increment_rad * seconds_per_rad)


@dataclass(frozen=True, eq=False)
class Measurement:
    """One simulated sweep and its ground truth (see `SimFrame`)."""

    scan: LaserScan
    true_pose: Pose2D
    true_beam_poses: NDArray[np.float64]
    true_points: NDArray[np.float64]


def measure(
    lidar: LidarModel,
    trajectory: Trajectory,
    segments: NDArray[np.float64],
    stamp_s: float,
    rng: np.random.Generator,
    seq: int = 0,
    robot_id: str = "robot",
    mount: Pose2D = IDENTITY,
) -> Measurement:
    """Sweep starting at `stamp_s`: beam i cast at stamp_s + offset_i from the true pose then,
    by a lidar mounted at `mount` on the robot (`true_pose` and `true_beam_poses` are the robot's).

    Dropouts are reported as NaN, rays that hit nothing as `range_max_m` (both masked by
    LaserScan). `true_points` are the valid measured endpoints re-expressed in the robot's frame
    at `stamp_s` using the true per-beam poses: the exact target of deskewing.
    """
    offsets_s = lidar.beam_offsets_s
    beam_poses = trajectory.pose_at(stamp_s + offsets_s)
    sensor_poses = beam_poses if mount == IDENTITY else compose_arrays(beam_poses, mount.to_array())
    angles_rad = lidar.angle_min_rad + lidar.angle_increment_rad * np.arange(lidar.beams)
    if lidar.bearing_noise_deg > 0:  # cast off the reported angles (the scan keeps those)
        angles_rad = angles_rad + rng.normal(0.0, math.radians(lidar.bearing_noise_deg),
                                             lidar.beams)
    ranges_m = cast_rays(
        sensor_poses[:, :2], sensor_poses[:, 2] + angles_rad, segments, lidar.range_max_m
    )
    if lidar.range_noise_m > 0:
        ranges_m = ranges_m + rng.normal(0.0, lidar.range_noise_m, ranges_m.shape)
    ranges_m[~np.isfinite(ranges_m)] = lidar.range_max_m
    ranges_m[rng.random(ranges_m.shape) < lidar.dropout_prob] = np.nan
    scan = LaserScan(
        ranges_m=ranges_m.astype(np.float32),
        angle_min_rad=lidar.angle_min_rad,
        angle_increment_rad=lidar.angle_increment_rad,
        range_min_m=lidar.range_min_m,
        range_max_m=lidar.range_max_m,
        stamp_s=stamp_s,
        scan_duration_s=1.0 / lidar.rate_hz,
        beam_time_offsets_s=offsets_s,
        robot_id=robot_id,
        seq=seq,
        mount=mount,
    )
    valid = scan.valid_mask
    start = Pose2D.from_array(beam_poses[0])
    relative = compose_arrays(start.inverse().to_array(), sensor_poses[valid])
    true_points = transform_points_per_pose(
        relative[:, 0], relative[:, 1], relative[:, 2], scan.points(valid_only=True)
    )
    return Measurement(scan, start, beam_poses, true_points)
