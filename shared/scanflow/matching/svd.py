"""Closed-form rigid alignment for KNOWN correspondences (source[i] <-> target[i]), weighted.

Arun/Umeyama (first seed, part 2): centre both sets, H = sum w q_i q'_i^T = U S V^T, R = V D U^T
with D = diag(1, det(V U^T)) so a reflection (det = -1) is never returned, t = p' - R p.
Registered `paired`: `match` keeps the rows as given, and a pair is used only when both of its
points are finite (dropping each array's NaN rows apart would shift every pair between them).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.matching.api import (
    MatchInputError,
    MatchResult,
    MatchStatus,
    failed,
    register_method,
)
from scanflow.matching.checks import analyse_hessian, characteristic_length_m
from scanflow.matching.covariance import least_squares_covariance


def rigid_transform_svd(
    source: NDArray[np.float64],
    target: NDArray[np.float64],
    weights: NDArray[np.float64] | None = None,
) -> Pose2D:
    """The rotation + translation minimising sum w_i |target_i - (R source_i + t)|^2."""
    w = np.ones(len(source)) if weights is None else weights
    w_sum = float(w.sum())
    mu_s = (w @ source) / w_sum
    mu_t = (w @ target) / w_sum
    h = (source - mu_s).T @ ((target - mu_t) * w[:, None])
    u, _, vt = np.linalg.svd(h)
    v = vt.T
    d = np.diag([1.0, np.sign(np.linalg.det(v @ u.T)) or 1.0])
    r = v @ d @ u.T
    t = mu_t - r @ mu_s
    return Pose2D(float(t[0]), float(t[1]), math.atan2(r[1, 0], r[0, 0]))


def point_hessian(points: NDArray[np.float64], weights: NDArray[np.float64]) -> NDArray[np.float64]:
    """Gauss-Newton Hessian of sum w |R p + t - q|^2 in the pose's (x, y, theta), given the
    rotated source points R p (d(R p + t)/dtheta = R' p turns them about the source's origin)."""
    w_sum = float(weights.sum())
    sx, sy = weights @ points
    sq = float(weights @ np.sum(points * points, axis=1))
    return np.array([[w_sum, 0.0, -sy], [0.0, w_sum, sx], [-sy, sx, sq]])


@register_method("svd", paired=True)
def match_svd(
    source: NDArray[np.float64],
    target: NDArray[np.float64],
    guess: Pose2D,
    *,
    weights: NDArray[np.float64] | None = None,
) -> MatchResult:
    """Method "svd": one closed-form step; `initial_guess` is ignored (the solution is global).
    source[i] pairs with target[i] (and weights[i]); a pair with a non-finite point is left out."""
    if not isinstance(target, np.ndarray):
        raise MatchInputError("svd needs a target point array with known correspondences")
    if len(source) != len(target):
        raise MatchInputError(
            f"svd needs source and target of equal length (known correspondences), "
            f"got {len(source)} and {len(target)}"
        )
    try:
        w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MatchInputError(f"weights must be {len(source)} numbers, got {weights!r}") from exc
    if w.shape != (len(source),) or not np.all(np.isfinite(w)) or np.any(w < 0.0):
        raise MatchInputError(f"weights must be {len(source)} finite values >= 0, got {w!r}")
    finite = np.all(np.isfinite(source), axis=1) & np.all(np.isfinite(target), axis=1)
    used = finite & (w > 0.0)
    if used.sum() < 2:
        return failed(
            "svd", MatchStatus.TOO_FEW_POINTS, guess, f"{used.sum()} finite weighted pairs < 2"
        )
    pose = rigid_transform_svd(source[used], target[used], w[used])
    moved = pose.transform_points(source[used])
    sq = np.sum((moved - target[used]) ** 2, axis=1)
    hessian = point_hessian(moved - [pose.x, pose.y], w[used])
    cov = least_squares_covariance(hessian, float(w[used] @ sq), 2 * int(used.sum()))
    status, message, weak = MatchStatus.OK, "", None
    cond = analyse_hessian(hessian, characteristic_length_m(moved))
    if cond.degenerate:
        status, message = MatchStatus.DEGENERATE, "the points coincide: rotation unobservable"
        weak = cond.weak_direction
    return MatchResult(
        pose=pose,
        covariance=cov,
        score=float(np.sqrt(np.mean(sq))),
        iterations=1,
        converged=status is MatchStatus.OK,
        status=status,
        method="svd",
        message=message,
        weak_direction=weak,
        inliers=int(used.sum()),
    )
