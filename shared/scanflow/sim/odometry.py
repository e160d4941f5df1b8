"""Wheel odometry integrated from the true motion, with scale error and a yaw-bias random walk."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import normalize_angles, relative_arrays, se2_exp, se2_log
from scanflow.sim.trajectory import Trajectory


def odometry_poses(
    trajectory: Trajectory,
    stamps_s: NDArray[np.float64],
    rng: np.random.Generator,
    scale_error: float = 0.0,
    yaw_noise_rps: float = 0.0,
) -> NDArray[np.float64]:
    """Odometry poses (N, 3) at `stamps_s`, starting at the true pose at stamps_s[0].

    Each true increment between samples is measured with its translation scaled by
    (1 + scale_error) and its rotation biased by a yaw-rate bias that random-walks with
    `yaw_noise_rps` per sqrt(second). With both zero, the poses equal the truth.
    """
    truth = trajectory.pose_at(stamps_s)
    if stamps_s.size < 2:
        return truth
    steps = se2_log(relative_arrays(truth[:-1], truth[1:]))
    dt_s = np.diff(stamps_s)
    bias_rps = np.cumsum(rng.normal(0.0, yaw_noise_rps, dt_s.shape) * np.sqrt(dt_s))
    steps[:, :2] *= 1.0 + scale_error
    steps[:, 2] += bias_rps * dt_s
    increments = se2_exp(steps)
    poses = np.empty_like(truth)
    poses[0] = truth[0]
    heading = truth[0, 2] + np.concatenate(([0.0], np.cumsum(increments[:, 2])))
    c, s = np.cos(heading[:-1]), np.sin(heading[:-1])
    moves = np.column_stack(
        (c * increments[:, 0] - s * increments[:, 1], s * increments[:, 0] + c * increments[:, 1])
    )
    poses[1:, :2] = truth[0, :2] + np.cumsum(moves, axis=0)
    poses[:, 2] = normalize_angles(heading)
    return poses
