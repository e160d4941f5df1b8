"""Method "csm+plicp": correlative search for the basin, point-to-line ICP for the fine pose.

Local matchers fail once the initial error leaves their basin (tens of cm, a few degrees);
branch-and-bound correlative search (`csm`) scores its window on a likelihood grid at grid
resolution. On sparse scans far apart its best lattice peak is not always the right basin (a
sharp true peak between lattice points can score below a broad wrong one), so the K best
DISTINCT csm peaks are each refined by `plicp` and the refinement under which the most source
points lie within a fixed gate of the (densified) target wins, computed the same way for every
candidate and not by csm score; csm's best is kept unless another is clearly better (a margin:
on the real logs near-ties switched to wrong basins as often as to right ones).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from scanflow.geometry import Pose2D
from scanflow.matching.api import MatchResult, MatchStatus, Target, register_method, target_points
from scanflow.matching.checks import guess_along, weak_length_m
from scanflow.matching.csm import CONDITIONED, found_a_pose, match_csm
from scanflow.matching.inputs import (
    require_at_least,
    require_in,
    require_non_negative,
    require_positive,
)
from scanflow.matching.plicp import match_plicp
from scanflow.matching.surface import densify_scan

# Densification step of the overlap test: point-to-surface distances to ~1 cm.
OVERLAP_STEP_M = 0.02


@dataclass(frozen=True, eq=False)
class OverlapScorer:
    """Fraction of source points within a fixed gate of the target: the hypothesis criterion."""

    source: NDArray[np.float64]
    target_tree: cKDTree
    gate_m: float

    @staticmethod
    def build(
        source: NDArray[np.float64], target: NDArray[np.float64], gate_m: float
    ) -> OverlapScorer:
        """KD-tree over the target densified along its surfaces (sparse far points)."""
        if not gate_m > 0:
            raise ValueError(f"overlap gate_m must be > 0, got {gate_m}")
        return OverlapScorer(source, cKDTree(densify_scan(target, OVERLAP_STEP_M)), gate_m)

    def score(self, pose: Pose2D) -> float:
        """Fraction (0..1) of the source points, moved by `pose`, within the gate of the target."""
        d, _ = self.target_tree.query(pose.transform_points(self.source),
                                      distance_upper_bound=self.gate_m)
        return float(np.mean(d <= self.gate_m))


def pick_hypothesis(overlaps: list[float], switch_margin: float) -> int:
    """Index of the hypothesis to keep: the first (csm's best) unless another overlaps by more
    than `switch_margin` (a fraction of the source points) more."""
    best = int(np.argmax(overlaps))
    return best if overlaps[best] > overlaps[0] + switch_margin else 0


@register_method("csm+plicp", forwards_to=[match_plicp])
def match_csm_plicp(
    source: NDArray[np.float64],
    target: Target,
    guess: Pose2D,
    *,
    linear_m: float = 0.5,
    angular_rad: float = math.radians(20.0),
    resolution_m: float = 0.05,
    hypotheses: int = 3,
    suppress_m: float = 0.25,
    suppress_rad: float = math.radians(5.0),
    hypothesis_min_ratio: float = 0.6,
    overlap_gate_m: float = 0.1,
    switch_margin: float = 0.02,
    **plicp_options: float,
) -> MatchResult:
    """Search +-linear_m / +-angular_rad around `guess` with csm for up to `hypotheses` distinct
    peaks (suppress_m / suppress_rad apart, scoring >= hypothesis_min_ratio x the best), refine
    each with plicp, keep csm's best unless another refinement overlaps by > switch_margin more."""
    require_non_negative(
        linear_m=linear_m, angular_rad=angular_rad, suppress_m=suppress_m, suppress_rad=suppress_rad
    )
    require_positive(resolution_m=resolution_m, overlap_gate_m=overlap_gate_m)
    require_at_least(1, hypotheses=hypotheses)
    require_in(0.0, 1.0, hypothesis_min_ratio=hypothesis_min_ratio)
    coarse = match_csm(
        source, target, guess, linear_m=linear_m, angular_rad=angular_rad,
        resolution_m=resolution_m, candidates=hypotheses, suppress_m=suppress_m,
        suppress_rad=suppress_rad, candidate_min_ratio=hypothesis_min_ratio,
    )
    # A corridor's search still gives the basin across the corridor: plicp refines it and
    # reports its own conditioning.
    if not found_a_pose(coarse):
        return replace(coarse, method="csm+plicp")
    starts: list[Pose2D] = coarse.extra["candidates"]
    fines = [match_plicp(source, target, start, **plicp_options) for start in starts]
    overlaps = [math.nan] * len(fines)
    if len(fines) > 1:
        scorer = OverlapScorer.build(source, target_points(target), overlap_gate_m)
        # csm's best stands unless another refinement is ok and overlaps clearly more; its own
        # is ranked whenever it found a pose, however conditioned (along rows of trees the right
        # refinement is rightly degenerate, and a wrong basin's few matched points may look
        # well conditioned); any other refinement that is not ok ranks below it.
        overlaps = [
            scorer.score(f.pose) if f.ok or (i == 0 and f.status in CONDITIONED) else -1.0
            for i, f in enumerate(fines)
        ]
    best = pick_hypothesis(overlaps, switch_margin) if len(fines) > 1 else 0
    fine = fines[best]
    pose = fine.pose
    if fine.status is MatchStatus.DEGENERATE and fine.weak_direction is not None:
        # Along a direction the scans do not observe, the search's peak is a tie-break that
        # drifts with the scans' extents (to the window's edge along a corridor): keep the
        # guess's value there, the only information along it.
        pose = guess_along(fine.weak_direction, pose, guess, weak_length_m(fine.extra, source))
    return replace(
        fine,
        pose=pose,
        method="csm+plicp",
        iterations=fine.iterations + coarse.iterations,
        extra={
            **fine.extra,
            "csm_pose": starts[best],
            "csm_score": coarse.extra["candidate_scores"][best],
            "hypothesis": best,
            "overlaps": overlaps,
        },
    )
