"""Point-to-point ICP's outlier rules (trimming, adaptive gate), its statuses and its covariance's
calibration (its accuracy on simulated scans is tested with plicp's in test_plicp.py)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.geometry import Pose2D
from scanflow.matching import MatchStatus, match
from scanflow.matching.correspondence import adaptive_gate_m, trimmed_mask

from .conftest import simulated_nees


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 200), frac=st.floats(0.05, 1.0), seed=st.integers(0, 2**31))
def test_trimming_keeps_the_closest_fraction(n: int, frac: float, seed: int) -> None:
    d = np.random.default_rng(seed).exponential(1.0, n)
    keep = trimmed_mask(d, frac)
    assert keep.sum() >= min(n, int(np.ceil(frac * n)))
    if keep.any() and (~keep).any():
        assert d[keep].max() <= d[~keep].min()


def test_trimming_rejects_a_bad_fraction() -> None:
    with pytest.raises(ValueError, match="keep_fraction"):
        trimmed_mask(np.ones(3), 0.0)


def test_gate_follows_the_robust_spread_within_bounds() -> None:
    assert adaptive_gate_m(np.full(10, 0.01), 0.15, 1.0) == 0.15
    assert adaptive_gate_m(np.full(10, 10.0), 0.15, 1.0) == 1.0
    assert np.isclose(adaptive_gate_m(np.full(10, 0.1), 0.15, 1.0), 3 * 1.4826 * 0.1)
    assert adaptive_gate_m(np.zeros(0), 0.15, 1.0) == 1.0


def test_gross_outliers_do_not_move_the_solution() -> None:
    rng = np.random.default_rng(3)
    t = np.linspace(0, 6, 150)
    z, six = np.zeros(150), np.full(150, 6.0)
    walls = np.r_[np.c_[t, z], np.c_[z, t], np.c_[t, six], np.c_[six, t]]
    truth = Pose2D(0.1, -0.05, 0.03)
    source = truth.inverse().transform_points(walls[::2] + rng.normal(0, 0.003, (300, 2)))
    source = np.r_[source, rng.uniform(20, 30, (20, 2))]
    r = match(source, walls, truth * Pose2D(0.02, 0.02, 0.005), method="icp")
    assert r.ok and r.pose.relative_to(truth).translation_norm() < 0.01
    assert r.inliers <= 300


def test_disjoint_sets_report_no_overlap() -> None:
    pts = np.random.default_rng(0).uniform(0, 5, (100, 2))
    assert match(pts + 50.0, pts, method="icp").status is MatchStatus.NO_OVERLAP


def test_covariance_is_calibrated_nees_near_three() -> None:
    """Censi's covariance of the point-to-line optimum plus icp's offset from it: mean NEES near
    3 on seeded simulated pairs (Censi's alone gave ~40: icp stopped 0.3 deg off on average)."""
    nees = simulated_nees("icp")
    assert len(nees) >= 50
    assert 1.5 < float(np.mean(nees)) < 6.0
