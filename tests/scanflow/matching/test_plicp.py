"""Point-to-line ICP on simulated scans: accuracy, degeneracy, bad input, covariance calibration
(the target line fits and the compiled grid lookup are tested in test_correspondence.py)."""

import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.matching import MatchStatus, match

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


@pytest.mark.parametrize("offset_m", [30.0, 250.0])
def test_a_map_far_from_its_origin_matches_as_one_near_it(offset_m: float) -> None:
    """Where a map's frame has its origin says nothing about the match: the same room
    30 m or 250 m from it gives the same pose (shifted), status and covariance. The solver
    and its conditioning took the pose's rotation about the MAP's origin (a left increment),
    whose lever arm grows with the distance: a room 30 m out was 'degenerate' along a tilted
    direction and moved 6 cm towards the guess; 250 m out, 'singular'."""
    from .conftest import assert_far_map_matches_as_near

    assert_far_map_matches_as_near("plicp", offset_m)
