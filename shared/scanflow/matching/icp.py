"""Point-to-point ICP: scipy cKDTree association, trimming plus an adaptive gate, and the
closed-form (SVD) step on the kept pairs each iteration; stops on step size or error change.

The textbook baseline. Its point-to-point cost cannot see a wall sliding along itself, so the
covariance and the degeneracy check use the point-to-line linearisation at the final pairs.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.matching.api import (
    MatchResult,
    check_point_inputs,
    register_method,
    target_points,
)
from scanflow.matching.checks import line_hessian
from scanflow.matching.correspondence import KDTreeIndex, adaptive_gate_m, trimmed_mask
from scanflow.matching.plicp import CONVERGED, MAX_ITER, MIN_PAIRS, TOO_FEW, line_match_result
from scanflow.matching.svd import rigid_transform_svd


@register_method("icp")
def match_icp(
    source: NDArray[np.float64],
    target: object,
    guess: Pose2D,
    *,
    max_correspondence_m: float = 1.0,
    min_correspondence_m: float = 0.15,
    keep_fraction: float = 0.9,
    max_iterations: int = 60,
    tolerance_m: float = 1e-3,
    tolerance_rad: float = 1e-3,
    relative_error_change: float = 1e-3,
    min_inlier_fraction: float = 0.2,
) -> MatchResult:
    """Method "icp": point-to-point ICP from `guess`."""
    tgt = target_points(target)
    bad = check_point_inputs("icp", source, tgt, guess, MIN_PAIRS)
    if bad is not None:
        return bad
    index = KDTreeIndex.build(tgt)
    pose, gate, code, previous_error = guess, max_correspondence_m, MAX_ITER, math.inf
    keep = np.zeros(len(source), dtype=bool)
    j = np.zeros(len(source), dtype=np.intp)
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        moved = pose.transform_points(source)
        dist, j = index.nearest(moved, gate)
        found = np.isfinite(dist)
        if found.sum() < MIN_PAIRS:
            code = TOO_FEW
            break
        keep = found.copy()
        keep[found] = trimmed_mask(dist[found], keep_fraction)
        step = rigid_transform_svd(moved[keep], tgt[j[keep]])
        pose = step * pose
        gate = adaptive_gate_m(dist[found], min_correspondence_m, max_correspondence_m)
        error = float(np.mean(dist[keep] ** 2))
        small_step = step.translation_norm() < tolerance_m and abs(step.theta) < tolerance_rad
        flat = abs(previous_error - error) <= relative_error_change * max(error, 1e-12)
        previous_error = error
        if small_step or flat:
            code = CONVERGED
            break
    if code == TOO_FEW:
        return line_match_result("icp", source, guess, pose, np.zeros((3, 3)), 0.0,
                                 int(found.sum()), iterations, code, min_inlier_fraction)
    moved = pose.transform_points(source[keep])
    q = tgt[j[keep]]
    normals = _pair_normals(index, q)
    residuals = np.sum(normals * (moved - q), axis=1)
    return line_match_result(
        "icp", source, guess, pose, line_hessian(moved, normals),
        float(residuals @ residuals), len(q), iterations, code, min_inlier_fraction,
    )


def _pair_normals(index: KDTreeIndex, q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit normal at each matched target point: perpendicular to its nearest other point."""
    _, nn = index.tree.query(q, k=2, workers=1)
    e = index.points[nn[:, 1]] - q
    e /= np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-12)
    return np.column_stack((-e[:, 1], e[:, 0]))
