"""The built-in simulator: worlds, trajectories, a lidar with true motion distortion, odometry.

`simulate(SimConfig(...))` yields one `SimFrame` per sweep with exact ground truth; it is the
embedded default the whole product runs on when no log is given.
"""

from scanflow.sim.lidar import LidarModel, measure
from scanflow.sim.odometry import odometry_poses
from scanflow.sim.raycast import cast_rays, static_scan
from scanflow.sim.run import SimConfig, SimFrame, simulate
from scanflow.sim.trajectory import (
    ConstantVelocityTrajectory,
    PiecewiseTwistTrajectory,
    Trajectory,
    tour_trajectory,
)
from scanflow.sim.world import WORLDS, World, get_world

__all__ = [
    "WORLDS",
    "ConstantVelocityTrajectory",
    "LidarModel",
    "PiecewiseTwistTrajectory",
    "SimConfig",
    "SimFrame",
    "Trajectory",
    "World",
    "cast_rays",
    "get_world",
    "measure",
    "odometry_poses",
    "simulate",
    "static_scan",
    "tour_trajectory",
]
