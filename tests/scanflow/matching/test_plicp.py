"""Point-to-line ICP on simulated scans: accuracy, degeneracy, bad input, covariance calibration,
the target line fits, and the compiled grid lookup against scipy's KD-tree."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.geometry import Pose2D
from scanflow.matching import MatchStatus, match
from scanflow.matching.correspondence import GridIndex, grid_k_nearest, target_lines
from scipy.spatial import cKDTree

from .conftest import scan_points, simulated_nees

TARGET_POSE = Pose2D(7.0, 2.5, 0.1)
SOURCE_POSE = Pose2D(7.3, 2.3, 0.2)
TRUTH = SOURCE_POSE.relative_to(TARGET_POSE)


@pytest.mark.parametrize(("method", "max_error_deg"), [("plicp", 0.3), ("icp", 0.15)])
@pytest.mark.parametrize(("dx_m", "dtheta_rad"), [(0.0, 0.0), (0.15, 0.05), (-0.2, -0.08)])
def test_converges_to_truth_from_nearby_guess(
    method: str, max_error_deg: float, dx_m: float, dtheta_rad: float
) -> None:
    target = scan_points("rooms", TARGET_POSE, 1)
    source = scan_points("rooms", SOURCE_POSE, 2)
    guess = TRUTH * Pose2D(dx_m, -dx_m, dtheta_rad)
    r = match(source, target, guess, method=method)
    err = r.pose.relative_to(TRUTH)
    assert r.ok, r.message
    assert err.translation_norm() < 0.02 and abs(err.theta) < math.radians(max_error_deg)
    assert np.all(np.isfinite(r.covariance)) and np.all(np.linalg.eigvalsh(r.covariance) > 0)


def test_corridor_is_flagged_with_the_weak_direction() -> None:
    pose = Pose2D(20.0, 1.0, 0.0)
    target = scan_points("corridor", pose, 3, noise_m=0.0)
    # Keep only the two long walls: nothing constrains motion along the corridor.
    target = target[np.abs(target[:, 0]) < 8.0]
    source = target + np.random.default_rng(4).normal(0, 0.005, target.shape)
    r = match(source, target, Pose2D(0.05, 0.0, 0.0), method="plicp")
    assert r.status is MatchStatus.DEGENERATE
    assert r.weak_direction is not None and abs(r.weak_direction[0]) > 0.9


def test_too_few_points_and_empty_target() -> None:
    target = scan_points("rooms", TARGET_POSE, 1)
    assert match(target[:3], target, method="plicp").status is MatchStatus.TOO_FEW_POINTS
    assert match(target, np.zeros((0, 2)), method="plicp").status is MatchStatus.EMPTY_MAP


def test_collinear_target_has_no_usable_solution() -> None:
    line = np.column_stack((np.linspace(0, 5, 100), np.zeros(100)))
    r = match(line + np.array([0.0, 0.01]), line, method="plicp")
    assert not r.ok
    assert r.status in (MatchStatus.DEGENERATE, MatchStatus.ILL_CONDITIONED)


def test_no_overlap_is_reported() -> None:
    target = scan_points("rooms", TARGET_POSE, 1)
    r = match(target + 100.0, target, method="plicp")
    assert r.status is MatchStatus.NO_OVERLAP and not r.converged


def test_covariance_is_calibrated_nees_near_three() -> None:
    """Censi's covariance: mean NEES over random simulated pairs with 2 cm range noise near 3
    (sigma^2 H^-1 gave 10-40: it ignores the target's noise shared by many residuals)."""
    nees = simulated_nees("plicp")
    assert len(nees) >= 50
    assert 1.5 < float(np.mean(nees)) < 6.0


def test_line_fit_uses_the_neighbours_within_the_fit_radius() -> None:
    """Dense wall points get a many-point line; an isolated pair the two-point fallback."""
    wall = np.column_stack((np.linspace(0.0, 2.0, 41), np.zeros(41)))
    pair = np.array([[5.0, 5.0], [5.3, 5.3]])
    lines = target_lines(GridIndex.build(np.vstack((wall, pair))), k=8, fit_radius_m=0.2)
    counts = np.sum(lines.neighbours >= 0, axis=1)
    assert counts[20] == 8 and np.all(counts[-2:] == 2)
    assert np.allclose(np.abs(lines.normals[:41, 1]), 1.0) and lines.ok.all()
    assert np.isclose(abs(lines.normals[-1] @ (pair[1] - pair[0])), 0.0)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    gate=st.floats(0.05, 2.0),
    k=st.sampled_from([1, 3, 8]),
    cell=st.sampled_from([0.05, 0.25, 1.0]),
)
def test_grid_k_nearest_matches_kdtree(seed: int, gate: float, k: int, cell: float) -> None:
    """The ring search (which stops early) finds the same k nearest as scipy's KD-tree."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-10, 10, (200, 2))
    queries = rng.uniform(-11, 11, (50, 2))
    grid = GridIndex.build(pts, cell)
    dist, _ = cKDTree(pts).query(queries, k=k, distance_upper_bound=gate)
    dist = dist.reshape(len(queries), k)
    best_d2, best_j = np.empty(k), np.empty(k, dtype=np.int64)
    for q, d in zip(queries, dist, strict=True):
        found = grid_k_nearest(grid.arrays, q[0], q[1], gate, best_d2, best_j)
        expected = d[np.isfinite(d)]
        assert found == len(expected) and np.all(best_j[found:] == -1)
        assert np.allclose(np.sqrt(best_d2[:found]), expected, rtol=1e-12, atol=0.0)
        assert np.allclose(np.hypot(*(pts[best_j[:found]] - q).T), expected, rtol=1e-12, atol=0.0)
