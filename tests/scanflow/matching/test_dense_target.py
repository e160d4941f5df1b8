"""Dense point targets (3,600 and 20,000 beams, an RPLidar S2/S3 or an accumulated point set)
against a 360-beam source, and dense sources against a 360-beam target: the line fits over a
point's nearest neighbours and point-to-point pairs must not drown in the range noise
(`thin_dense_target`)."""

import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.matching import match
from scanflow.sim import get_world, static_scan

SOURCE_POSE = Pose2D(2.5, 2.0, 0.2)
TARGET_POSE = SOURCE_POSE * Pose2D(0.05, 0.0, 0.01)
TRUTH = SOURCE_POSE.relative_to(TARGET_POSE)


def scan_points(pose: Pose2D, seed: int, beams: int = 360) -> np.ndarray:
    """A still 360-deg sweep of `beams` in the "rooms" world, 1 cm range noise (the sim's lidar
    model stops at 1,440 beams)."""
    angles = np.arange(beams) * (2 * math.pi / beams)
    rng = np.random.default_rng(seed)
    return static_scan(get_world("rooms").segments, pose, angles, 12.0, 0.01, rng)


@pytest.mark.parametrize("beams", [3600, 20_000])
@pytest.mark.parametrize("method", ["plicp", "icp", "csm+plicp", "gn+plicp"])
def test_dense_target_matches_like_a_sparse_one(method: str, beams: int) -> None:
    source = scan_points(SOURCE_POSE, 1)
    target = scan_points(TARGET_POSE, 2, beams=beams)
    r = match(source, target, Pose2D(), method=method)
    err = r.pose.relative_to(TRUTH)
    assert r.ok, r.message
    assert err.translation_norm() < 0.005 and abs(err.theta) < math.radians(0.3)
    assert np.all(np.isfinite(r.covariance))


@pytest.mark.parametrize("beams", [3600, 20_000])
@pytest.mark.parametrize("method", ["plicp", "icp", "csm+plicp"])
def test_a_dense_source_is_judged_like_a_sparse_one(method: str, beams: int) -> None:
    """The surface check fits each matched source point's line over its 16 nearest: a few mm
    on a dense scan, where range noise fails the flatness test (plicp said `degenerate` at
    20,000 beams); the source is averaged per bearing bin for the check, as a target is."""
    source = scan_points(SOURCE_POSE, 1, beams=beams)
    target = scan_points(TARGET_POSE, 2)
    r = match(source, target, Pose2D(), method=method)
    err = r.pose.relative_to(TRUTH)
    assert r.ok, r.message
    assert err.translation_norm() < 0.005 and abs(err.theta) < math.radians(0.3)
