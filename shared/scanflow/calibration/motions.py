"""Paired motions for the mount fit: wheel odometry against scan matching, scan to scan."""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import IDENTITY, Pose2D
from scanflow.matching import match


def paired_motions(
    points: Sequence[NDArray[np.float64]],
    odom_poses: Sequence[Pose2D],
    mount_guess: Pose2D = IDENTITY,
    method: str = "csm+plicp",
) -> tuple[list[Pose2D], list[Pose2D]]:
    """(robot motions A_i, sensor motions B_i) between consecutive scans: A from the odometry
    poses, B by matching scan i+1 (points in the SENSOR frame, no mount applied) to scan i from
    the guess mount^-1 A mount. Pairs whose match is not OK are left out. Scans must be
    motion-free (keyframes, or a slowly driven robot): deskewing needs the very mount sought."""
    if len(points) != len(odom_poses):
        raise ValueError(f"{len(points)} scans but {len(odom_poses)} odometry poses")
    robot: list[Pose2D] = []
    sensor: list[Pose2D] = []
    inverse = mount_guess.inverse()
    for (p0, o0), (p1, o1) in pairwise(zip(points, odom_poses, strict=True)):
        a = o1.relative_to(o0)
        found = match(p1, p0, inverse * a * mount_guess, method=method)
        if found.ok:
            robot.append(a)
            sensor.append(found.pose)
    return robot, sensor
