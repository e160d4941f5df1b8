"""Point-to-line ICP (Censi 2008, PL-ICP): each source point against the line through its
nearest target point, with the line's normal fitted once from the target's neighbours.

Cost sum_i rho(n_i . (T p_i - q_i)) with Cauchy weights, an adaptive association gate and a
Gauss-Newton step on the 3x3 normal equations per iteration. The whole iteration loop is one
numba function over a `GridIndex` (see correspondence.py for why); the Python side validates,
builds the target index and turns the outcome into a `MatchResult`.
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
from scanflow.matching.checks import analyse_hessian, characteristic_length_m
from scanflow.matching.correspondence import (
    MAD_TO_SIGMA,
    GridIndex,
    adaptive_gate_m,
    grid_nearest,
    target_normals,
)
from scanflow.matching.covariance import least_squares_covariance

MIN_PAIRS = 6
# Solver outcome codes (shared with icp).
CONVERGED, MAX_ITER, TOO_FEW, SINGULAR = 0, 1, 2, 3


@njit(cache=True)
def _plicp_kernel(
    src: NDArray[np.float64],
    tgt: NDArray[np.float64],
    normals: NDArray[np.float64],
    normal_ok: NDArray[np.bool_],
    order: NDArray[np.int64],
    starts: NDArray[np.int64],
    ox: float,
    oy: float,
    cell: float,
    cols: int,
    rows: int,
    pose0: NDArray[np.float64],
    gate_max_m: float,
    gate_min_m: float,
    cauchy_min_m: float,
    max_iterations: int,
    tol_m: float,
    tol_rad: float,
    max_step_m: float,
    max_step_rad: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], float, int, int, int]:
    n = len(src)
    x, y, th = pose0[0], pose0[1], pose0[2]
    gate = gate_max_m
    dist = np.empty(n)
    res = np.empty(n)
    jx = np.empty(n)
    jy = np.empty(n)
    jt = np.empty(n)
    hess = np.zeros((3, 3))
    ssr = 0.0
    m = 0
    code = MAX_ITER
    it = 0
    while it < max_iterations:
        it += 1
        c, s = math.cos(th), math.sin(th)
        m = 0
        for i in range(n):
            px = c * src[i, 0] - s * src[i, 1] + x
            py = s * src[i, 0] + c * src[i, 1] + y
            j, d2 = grid_nearest(tgt, order, starts, ox, oy, cell, cols, rows, px, py, gate)
            if j < 0 or not normal_ok[j]:
                continue
            nx, ny = normals[j, 0], normals[j, 1]
            dist[m] = math.sqrt(d2)
            res[m] = nx * (px - tgt[j, 0]) + ny * (py - tgt[j, 1])
            jx[m] = nx
            jy[m] = ny
            jt[m] = nx * -py + ny * px
            m += 1
        if m < MIN_PAIRS:
            code = TOO_FEW
            break
        scale = max(cauchy_min_m, MAD_TO_SIGMA * np.median(np.abs(res[:m])))
        hess[:, :] = 0.0
        g = np.zeros(3)
        ssr = 0.0
        for i in range(m):
            u = res[i] / scale
            w = 1.0 / (1.0 + u * u)
            a = (jx[i], jy[i], jt[i])
            for r in range(3):
                g[r] += w * a[r] * res[i]
                for q in range(3):
                    hess[r, q] += w * a[r] * a[q]
            ssr += w * res[i] * res[i]
        if np.linalg.det(hess) <= 1e-12 * np.trace(hess) ** 3:
            code = SINGULAR
            break
        step = -np.linalg.solve(hess, g)
        t_norm = math.hypot(step[0], step[1])
        limit = max(t_norm / max_step_m, abs(step[2]) / max_step_rad, 1.0)
        step /= limit
        # Left-multiply the increment: T <- Exp(step) * T.
        cd, sd = math.cos(step[2]), math.sin(step[2])
        x, y = cd * x - sd * y + step[0], sd * x + cd * y + step[1]
        th = th + step[2]
        gate = adaptive_gate_m(dist[:m], gate_min_m, gate_max_m)
        if t_norm < tol_m and abs(step[2]) < tol_rad:
            code = CONVERGED
            break
    return np.array([x, y, th]), hess, ssr, m, it, code


@register_method("plicp")
def match_plicp(
    source: NDArray[np.float64],
    target: object,
    guess: Pose2D,
    *,
    max_correspondence_m: float = 1.0,
    min_correspondence_m: float = 0.15,
    cauchy_min_m: float = 0.01,
    normal_neighbours: int = 2,
    normal_radius_m: float = 0.5,
    grid_cell_m: float = 0.25,
    max_iterations: int = 50,
    tolerance_m: float = 1e-3,
    tolerance_rad: float = 1e-3,
    max_step_m: float = 0.5,
    max_step_rad: float = 0.3,
    min_inlier_fraction: float = 0.2,
) -> MatchResult:
    """Method "plicp": point-to-line ICP from `guess`; the accurate local 2D matcher."""
    tgt = target_points(target)
    bad = check_point_inputs("plicp", source, tgt, guess, MIN_PAIRS)
    if bad is not None:
        return bad
    grid = GridIndex.build(tgt, grid_cell_m)
    normals, normal_ok = target_normals(grid, normal_neighbours, normal_radius_m)
    if normal_ok.sum() < MIN_PAIRS:
        return failed(
            "plicp", MatchStatus.TOO_FEW_POINTS, guess,
            f"only {int(normal_ok.sum())} target points have a line-like neighbourhood",
        )
    pose_arr, hess, ssr, inliers, iterations, code = _plicp_kernel(
        source, tgt, normals, normal_ok, grid.order, grid.starts, grid.origin_x_m,
        grid.origin_y_m, grid.cell_m, grid.cols, grid.rows, guess.to_array(),
        max_correspondence_m, min_correspondence_m, cauchy_min_m, max_iterations,
        tolerance_m, tolerance_rad, max_step_m, max_step_rad,
    )
    return line_match_result(
        "plicp", source, guess, Pose2D.from_array(pose_arr), hess, ssr, inliers, iterations,
        code, min_inlier_fraction,
    )


def line_match_result(
    method: str,
    source: NDArray[np.float64],
    guess: Pose2D,
    pose: Pose2D,
    hessian: NDArray[np.float64],
    ssr: float,
    inliers: int,
    iterations: int,
    code: int,
    min_inlier_fraction: float,
) -> MatchResult:
    """Status, covariance and degeneracy of a point-to-line solution (shared by icp and plicp)."""
    if code == TOO_FEW:
        return failed(
            method, MatchStatus.NO_OVERLAP, guess,
            f"only {inliers} source points found a target line within the gate", iterations,
        )
    if code == SINGULAR:
        weak = analyse_hessian(hessian, characteristic_length_m(source)).weak_direction
        singular = failed(
            method, MatchStatus.DEGENERATE, guess,
            f"point-to-line Hessian is singular: no constraint along {np.round(weak, 3).tolist()}",
            iterations,
        )
        return replace(singular, weak_direction=weak)
    cov = least_squares_covariance(hessian, ssr, inliers)
    fraction = inliers / len(source)
    cond = analyse_hessian(hessian, characteristic_length_m(source))
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
    elif code == MAX_ITER:
        status, message = MatchStatus.MAX_ITERATIONS, f"no convergence in {iterations} iterations"
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
    )
