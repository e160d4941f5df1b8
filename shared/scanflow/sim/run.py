"""`simulate(config)`: the built-in simulated robot, one frame per lidar sweep with ground truth."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import IDENTITY, Pose2D
from scanflow.scan import LaserScan, Odometry
from scanflow.sim.lidar import LidarModel, measure
from scanflow.sim.odometry import odometry_poses
from scanflow.sim.trajectory import Trajectory, tour_trajectory
from scanflow.sim.world import get_world

# The tour is laid out in advance at 200 steps a second: an hour is 35 MB and seconds to build,
# a day 0.8 GB and minutes. Longer runs are replays (SCANFLOW_INGEST_REPLAYS).
MAX_DURATION_S = 3600.0


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated run; the same config and seed give the same run."""

    world: str = "rooms"
    duration_s: float = 30.0
    seed: int = 0
    beams: int = 360
    fov_deg: float = 270.0
    rate_hz: float = 10.0
    max_speed_mps: float = 1.0
    max_yaw_rate_dps: float = 90.0
    range_max_m: float = 30.0
    range_noise_m: float = 0.01
    bearing_noise_deg: float = 0.0  # beams cast off their reported angles (see LidarModel)
    dropout_prob: float = 0.01
    odom_rate_hz: float = 50.0
    odom_scale_error: float = 0.01
    odom_yaw_noise: float = 0.002
    robot_id: str = "robot"
    mount: Pose2D = IDENTITY  # the lidar's pose on the robot (T_base_sensor)

    def __post_init__(self) -> None:
        if not 0 < self.duration_s <= MAX_DURATION_S:  # NaN fails too
            raise ValueError(
                f"SimConfig.duration_s must be > 0 and at most {MAX_DURATION_S:g} s, got "
                f"{self.duration_s!r}"
            )
        if self.seed < 0:  # numpy's SeedSequence takes none
            raise ValueError(f"SimConfig.seed must be >= 0, got {self.seed!r}")
        if not (math.isfinite(self.odom_rate_hz) and self.odom_rate_hz > 0):
            raise ValueError(f"SimConfig.odom_rate_hz must be > 0, got {self.odom_rate_hz!r}")
        if not 0 < self.max_speed_mps <= 1.5:
            raise ValueError(
                f"SimConfig.max_speed_mps must be in (0, 1.5], got {self.max_speed_mps}"
            )
        if not 0 < self.max_yaw_rate_dps <= 180:
            raise ValueError(
                f"SimConfig.max_yaw_rate_dps must be in (0, 180], got {self.max_yaw_rate_dps}"
            )
        self.lidar()

    def lidar(self) -> LidarModel:
        """The sensor this config describes (validates its fields)."""
        return LidarModel(
            beams=self.beams,
            fov_deg=self.fov_deg,
            rate_hz=self.rate_hz,
            range_max_m=self.range_max_m,
            range_noise_m=self.range_noise_m,
            bearing_noise_deg=self.bearing_noise_deg,
            dropout_prob=self.dropout_prob,
        )


@dataclass(frozen=True, eq=False)
class SimFrame:
    """One sweep as measured (motion-distorted) plus its ground truth.

    `true_pose` is at scan.stamp_s (the first beam); `true_beam_poses` (N, 3) is the pose at each
    beam's time, for all beams; `true_points` (M, 2) are the valid beams' endpoints (in
    `scan.valid_mask` order) in the frame of `true_pose`; `odometry` holds the samples since the
    previous frame, up to the first one at or after the sweep's last beam.
    """

    scan: LaserScan
    true_pose: Pose2D
    true_beam_poses: NDArray[np.float64]
    odometry: list[Odometry] = field(default_factory=list)
    true_points: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))


def simulate(config: SimConfig, trajectory: Trajectory | None = None) -> Iterator[SimFrame]:
    """Frames of a run over `config.world`, following a seeded tour unless `trajectory` is given."""
    world = get_world(config.world)
    lidar = config.lidar()
    seeds = np.random.SeedSequence(config.seed).spawn(3)
    if trajectory is None:
        trajectory = tour_trajectory(
            world,
            config.duration_s + 1.0,
            int(seeds[0].generate_state(1)[0]),
            config.max_speed_mps,
            config.max_yaw_rate_dps,
        )
    lidar_rng = np.random.default_rng(seeds[1])
    scan_stamps_s = np.arange(0.0, config.duration_s, 1.0 / config.rate_hz)
    sweep_end_s = float(scan_stamps_s[-1] + lidar.beam_offsets_s[-1])
    odom_stamps_s = np.arange(
        0.0, sweep_end_s + 2.0 / config.odom_rate_hz, 1.0 / config.odom_rate_hz
    )
    odom_poses = odometry_poses(
        trajectory,
        odom_stamps_s,
        np.random.default_rng(seeds[2]),
        config.odom_scale_error,
        config.odom_yaw_noise,
    )
    scale = 1.0 + config.odom_scale_error  # on translations, as odometry_poses measures them
    odom_twists = trajectory.twist_at(odom_stamps_s) * (scale, scale, 1.0)
    next_odom = 0
    for seq, stamp_s in enumerate(scan_stamps_s):
        m = measure(
            lidar, trajectory, world.segments, float(stamp_s), lidar_rng, seq, config.robot_id,
            config.mount,
        )
        last_beam_s = m.scan.end_stamp_s
        first = next_odom
        while next_odom < odom_stamps_s.size and (
            next_odom == first or odom_stamps_s[next_odom - 1] < last_beam_s
        ):
            next_odom += 1
        odometry = [
            Odometry(
                stamp_s=float(odom_stamps_s[j]),
                pose=Pose2D.from_array(odom_poses[j]),
                velocity=(
                    float(odom_twists[j, 0]), float(odom_twists[j, 1]), float(odom_twists[j, 2])
                ),
                robot_id=config.robot_id,
                seq=j,
            )
            for j in range(first, next_odom)
        ]
        yield SimFrame(m.scan, m.true_pose, m.true_beam_poses, odometry, m.true_points)
