"""Acceptance: why a match result is rejected against the limits, or accepted."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scanflow.frontend import AcceptanceLimits, rejection_reason
from scanflow.geometry import Pose2D
from scanflow.matching import MatchResult, MatchStatus

LIMITS = AcceptanceLimits(
    max_correction_m=0.5, max_correction_rad=math.radians(10), min_score=0.3,
    max_position_std_m=0.2, max_heading_std_rad=math.radians(5), accept_degenerate=True,
)


IDENTITY = Pose2D()


def result(pose: Pose2D = IDENTITY, status: MatchStatus = MatchStatus.OK, score: float = 0.9,
           std_m: float = 0.01) -> MatchResult:
    cov = np.diag([std_m**2, std_m**2, 1e-6])
    return MatchResult(pose, cov, score, 5, status is MatchStatus.OK, status, "gn", "why")


@pytest.mark.parametrize(
    ("res", "needle"),
    [
        (result(), ""),
        (result(status=MatchStatus.DIVERGED), "failed (diverged): why"),
        (result(score=0.1), "score"),
        (result(score=math.nan), "score nan below min_score"),
        (result(Pose2D(0.6, 0.0, 0.0)), "max_correction_m"),
        (result(Pose2D(0.0, 0.0, math.radians(11))), "max_correction"),
        (result(std_m=0.3), "position std"),
        (result(status=MatchStatus.DEGENERATE, std_m=50.0), ""),
    ],
)
def test_rejection_reasons(res: MatchResult, needle: str) -> None:
    reason = rejection_reason(res, Pose2D(), LIMITS)
    assert (needle in reason) if needle else reason == ""


def test_degenerate_can_be_refused() -> None:
    strict = AcceptanceLimits(0.5, 0.2, 0.3, 0.2, 0.1, accept_degenerate=False)
    assert "degenerate" in rejection_reason(result(status=MatchStatus.DEGENERATE), Pose2D(), strict)


def with_covariance(cov: np.ndarray, status: MatchStatus = MatchStatus.OK) -> MatchResult:
    return MatchResult(IDENTITY, cov, 0.9, 5, status is MatchStatus.OK, status, "gn", "")


@pytest.mark.parametrize("status", [MatchStatus.OK, MatchStatus.DEGENERATE])
@pytest.mark.parametrize("entry", [(0, 0), (1, 1), (2, 2), (0, 1)])
def test_a_nan_in_the_covariance_is_rejected(status: MatchStatus, entry: tuple[int, int]) -> None:
    """A NaN anywhere in the covariance (the y variance too, which max() with x let by) is
    refused by name, not trusted and not passed on to the pose graph."""
    cov = np.diag([1e-4, 1e-4, 1e-6])
    cov[entry] = math.nan
    reason = rejection_reason(with_covariance(cov, status), IDENTITY, LIMITS)
    assert "NaN in its covariance" in reason


def test_a_variance_rounded_below_zero_is_a_zero() -> None:
    """An exact fit's variances can come out at -1e-20: accepted, not a math domain error."""
    cov = np.diag([-1e-20, -1e-20, -1e-22])
    assert rejection_reason(with_covariance(cov), IDENTITY, LIMITS) == ""


def test_an_infinite_variance_is_judged_as_wide_not_refused_outright() -> None:
    """inf is a direction nothing is known along: too wide for an OK match, and by design
    allowed along a degenerate match's weak direction."""
    cov = np.diag([1e-4, math.inf, 1e-6])
    assert "position std inf" in rejection_reason(with_covariance(cov), IDENTITY, LIMITS)
    degenerate = with_covariance(cov, MatchStatus.DEGENERATE)
    assert rejection_reason(degenerate, IDENTITY, LIMITS) == ""
