"""Point-to-point ICP: closest points of the target's surface on the compiled grid index,
trimming plus an adaptive gate, and the closed-form rigid step (2D Kabsch/Umeyama) on the kept
pairs each iteration; stops on step size or relative error change.

The textbook baseline, one numba loop like plicp (a cKDTree query from Python costs 0.1-0.3 ms
per iteration at these sizes). Besl & McKay pair each point with the closest point of the
target SHAPE, not of its samples: a scan's samples are 5-20 cm apart, and nearest-sample pairs
stall in fixed points 0.3-0.8 deg off on simulated pairs (wall samples alias onto each other).
So a scan target is densified along its surfaces and the loop runs to a tight step tolerance.
Its point-to-point cost cannot see a wall sliding along itself, so the degeneracy check and the
covariance use the lines of the original target points at the final pairs; the covariance adds
the offset from icp's pose to the point-to-line optimum (`line_optimum_offset`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.matching.api import MatchResult, check_point_inputs, register_method, target_points
from scanflow.matching.checks import line_hessian, surfaces_of
from scanflow.matching.correspondence import (
    THIN_BELOW_DEG,
    GridArrays,
    GridIndex,
    adaptive_gate_m,
    grid_k_nearest,
    grid_nearest_all,
    target_lines,
    thin_dense_target,
)
from scanflow.matching.inputs import (
    require_in,
    require_iterations,
    require_non_negative,
    require_positive,
)
from scanflow.matching.plicp import CONVERGED, MAX_ITER, MIN_PAIRS, TOO_FEW, line_match_result
from scanflow.matching.surface import densify_scan, surface_gap_m
from scanflow.matching.trust import fit_checked


@njit(cache=True)
def _icp_kernel(
    src: NDArray[np.float64],
    grid: GridArrays,
    pose0: NDArray[np.float64],
    gate_max_m: float,
    gate_min_m: float,
    keep_fraction: float,
    max_iterations: int,
    tol_m: float,
    tol_rad: float,
    relative_error_change: float,
) -> tuple[NDArray[np.float64], NDArray[np.int64], int, int]:
    tgt = grid[0]
    n = len(src)
    x, y, th = pose0[0], pose0[1], pose0[2]
    gate = gate_max_m
    moved = np.empty((n, 2))
    dist = np.empty(n)
    pair = np.full(n, -1, dtype=np.int64)
    near_d2 = np.empty(1)
    near_j = np.empty(1, dtype=np.int64)
    previous_error = np.inf
    code = MAX_ITER
    it = 0
    while it < max_iterations:
        it += 1
        c, s = math.cos(th), math.sin(th)
        found = 0
        for i in range(n):
            moved[i, 0] = c * src[i, 0] - s * src[i, 1] + x
            moved[i, 1] = s * src[i, 0] + c * src[i, 1] + y
            found += grid_k_nearest(grid, moved[i, 0], moved[i, 1], gate, near_d2, near_j)
            pair[i] = near_j[0]
            dist[i] = math.sqrt(near_d2[0])
        if found < MIN_PAIRS:
            code = TOO_FEW
            break
        # Trimmed ICP: keep the keep_fraction closest pairs.
        ranked = np.sort(dist)
        cut = ranked[max(math.ceil(keep_fraction * found), 1) - 1]
        msx = msy = mtx = mty = 0.0
        kept = 0
        for i in range(n):
            if pair[i] >= 0 and dist[i] <= cut:
                msx += moved[i, 0]
                msy += moved[i, 1]
                mtx += tgt[pair[i], 0]
                mty += tgt[pair[i], 1]
                kept += 1
            else:
                pair[i] = -1
        msx, msy, mtx, mty = msx / kept, msy / kept, mtx / kept, mty / kept
        # Closed form in 2D: the rotation angle of the centred cross-covariance.
        dot = 0.0
        cross = 0.0
        error = 0.0
        for i in range(n):
            if pair[i] >= 0:
                ax, ay = moved[i, 0] - msx, moved[i, 1] - msy
                bx, by = tgt[pair[i], 0] - mtx, tgt[pair[i], 1] - mty
                dot += ax * bx + ay * by
                cross += ax * by - ay * bx
                error += dist[i] * dist[i]
        error /= kept
        dth = math.atan2(cross, dot)
        cd, sd = math.cos(dth), math.sin(dth)
        dx = mtx - (cd * msx - sd * msy)
        dy = mty - (sd * msx + cd * msy)
        # Left-multiply the step: T <- step * T. Its size is how far the source's origin moved
        # ((dx, dy) is the target origin's, 250 m away 250 m per radian turned).
        x0, y0 = x, y
        x, y = cd * x - sd * y + dx, sd * x + cd * y + dy
        th = th + dth
        gate = adaptive_gate_m(dist[pair >= 0], gate_min_m, gate_max_m)
        small_step = math.hypot(x - x0, y - y0) < tol_m and abs(dth) < tol_rad
        flat = abs(previous_error - error) <= relative_error_change * max(error, 1e-12)
        previous_error = error
        if small_step or flat:
            code = CONVERGED
            break
    return np.array([x, y, th]), pair, it, code


@register_method("icp")
@fit_checked
def match_icp(
    source: NDArray[np.float64],
    target: object,
    guess: Pose2D,
    *,
    max_correspondence_m: float = 1.0,
    min_correspondence_m: float = 0.15,
    keep_fraction: float = 0.9,
    grid_cell_m: float = 0.1,
    surface_step_m: float | None = 0.02,
    max_iterations: int = 100,
    tolerance_m: float = 3e-4,
    tolerance_rad: float = 3e-4,
    relative_error_change: float = 1e-6,
    line_radius_m: float = 0.5,
    min_inlier_fraction: float = 0.2,
    thin_below_deg: float = THIN_BELOW_DEG,
) -> MatchResult:
    """Method "icp": point-to-point ICP from `guess`. A target given as points is a scan:
    thinned where denser than `thin_below_deg` between neighbours (`thin_dense_target`; 0:
    never), then densified every `surface_step_m` along its surfaces (None: its samples only);
    a map's occupied cells are used as they are."""
    require_positive(
        max_correspondence_m=max_correspondence_m, min_correspondence_m=min_correspondence_m,
        keep_fraction=keep_fraction, grid_cell_m=grid_cell_m, surface_step_m=surface_step_m,
        line_radius_m=line_radius_m,
    )
    require_in(0.0, 1.0, keep_fraction=keep_fraction, min_inlier_fraction=min_inlier_fraction)
    require_iterations(max_iterations)
    require_non_negative(
        tolerance_m=tolerance_m, tolerance_rad=tolerance_rad,
        relative_error_change=relative_error_change, thin_below_deg=thin_below_deg,
    )
    tgt = target_points(target)
    bad = check_point_inputs("icp", source, tgt, guess, MIN_PAIRS)
    if bad is not None:
        return bad
    scan = isinstance(target, np.ndarray)  # a point target is one scan seen from its origin
    if scan:
        tgt = thin_dense_target(tgt, thin_below_deg)
    surface = tgt
    if surface_step_m is not None and scan:
        surface = densify_scan(tgt, surface_step_m, "surface_step_m")
    pose_arr, pair, iterations, code = _icp_kernel(
        source, GridIndex.build(surface, grid_cell_m).arrays, guess.to_array(),
        max_correspondence_m, min_correspondence_m, keep_fraction, max_iterations, tolerance_m,
        tolerance_rad, relative_error_change,
    )
    pose = Pose2D.from_array(pose_arr)
    grid = GridIndex.build(tgt, grid_cell_m)
    lines = target_lines(grid, seen_from_origin=scan)
    # Judge the solution on the lines of the original target points nearest to the kept pairs
    # (a scan's: as far off as one of its surfaces spans between two points).
    kept = np.flatnonzero(pair >= 0)
    paired = pose.transform_points(source[kept])
    reach = np.full(len(kept), line_radius_m)
    if scan:
        reach = np.maximum(reach, surface_gap_m(np.hypot(*paired.T)))
    assoc = np.full(len(source), -1, dtype=np.int64)
    assoc[kept] = grid_nearest_all(grid.arrays, paired, reach)
    assoc[(assoc >= 0) & ~lines.ok[assoc]] = -1
    lined = assoc >= 0
    moved = paired[lined[kept]]  # the lined pairs are among the kept ones, already moved
    normals, centres = lines.normals[assoc[lined]], lines.centres[assoc[lined]]
    # In the pose's own (x, y, theta): the source turns about its origin, R p = moved - t.
    hessian = line_hessian(moved - [pose.x, pose.y], normals)
    result = line_match_result(
        "icp", source, tgt, lines, guess, pose, hessian, assoc, lined.astype(np.float64),
        iterations, code, min_inlier_fraction, surfaces_of(target),
    )
    if not np.all(np.isfinite(result.covariance)):
        return result
    bias = line_optimum_offset(moved, normals, centres, hessian, pose)
    return replace(result, covariance=result.covariance + np.outer(bias, bias))


def line_optimum_offset(
    moved: NDArray[np.float64],
    normals: NDArray[np.float64],
    centres: NDArray[np.float64],
    hessian: NDArray[np.float64],
    pose: Pose2D,
) -> NDArray[np.float64]:
    """How far (x, y, theta) the point-to-line optimum lies from `pose`: one Gauss-Newton step
    on the residuals n . (p - c) of the moved source points against their target lines.

    Censi's covariance is that of the line optimum; point-to-point ICP stops off it (walls
    slide, the pairs' tangential residuals pull). With b this offset, cov + b b^T is the mean
    squared error about the truth: if the line optimum's error e ~ N(0, C), the expected NEES
    of b + e under C + b b^T is exactly 3.
    """
    residuals = np.sum(normals * (moved - centres), axis=1)
    turned = moved - [pose.x, pose.y]  # R p: `hessian` is in the pose's own parameters
    jac = np.column_stack((normals, normals[:, 1] * turned[:, 0] - normals[:, 0] * turned[:, 1]))
    # Least squares: a singular H (points at one spot, which the checks judge) raises nothing.
    return -np.linalg.lstsq(hessian, jac.T @ residuals, rcond=None)[0]
