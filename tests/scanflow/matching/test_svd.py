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


@pytest.mark.parametrize(
    ("source_nan", "target_nan"),
    [([3], [30]), ([30], [3]), ([0], [39]), ([5], [5]), ([1, 2], []), ([], [7, 20, 33])],
)
def test_nan_rows_drop_their_pairs_not_shift_the_others(
    source_nan: list[int], target_nan: list[int]
) -> None:
    """A NaN row in one array (a dropped beam) leaves out its pair only: dropping each array's
    NaN rows apart shifted every pair between them (3 deg off, still 'ok')."""
    rng = np.random.default_rng(0)
    source = rng.uniform(-5, 5, (40, 2))
    target = Pose2D(0.5, -0.2, 0.1).transform_points(source) + rng.normal(0, 0.01, (40, 2))
    keep = np.setdiff1d(np.arange(40), source_nan + target_nan)
    expected = match(source[keep], target[keep], method="svd")
    source[source_nan], target[target_nan] = np.nan, np.nan
    r = match(source, target, method="svd")
    assert r.ok and r.inliers == len(keep) == expected.inliers
    assert np.allclose(r.pose.to_array(), expected.pose.to_array(), rtol=0, atol=1e-12)
    assert np.allclose(r.covariance, expected.covariance, rtol=1e-9, atol=0)


def test_weights_pair_with_the_rows_as_given() -> None:
    rng = np.random.default_rng(2)
    source = rng.uniform(-3, 3, (20, 2))
    truth = Pose2D(-0.3, 0.2, -0.4)
    target = truth.transform_points(source)
    target[4] += 9.0  # an outlier, weighted out by its own row's weight
    source[10] = np.nan
    weights = np.ones(20)
    weights[4] = 0.0
    r = match(source, target, method="svd", weights=weights)
    assert r.ok and r.inliers == 18
    assert r.pose.relative_to(truth).translation_norm() < 1e-9


@settings(max_examples=80, deadline=None)
@given(
    pose=poses,
    seed=st.integers(0, 2**31),
    n=st.integers(3, 40),
    source_nan=st.sets(st.integers(0, 39), max_size=10),
    target_nan=st.sets(st.integers(0, 39), max_size=10),
)
def test_nan_rows_anywhere_still_give_the_exact_pose(
    pose: Pose2D, seed: int, n: int, source_nan: set[int], target_nan: set[int]
) -> None:
    source = np.random.default_rng(seed).uniform(-5, 5, (n, 2))
    target = pose.transform_points(source)
    source[[i for i in source_nan if i < n]] = np.nan
    target[[i for i in target_nan if i < n]] = np.nan
    finite = n - len({i for i in source_nan | target_nan if i < n})
    r = match(source, target, method="svd")
    if finite < 2:
        assert r.status is MatchStatus.TOO_FEW_POINTS
        return
    assert r.inliers == finite
    err = r.pose.relative_to(pose)
    assert err.translation_norm() < 1e-9 and abs(err.theta) < 1e-9


def test_covariance_is_in_the_poses_own_parameters_wherever_the_target_lies() -> None:
    """MatchResult.covariance is of (x, y, theta), where dpose/dtheta turns the source about its
    own origin: the same residuals give the same covariance whatever the translation. It was
    the covariance of a left increment (turns about the target's origin): 50 m away, x and y
    were given a 10 m-per-radian lever that a Monte Carlo of the estimate does not show."""
    rng = np.random.default_rng(0)
    source = rng.uniform(-5, 5, (50, 2))
    noise = rng.normal(0.0, 0.01, (50, 2))
    near = match(source, Pose2D(0.0, 0.0, 0.3).transform_points(source) + noise, method="svd")
    far = match(source, Pose2D(50.0, 30.0, 0.3).transform_points(source) + noise, method="svd")
    assert near.ok and far.ok
    assert np.allclose(far.covariance, near.covariance, rtol=1e-6, atol=1e-15)
    # And it is the estimate's spread: a Monte Carlo of the far match.
    truth = Pose2D(50.0, 30.0, 0.3)
    draws = np.array([
        match(source, truth.transform_points(source) + rng.normal(0.0, 0.01, (50, 2)),
              method="svd").pose.to_array()
        for _ in range(2000)
    ])
    sampled = np.cov(draws.T)
    assert np.allclose(np.diag(far.covariance), np.diag(sampled), rtol=0.2)
