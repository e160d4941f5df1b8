"""A drive around the simulator's `loop` world (a ring corridor), for back-end tests: true
poses, scans cast there, and a drifting estimate of the same poses."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.frontend import FrontendOutput, FrontendStatus
from scanflow.geometry import Pose2D, compose_arrays, relative_arrays
from scanflow.sim import get_world, static_scan

BEAMS = 360
RANGE_MAX_M = 12.0
STEP_M = 0.4


@dataclass(frozen=True)
class Drive:
    truth: NDArray[np.float64]  # (N, 3) true poses
    drifted: NDArray[np.float64]  # (N, 3) the same motion with a heading drift
    scans: list[NDArray[np.float64]]  # robot-frame points at each true pose


def ring_poses(laps: float = 1.15) -> NDArray[np.float64]:
    """Poses every STEP_M along the `loop` world's tour (a closed ring), `laps` times round."""
    corners = get_world("loop").waypoints
    closed = np.vstack((corners, corners[:1]))
    legs = np.diff(closed, axis=0)
    lengths = np.hypot(legs[:, 0], legs[:, 1])
    total = float(lengths.sum())
    s = np.arange(0.0, laps * total, STEP_M) % total
    leg = np.searchsorted(np.cumsum(lengths), s, side="right")
    start = np.concatenate(([0.0], np.cumsum(lengths)[:-1]))
    frac = (s - start[leg]) / lengths[leg]
    xy = closed[leg] + frac[:, None] * legs[leg]
    heading = np.arctan2(legs[leg, 1], legs[leg, 0])
    return np.column_stack((xy, heading))


def drifted_copy(truth: NDArray[np.float64], deg_per_m: float) -> NDArray[np.float64]:
    """The true motion between poses, with the heading turned `deg_per_m` more per metre."""
    steps = relative_arrays(truth[:-1], truth[1:])
    steps[:, 2] += math.radians(deg_per_m) * np.hypot(steps[:, 0], steps[:, 1])
    poses = [truth[0]]
    for step in steps:
        poses.append(compose_arrays(poses[-1], step)[0])
    return np.array(poses)


def output(seq: int, pose: NDArray[np.float64], inserted: bool = True) -> FrontendOutput:
    """A front-end output that accepted and inserted a scan at `pose`."""
    return FrontendOutput(
        seq=seq, stamp_s=0.1 * seq, pose=Pose2D.from_array(pose), covariance=np.eye(3) * 1e-4,
        status=FrontendStatus.TRACKED, method="gn", iterations=3, score=0.8, message="",
        inserted=inserted, prediction_source="odometry",
    )


@pytest.fixture(scope="session")
def drive() -> Drive:
    truth = ring_poses()
    angles = np.arange(BEAMS) * (2 * np.pi / BEAMS)
    segments = get_world("loop").segments
    rng = np.random.default_rng(7)
    scans = [
        static_scan(segments, Pose2D.from_array(p), angles, RANGE_MAX_M, 0.01, rng)
        for p in truth
    ]
    return Drive(truth, drifted_copy(truth, 0.05), scans)
