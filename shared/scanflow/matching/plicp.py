"""Point-to-line ICP (Censi 2008, PL-ICP): each source point against the line fitted through
its nearest target point's neighbourhood (fitted once per target).

Cost sum_i rho(n_i . (T p_i - c_i)) with Cauchy weights, an adaptive association gate and a
Gauss-Newton step on the 3x3 normal equations per iteration. The whole iteration loop is one
numba function over a `GridIndex` (see correspondence.py for why); the Python side validates,
builds the target index and turns the outcome into a `MatchResult` with Censi's covariance.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.matching.api import (
    MatchResult,
    MatchStatus,
    check_point_inputs,
    failed,
    register_method,
    target_points,
)
from scanflow.matching.checks import (
    MapSurfaces,
    analyse_hessian,
    characteristic_length_m,
    guess_along,
    surface_conditioning,
    surfaces_of,
)
from scanflow.matching.correspondence import (
    MAD_TO_SIGMA,
    THIN_BELOW_DEG,
    GridArrays,
    GridIndex,
    TargetLines,
    adaptive_gate_m,
    grid_k_nearest,
    target_lines,
    thin_dense_target,
)
from scanflow.matching.covariance import line_fit_covariance, unknown_covariance
from scanflow.matching.inputs import (
    require_at_most,
    require_in,
    require_iterations,
    require_non_negative,
    require_positive,
)
from scanflow.matching.trust import fit_checked

MIN_PAIRS = 6
MAX_NORMAL_NEIGHBOURS = 64
# Solver outcome codes (shared with icp).
CONVERGED, MAX_ITER, TOO_FEW, SINGULAR = 0, 1, 2, 3


@njit(cache=True)
def _plicp_kernel(
    src: NDArray[np.float64],
    grid: GridArrays,
    normals: NDArray[np.float64],
    centres: NDArray[np.float64],
    line_ok: NDArray[np.bool_],
    pose0: NDArray[np.float64],
    gate_max_m: float,
    gate_min_m: float,
    cauchy_min_m: float,
    max_iterations: int,
    tol_m: float,
    tol_rad: float,
    max_step_m: float,
    max_step_rad: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], NDArray[np.float64],
           int, int]:
    n = len(src)
    x, y, th = pose0[0], pose0[1], pose0[2]
    gate = gate_max_m
    dist = np.empty(n)
    res = np.empty(n)
    jac = np.empty((n, 3))
    rows = np.empty(n, dtype=np.int64)
    assoc = np.full(n, -1, dtype=np.int64)
    weights = np.zeros(n)
    hess = np.zeros((3, 3))
    near_d2 = np.empty(1)
    near_j = np.empty(1, dtype=np.int64)
    code = MAX_ITER
    it = 0
    while it < max_iterations:
        it += 1
        c, s = math.cos(th), math.sin(th)
        m = 0
        for i in range(n):
            px = c * src[i, 0] - s * src[i, 1] + x
            py = s * src[i, 0] + c * src[i, 1] + y
            grid_k_nearest(grid, px, py, gate, near_d2, near_j)
            j, d2 = near_j[0], near_d2[0]
            if j < 0 or not line_ok[j]:
                continue
            nx, ny = normals[j, 0], normals[j, 1]
            dist[m] = math.sqrt(d2)
            res[m] = nx * (px - centres[j, 0]) + ny * (py - centres[j, 1])
            jac[m, 0] = nx
            jac[m, 1] = ny
            # d/dtheta of the pose's own parameters: the source turns about its origin (x, y),
            # not the target's (a lever arm growing with the distance from the target's origin).
            jac[m, 2] = nx * -(py - y) + ny * (px - x)
            rows[m] = i
            assoc[i] = j
            m += 1
        if m < MIN_PAIRS:
            code = TOO_FEW
            break
        scale = max(cauchy_min_m, MAD_TO_SIGMA * np.median(np.abs(res[:m])))
        hess[:, :] = 0.0
        g = np.zeros(3)
        weights[:] = 0.0
        for i in range(m):
            u = res[i] / scale
            w = 1.0 / (1.0 + u * u)
            weights[rows[i]] = w
            for r in range(3):
                g[r] += w * jac[i, r] * res[i]
                for q in range(3):
                    hess[r, q] += w * jac[i, r] * jac[i, q]
        if np.linalg.det(hess) <= 1e-12 * np.trace(hess) ** 3:
            code = SINGULAR
            break
        step = -np.linalg.solve(hess, g)
        t_norm = math.hypot(step[0], step[1])
        limit = max(t_norm / max_step_m, abs(step[2]) / max_step_rad, 1.0)
        step /= limit
        x, y, th = x + step[0], y + step[1], th + step[2]
        gate = adaptive_gate_m(dist[:m], gate_min_m, gate_max_m)
        if t_norm < tol_m and abs(step[2]) < tol_rad:
            code = CONVERGED
            break
        if it < max_iterations:  # the next iteration re-associates every point
            assoc[:] = -1
    return np.array([x, y, th]), hess, assoc, weights, it, code


@register_method("plicp")
@fit_checked
def match_plicp(
    source: NDArray[np.float64],
    target: object,
    guess: Pose2D,
    *,
    max_correspondence_m: float = 1.0,
    min_correspondence_m: float = 0.15,
    cauchy_min_m: float = 0.01,
    normal_neighbours: int = 8,
    normal_radius_m: float = 0.5,
    normal_fit_radius_m: float = 0.2,
    grid_cell_m: float = 0.25,
    max_iterations: int = 50,
    tolerance_m: float = 1e-3,
    tolerance_rad: float = 1e-3,
    max_step_m: float = 0.5,
    max_step_rad: float = 0.3,
    min_inlier_fraction: float = 0.2,
    thin_below_deg: float = THIN_BELOW_DEG,
) -> MatchResult:
    """Method "plicp": point-to-line ICP from `guess`; the accurate local 2D matcher. A target
    given as points denser than `thin_below_deg` between neighbours, seen from its origin, is
    thinned to that first (`thin_dense_target`; 0: never); a map's occupied cells are not."""
    require_positive(
        max_correspondence_m=max_correspondence_m, min_correspondence_m=min_correspondence_m,
        cauchy_min_m=cauchy_min_m, normal_radius_m=normal_radius_m,
        normal_fit_radius_m=normal_fit_radius_m, grid_cell_m=grid_cell_m,
        max_step_m=max_step_m, max_step_rad=max_step_rad,
    )
    require_at_most(normal_radius_m, normal_fit_radius_m=normal_fit_radius_m)
    require_in(2, MAX_NORMAL_NEIGHBOURS, normal_neighbours=normal_neighbours)
    require_iterations(max_iterations)
    require_non_negative(
        tolerance_m=tolerance_m, tolerance_rad=tolerance_rad, thin_below_deg=thin_below_deg
    )
    require_in(0.0, 1.0, min_inlier_fraction=min_inlier_fraction)
    tgt = target_points(target)
    bad = check_point_inputs("plicp", source, tgt, guess, MIN_PAIRS)
    if bad is not None:
        return bad
    if isinstance(target, np.ndarray):
        tgt = thin_dense_target(tgt, thin_below_deg)
    grid = GridIndex.build(tgt, grid_cell_m)
    lines = target_lines(grid, normal_neighbours, normal_radius_m, normal_fit_radius_m,
                         seen_from_origin=isinstance(target, np.ndarray))
    if lines.ok.sum() < MIN_PAIRS:
        return failed(
            "plicp", MatchStatus.TOO_FEW_POINTS, guess,
            f"only {int(lines.ok.sum())} target points have a line-like neighbourhood",
        )
    pose_arr, hess, assoc, weights, iterations, code = _plicp_kernel(
        source, grid.arrays, lines.normals, lines.centres, lines.ok, guess.to_array(),
        max_correspondence_m, min_correspondence_m, cauchy_min_m, max_iterations,
        tolerance_m, tolerance_rad, max_step_m, max_step_rad,
    )
    return line_match_result(
        "plicp", source, tgt, lines, guess, Pose2D.from_array(pose_arr), hess, assoc, weights,
        iterations, code, min_inlier_fraction, surfaces_of(target),
    )


def pair_covariance(
    source: NDArray[np.float64],
    target: NDArray[np.float64],
    lines: TargetLines,
    pose: Pose2D,
    assoc: NDArray[np.int64],
    weights: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Censi covariance of `pose` for source point i paired with target line assoc[i] (-1: none)."""
    paired = assoc >= 0
    if paired.sum() <= 3:
        return unknown_covariance()
    j = assoc[paired]
    moved = pose.transform_points(source[paired])
    normals, centres = lines.normals[j], lines.centres[j]
    residuals = np.sum(normals * (moved - centres), axis=1)
    return line_fit_covariance(
        moved, weights[paired], residuals, normals, centres, lines.neighbours[j],
        lines.spread_m2[j], target, np.array([pose.x, pose.y]),
    )


def line_match_result(
    method: str,
    source: NDArray[np.float64],
    target: NDArray[np.float64],
    lines: TargetLines,
    guess: Pose2D,
    pose: Pose2D,
    hessian: NDArray[np.float64],
    assoc: NDArray[np.int64],
    weights: NDArray[np.float64],
    iterations: int,
    code: int,
    min_inlier_fraction: float,
    surfaces: MapSurfaces | None,
) -> MatchResult:
    """Status, covariance and degeneracy of a solution scored on target lines (icp, plicp); a
    DEGENERATE pose keeps the guess's value along its weak direction. `surfaces`: the target's
    (`surfaces_of`), which judge the source's isolated two-point lines."""
    inliers = int(np.count_nonzero(assoc >= 0))
    if code == TOO_FEW:
        return failed(
            method, MatchStatus.NO_OVERLAP, guess,
            f"only {inliers} source points found a target line within the gate", iterations,
        )
    # Rotation scaled by the spread of the points paired with the target: the Hessian's.
    paired = assoc >= 0
    length_m = characteristic_length_m(source, paired)
    if code == SINGULAR:
        unconstrained = analyse_hessian(hessian, length_m).weak_direction
        singular = failed(
            method, MatchStatus.DEGENERATE, guess,
            "point-to-line Hessian is singular: no constraint along "
            f"{np.round(unconstrained, 3).tolist()}",
            iterations,
        )
        return replace(singular, weak_direction=unconstrained, extra={"length_m": length_m})
    cov = pair_covariance(source, target, lines, pose, assoc, weights)
    fraction = inliers / len(source)
    cond = analyse_hessian(hessian, length_m)
    status, message, weak = MatchStatus.OK, "", None
    if fraction < min_inlier_fraction:
        status = MatchStatus.NO_OVERLAP
        message = f"only {fraction:.0%} of source points matched (< {min_inlier_fraction:.0%})"
    elif cond.degenerate:
        status, weak = MatchStatus.DEGENERATE, cond.weak_direction
        message = (
            f"weakly constrained along {np.round(weak, 3).tolist()} "
            f"(eigenvalue ratio {cond.ratio:.1e}), e.g. a corridor"
        )
    elif (surface := surface_conditioning(source, paired, pose, length_m, surfaces)
          )[0] is not MatchStatus.OK:
        # The Hessian above holds the fitted normals' noise, which fakes a constraint along a
        # corridor (a near wall's dense points, 1 cm noise over a few cm): ask the surfaces,
        # the target's judging the source's isolated two-point lines.
        status, weak, message = surface
    elif code == MAX_ITER:
        status, message = MatchStatus.MAX_ITERATIONS, f"no convergence in {iterations} iterations"
    if weak is not None:
        # Along an unobserved direction the solution drifts with noise and the scans' extents
        # (plicp 0.5 m along the simulated corridor): the guess is the only information there.
        pose = guess_along(weak, pose, guess, length_m)
    return MatchResult(
        pose=pose,
        covariance=cov,
        score=fraction,
        iterations=iterations,
        converged=code == CONVERGED,
        status=status,
        method=method,
        message=message,
        weak_direction=weak,
        inliers=inliers,
        extra={} if weak is None else {"length_m": length_m},  # weak's rotation scale
    )
