"""Point-to-line ICP on simulated scans: accuracy, degeneracy, bad input, covariance calibration,
the target line fits, and the compiled grid lookup against scipy's KD-tree."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.geometry import Pose2D, angle_diff
from scanflow.matching import MatchStatus, match
from scanflow.matching.correspondence import GridIndex, grid_k_nearest, target_lines
from scanflow.sim import ConstantVelocityTrajectory, LidarModel, get_world, measure
from scipy.spatial import cKDTree


def scan_points(world: str, pose: Pose2D, seed: int, noise_m: float = 0.01) -> np.ndarray:
    """Valid endpoints of a static 360-beam sweep from `pose` (sensor frame)."""
    lidar = LidarModel(beams=360, fov_deg=360.0, range_noise_m=noise_m)
    still = ConstantVelocityTrajectory(pose, 0.0, 0.0)
    rng = np.random.default_rng(seed)
    return measure(lidar, still, get_world(world).segments, 0.0, rng).scan.points()


TARGET_POSE = Pose2D(7.0, 2.5, 0.1)
SOURCE_POSE = Pose2D(7.3, 2.3, 0.2)
TRUTH = SOURCE_POSE.relative_to(TARGET_POSE)


@pytest.mark.parametrize(("method", "max_error_deg"), [("plicp", 0.3), ("icp", 0.6)])
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
    rng = np.random.default_rng(11)
    nees = []
    for trial in range(60):
        base = Pose2D(rng.uniform(2, 13), rng.uniform(1.5, 6.5), rng.uniform(-math.pi, math.pi))
        moved = base * Pose2D(rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.normal(0, 0.05))
        target = scan_points("rooms", base, 2 * trial, noise_m=0.02)
        source = scan_points("rooms", moved, 2 * trial + 1, noise_m=0.02)
        truth = moved.relative_to(base)
        r = match(source, target, truth * Pose2D(0.05, -0.05, 0.02), method="plicp")
        if not r.ok:
            continue
        dtheta = angle_diff(r.pose.theta, truth.theta)
        v = np.array([r.pose.x - truth.x, r.pose.y - truth.y, dtheta])
        nees.append(float(v @ np.linalg.solve(r.covariance, v)))
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
@given(seed=st.integers(0, 2**31), gate=st.floats(0.05, 2.0))
def test_grid_k_nearest_matches_kdtree(seed: int, gate: float) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-10, 10, (200, 2))
    queries = rng.uniform(-11, 11, (50, 2))
    grid = GridIndex.build(pts, 0.25)
    dist, idx = cKDTree(pts).query(queries, distance_upper_bound=gate)
    best_d2, best_j = np.empty(1), np.empty(1, dtype=np.int64)
    for q, d, i in zip(queries, dist, idx, strict=True):
        found = grid_k_nearest(grid.arrays, q[0], q[1], gate, best_d2, best_j)
        j, d2 = best_j[0], best_d2[0]
        if math.isinf(d):
            assert j == -1 and found == 0
        else:
            assert math.isclose(math.sqrt(d2), d, rel_tol=1e-9) and (j == i or d2 == d * d)
