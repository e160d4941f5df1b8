"""The Hector cost sum_i (1 - M(T p_i))^2 on a likelihood field, shared by `gn` and `lm`.

Residual r_i = 1 - M(S_i(pose)), S_i the source point moved by the pose; its Jacobian is
-grad M(S_i) * dS_i/dpose with dS/dpose = [[1, 0, -s x - c y], [0, 1, c x - s y]] (seed 2,
part 1). The pose is updated additively in (x, y, theta). Both methods run coarse to fine over
a likelihood-field pyramid and end with the same checks, so that machinery lives here too.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from scanflow.geometry import Pose2D
from scanflow.maps.field import LikelihoodField
from scanflow.maps.grid import GridSpec
from scanflow.matching.api import MatchResult, MatchStatus, failed
from scanflow.matching.checks import DEGENERATE_RATIO, analyse_hessian, characteristic_length_m
from scanflow.matching.covariance import least_squares_covariance

MIN_POINTS = 10
GAP_BASE_M = 0.05
GAP_PER_RANGE = 0.06  # about 3.5 degrees of arc: wider gaps are occlusion edges
# The coarse levels may lead into a worse basin: a final fine-level cost this many times the
# initial one means the match ran away from the guess.
DIVERGENCE_RATIO = 1.5


@dataclass(frozen=True)
class FieldLinearisation:
    """Cost, Gauss-Newton Hessian J^T J and gradient J^T r of the field cost at one pose."""

    cost: float
    hessian: NDArray[np.float64]
    gradient: NDArray[np.float64]
    hits: int


@dataclass(frozen=True)
class LevelOutcome:
    """Where one pyramid level's iterations ended and, if they failed, why."""

    pose: NDArray[np.float64]
    iterations: int
    status: MatchStatus | None
    message: str = ""


LevelSolver = Callable[
    [LikelihoodField, NDArray[np.float64], NDArray[np.float64], int], LevelOutcome
]


def moved_points(points: NDArray[np.float64], pose: NDArray[np.float64]) -> NDArray[np.float64]:
    """Source points moved by the (x, y, theta) pose vector."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = np.empty_like(points)
    out[:, 0] = c * points[:, 0] - s * points[:, 1] + pose[0]
    out[:, 1] = s * points[:, 0] + c * points[:, 1] + pose[1]
    return out


def field_cost(
    field: LikelihoodField, points: NDArray[np.float64], pose: NDArray[np.float64]
) -> float:
    """sum_i (1 - M(T p_i))^2: what gn and lm minimise."""
    value, _ = field.sample(moved_points(points, pose))
    r = 1.0 - value
    return float(r @ r)


def linearise(
    field: LikelihoodField, points: NDArray[np.float64], pose: NDArray[np.float64]
) -> FieldLinearisation:
    """Cost, H = J^T J and g = J^T r at `pose` (step: H dx = -g)."""
    value, grad = field.sample(moved_points(points, pose))
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dtheta_x = -s * points[:, 0] - c * points[:, 1]
    dtheta_y = c * points[:, 0] - s * points[:, 1]
    jac = -np.column_stack((grad[:, 0], grad[:, 1], grad[:, 0] * dtheta_x + grad[:, 1] * dtheta_y))
    r = 1.0 - value
    return FieldLinearisation(float(r @ r), jac.T @ jac, jac.T @ r, int(np.count_nonzero(value)))


def field_pyramid(
    target: object, levels: int, resolution_m: float, sigma_m: float
) -> list[LikelihoodField]:
    """Likelihood fields from coarse to fine: a map's own pyramid, or one built from points.

    Level k of a point target has cell size and sigma scaled by 2**k, widening the basin of
    convergence at the coarse levels while the finest level keeps the accuracy.
    """
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    if hasattr(target, "likelihood_pyramid"):
        fields = list(target.likelihood_pyramid(levels))
    else:
        pts = np.asarray(target, dtype=np.float64)
        fields = [points_field(pts, resolution_m * 2**k, sigma_m * 2**k) for k in range(levels)]
    return sorted(fields, key=lambda f: -f.spec.resolution_m)


def densify_scan(points: NDArray[np.float64], step_m: float) -> NDArray[np.float64]:
    """Add points every `step_m` between consecutive points that are close for their range.

    A scan's far points are sparser than the field's sigma, which would leave bumps along
    walls (a false constraint along corridors). Gaps up to GAP_BASE_M + GAP_PER_RANGE * range
    are filled; larger ones are occlusion edges and stay open.
    """
    if len(points) < 2:
        return points
    a, b = points[:-1], points[1:]
    gap = np.hypot(*(b - a).T)
    max_gap = GAP_BASE_M + GAP_PER_RANGE * np.minimum(np.hypot(*a.T), np.hypot(*b.T))
    n = np.where(gap < max_gap, np.maximum(np.ceil(gap / step_m).astype(np.int64) - 1, 0), 0)
    if not n.any():
        return points
    seg = np.repeat(np.arange(len(n)), n)
    f = (np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n) + 1) / np.repeat(n + 1, n)
    return np.vstack((points, a[seg] + f[:, None] * (b[seg] - a[seg])))


def points_field(
    points: NDArray[np.float64], resolution_m: float, sigma_m: float
) -> LikelihoodField:
    """Field exp(-d^2 / 2 sigma^2) with d measured to the nearest cell's mean point, not its centre.

    Snapping walls to cell centres biases the optimum by up to half a cell; keeping each
    cell's mean point makes the field's ridge follow the points to sub-cell accuracy.
    """
    points = densify_scan(points, resolution_m)
    spec = GridSpec.covering(points, resolution_m, 4.0 * sigma_m + 2.0 * resolution_m)
    n_cells = spec.rows * spec.cols
    cells = spec.world_to_cell(points)
    flat = cells[:, 0] * spec.cols + cells[:, 1]
    count = np.bincount(flat, minlength=n_cells)
    occupied = count > 0
    safe = np.maximum(count, 1)
    mean_x = np.bincount(flat, points[:, 0], n_cells) / safe
    mean_y = np.bincount(flat, points[:, 1], n_cells) / safe
    nearest = ndimage.distance_transform_edt(
        ~occupied.reshape(spec.shape), return_distances=False, return_indices=True
    )
    nearest_flat = nearest[0] * spec.cols + nearest[1]
    centre_x = spec.origin_x_m + (np.arange(spec.cols) + 0.5) * resolution_m
    centre_y = spec.origin_y_m + (np.arange(spec.rows) + 0.5) * resolution_m
    dx = centre_x[None, :] - mean_x[nearest_flat]
    dy = centre_y[:, None] - mean_y[nearest_flat]
    return LikelihoodField(spec, np.exp((dx * dx + dy * dy) * (-0.5 / sigma_m**2)), sigma_m)


def is_empty_target(target: object) -> bool:
    """True for a point set with no points or a map whose field holds nothing."""
    if hasattr(target, "likelihood_field"):
        return bool(target.likelihood_field(0).is_empty)
    return len(np.asarray(target)) == 0


def converged_step(
    step: NDArray[np.float64], translation_tol_m: float, rotation_tol_rad: float
) -> bool:
    """Both the translation and the |rotation| of a step are below their tolerances."""
    return math.hypot(step[0], step[1]) < translation_tol_m and abs(step[2]) < rotation_tol_rad


def solve_well_determined(
    hessian: NDArray[np.float64], rhs: NDArray[np.float64], length_m: float
) -> NDArray[np.float64] | None:
    """H^-1 rhs restricted to the directions H constrains (eigenvalues scaled by the point spread).

    A corridor leaves one direction unconstrained: the step is zero along it instead of
    arbitrary. Returns None when fewer than two directions are constrained (ill-conditioned).
    """
    scale = np.array([1.0, 1.0, 1.0 / length_m])
    hs = hessian * np.outer(scale, scale)
    vals, vecs = np.linalg.eigh(0.5 * (hs + hs.T))
    if not np.all(np.isfinite(vals)) or vals[-1] <= 0.0:
        return None
    keep = vals > DEGENERATE_RATIO * vals[-1]
    if np.count_nonzero(keep) < 2:
        return None
    v = vecs[:, keep]
    return scale * (v @ ((v.T @ (scale * rhs)) / vals[keep]))


def check_inputs(
    method: str, source: NDArray[np.float64], target: object, guess: Pose2D
) -> MatchResult | None:
    """TOO_FEW_POINTS or EMPTY_MAP result when there is nothing to match, else None."""
    if len(source) < MIN_POINTS:
        return failed(
            method,
            MatchStatus.TOO_FEW_POINTS,
            guess,
            f"source has {len(source)} points, need >= {MIN_POINTS}",
        )
    if is_empty_target(target):
        return failed(method, MatchStatus.EMPTY_MAP, guess, "target holds no points")
    return None


def run_coarse_to_fine(
    method: str,
    source: NDArray[np.float64],
    target: object,
    guess: Pose2D,
    solve_level: LevelSolver,
    levels: int,
    resolution_m: float,
    sigma_m: float,
) -> MatchResult:
    """Validate, build the pyramid, run `solve_level` per level (coarse first), assess."""
    bad = check_inputs(method, source, target, guess)
    if bad is not None:
        return bad
    pyramid = field_pyramid(target, levels, resolution_m, sigma_m)
    pose = guess.to_array()
    start_cost = field_cost(pyramid[-1], source, pose)
    total = 0
    for index, field in enumerate(pyramid):
        if np.count_nonzero(field.sample(moved_points(source, pose))[0]) < MIN_POINTS:
            return failed(
                method,
                MatchStatus.NO_OVERLAP,
                guess,
                f"fewer than {MIN_POINTS} points fall on the field at level {index}",
                total,
            )
        outcome = solve_level(field, source, pose, index == len(pyramid) - 1)
        total += outcome.iterations
        if outcome.status is not None:
            return failed(method, outcome.status, guess, outcome.message, total)
        pose = outcome.pose
    end_cost = field_cost(pyramid[-1], source, pose)
    if end_cost > DIVERGENCE_RATIO * start_cost:
        return failed(
            method,
            MatchStatus.DIVERGED,
            guess,
            f"fine-level cost rose from {start_cost:.3g} to {end_cost:.3g}",
            total,
        )
    return assess_field_match(method, pyramid[-1], source, pose, total)


def assess_field_match(
    method: str,
    field: LikelihoodField,
    source: NDArray[np.float64],
    pose: NDArray[np.float64],
    iterations: int,
) -> MatchResult:
    """Covariance sigma^2 H^-1 and the degeneracy check at the final pose on the finest field."""
    lin = linearise(field, source, pose)
    cond = analyse_hessian(lin.hessian, characteristic_length_m(source))
    status, message, weak = MatchStatus.OK, "", None
    if cond.degenerate:
        status, weak = MatchStatus.DEGENERATE, cond.weak_direction
        message = f"one direction unconstrained (eigenvalue ratio {cond.ratio:.2e})"
    return MatchResult(
        pose=Pose2D.from_array(pose),
        covariance=least_squares_covariance(lin.hessian, lin.cost, lin.hits),
        score=1.0 - lin.cost / len(source),
        iterations=iterations,
        converged=True,
        status=status,
        method=method,
        message=message,
        weak_direction=weak,
        inliers=lin.hits,
    )
