"""Checks a scan-to-map match must pass before the front end trusts it and updates the map.

A wrong pose inserted into the map corrupts every later match, so a match is rejected when its
status is not OK (or DEGENERATE, if allowed), its covariance holds a NaN, its score is low,
its covariance is wide, or it moved the pose further from the prediction than the prediction can
plausibly be wrong.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from scanflow.geometry import Pose2D
from scanflow.matching import MatchResult, MatchStatus


@dataclass(frozen=True)
class AcceptanceLimits:
    """Thresholds of `rejection_reason` (metres, radians, score units of the method)."""

    max_correction_m: float
    max_correction_rad: float
    min_score: float
    max_position_std_m: float
    max_heading_std_rad: float
    accept_degenerate: bool = True


def rejection_reason(result: MatchResult, prediction: Pose2D, limits: AcceptanceLimits) -> str:
    """Why `result` must not be used, or "" when it passes every check.

    A DEGENERATE match (a corridor) is only constrained across its weak direction, where the
    matcher keeps the prediction; its covariance is wide along that direction by design, so
    the covariance check applies to OK matches only.
    """
    degenerate = result.status is MatchStatus.DEGENERATE
    if not (result.ok or (degenerate and limits.accept_degenerate)):
        detail = f": {result.message}" if result.message else ""
        return f"{result.method} match failed ({result.status}){detail}"
    # (An infinite variance is a direction nothing is known along: the checks below judge it.)
    if np.isnan(result.covariance).any():
        return (
            f"{result.method} match gave a NaN in its covariance (diagonal "
            f"{np.diag(result.covariance).tolist()})"
        )
    if not result.score >= limits.min_score:  # a NaN score fails too
        return f"score {result.score:.3f} below min_score {limits.min_score}"
    correction = result.pose.relative_to(prediction)
    if correction.translation_norm() > limits.max_correction_m:
        return (
            f"correction {correction.translation_norm():.3f} m from the prediction exceeds "
            f"max_correction_m {limits.max_correction_m}"
        )
    if abs(correction.theta) > limits.max_correction_rad:
        return (
            f"correction {math.degrees(correction.theta):.1f} deg from the prediction exceeds "
            f"max_correction {math.degrees(limits.max_correction_rad):.1f} deg"
        )
    if degenerate:
        return ""
    variances = np.diag(result.covariance)
    # Rounding can leave an exact fit's variance a hair below zero: that is a zero.
    position_std_m = math.sqrt(max(float(variances[0]), float(variances[1]), 0.0))
    if not position_std_m <= limits.max_position_std_m:
        return (
            f"position std {position_std_m:.3g} m exceeds max_position_std_m "
            f"{limits.max_position_std_m}"
        )
    heading_std_rad = math.sqrt(max(float(variances[2]), 0.0))
    if not heading_std_rad <= limits.max_heading_std_rad:
        return (
            f"heading std {math.degrees(heading_std_rad):.3g} deg exceeds max "
            f"{math.degrees(limits.max_heading_std_rad):.3g} deg"
        )
    return ""
