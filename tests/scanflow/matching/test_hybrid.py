"""csm+plicp: the correlative search brings large initial errors into plicp's basin."""

import math

import numpy as np
from scanflow.geometry import Pose2D
from scanflow.matching import match
from scanflow.sim import ConstantVelocityTrajectory, LidarModel, get_world, measure


def _scan(pose: Pose2D, seed: int) -> np.ndarray:
    lidar = LidarModel(beams=360, fov_deg=360.0, range_noise_m=0.01)
    still = ConstantVelocityTrajectory(pose, 0.0, 0.0)
    return measure(lidar, still, get_world("rooms").segments, 0.0,
                   np.random.default_rng(seed)).scan.points()


def test_recovers_from_a_large_initial_error() -> None:
    base, moved = Pose2D(7.0, 2.5, 0.1), Pose2D(7.3, 2.3, 0.2)
    truth = moved.relative_to(base)
    guess = truth * Pose2D(0.35, -0.3, math.radians(15.0))
    r = match(_scan(moved, 2), _scan(base, 1), guess, method="csm+plicp")
    err = r.pose.relative_to(truth)
    assert r.ok and r.method == "csm+plicp"
    assert err.translation_norm() < 0.02 and abs(err.theta) < math.radians(0.3)
    assert isinstance(r.extra["csm_pose"], Pose2D)


def test_empty_target_is_reported() -> None:
    r = match(_scan(Pose2D(7.0, 2.5, 0.0), 1), np.zeros((0, 2)), method="csm+plicp")
    assert not r.ok and r.method == "csm+plicp"
