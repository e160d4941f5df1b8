"""Sensor calibration from the robot's own data: where the lidar sits on the robot.

    robot, sensor = paired_motions(sensor_frame_points, odom_poses)   # scan i+1 to scan i
    estimate = estimate_mount(robot, sensor)   # estimate.mount = T_base_laser, .status, .std_*
"""

from scanflow.calibration.motions import paired_motions
from scanflow.calibration.mount import MountEstimate, MountStatus, estimate_mount

__all__ = ["MountEstimate", "MountStatus", "estimate_mount", "paired_motions"]
