"""Closed-form alignment with known correspondences: exactness, weights, the reflection case."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.geometry import Pose2D
from scanflow.matching import MatchInputError, MatchStatus, match
from scanflow.matching.svd import rigid_transform_svd

poses = st.builds(
    Pose2D,
    st.floats(-20, 20),
    st.floats(-20, 20),
    st.floats(-math.pi, math.pi, exclude_max=True),
)


@settings(max_examples=60, deadline=None)
@given(pose=poses, seed=st.integers(0, 2**31))
def test_recovers_any_pose_exactly(pose: Pose2D, seed: int) -> None:
    source = np.random.default_rng(seed).uniform(-5, 5, (20, 2))
    est = rigid_transform_svd(source, pose.transform_points(source))
    err = est.relative_to(pose)
    assert err.translation_norm() < 1e-8 and abs(err.theta) < 1e-9


def test_zero_weight_outlier_is_ignored() -> None:
    rng = np.random.default_rng(1)
    source = rng.uniform(-3, 3, (30, 2))
    truth = Pose2D(0.4, -0.2, 0.3)
    target = truth.transform_points(source)
    target[0] += 50.0
    weights = np.ones(30)
    weights[0] = 0.0
    r = match(source, target, method="svd", weights=weights)
    assert r.ok and r.pose.relative_to(truth).translation_norm() < 1e-9
    assert r.inliers == 29


def _best_rotation_cost(source: np.ndarray, target: np.ndarray) -> float:
    """Brute-force minimum over rotations (with the optimal translation) of the squared error."""
    best = math.inf
    for th in np.linspace(-math.pi, math.pi, 20001):
        c, s = math.cos(th), math.sin(th)
        rs = source @ np.array([[c, s], [-s, c]])
        t = target.mean(axis=0) - rs.mean(axis=0)
        best = min(best, float(np.sum((rs + t - target) ** 2)))
    return best


def test_reflection_is_never_returned_and_rotation_is_optimal() -> None:
    rng = np.random.default_rng(7)
    source = rng.uniform(-2, 2, (12, 2))
    target = source * np.array([1.0, -1.0]) + rng.normal(0, 0.05, (12, 2))
    # The unconstrained solution V U^T is a reflection for this configuration.
    qs, qt = source - source.mean(0), target - target.mean(0)
    u, _, vt = np.linalg.svd(qs.T @ qt)
    assert np.linalg.det(vt.T @ u.T) < 0
    est = rigid_transform_svd(source, target)
    cost = float(np.sum((est.transform_points(source) - target) ** 2))
    assert cost <= _best_rotation_cost(source, target) + 1e-6


def test_unequal_lengths_is_a_clear_error() -> None:
    with pytest.raises(MatchInputError, match="equal length"):
        match(np.zeros((5, 2)), np.zeros((4, 2)), method="svd")


def test_bad_weights_are_a_clear_error() -> None:
    with pytest.raises(MatchInputError, match="weights"):
        match(np.ones((3, 2)), np.ones((3, 2)), method="svd", weights=[1.0, np.nan, 1.0])


def test_coincident_points_leave_rotation_unobservable() -> None:
    r = match(np.zeros((10, 2)), np.zeros((10, 2)), method="svd")
    assert r.status is MatchStatus.DEGENERATE
    assert r.weak_direction is not None
    assert np.allclose(np.abs(r.weak_direction), [0.0, 0.0, 1.0], atol=1e-6)


def test_single_pair_is_too_few() -> None:
    assert match([[0.0, 0.0]], [[1.0, 1.0]], method="svd").status is MatchStatus.TOO_FEW_POINTS
