"""2D NDT scan matching (Biber & Strasser 2003; seed 2, part 3).

Maximise score(p) = sum_i sum_grids exp(-q^T S^-1 q / 2), q = T(p) x_i - mean of the cell
holding it, over the four overlapping grids. We minimise f = -score with Newton steps: the
analytic gradient and Hessian (including the second-derivative term q^T S^-1 d2q/dtheta2),
the Hessian made positive definite by flooring its eigenvalues, and a backtracking Armijo line
search.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.maps.ndt_cells import OverlappingCells
from scanflow.matching.api import MatchResult, MatchStatus, failed, register_method, target_points
from scanflow.matching.checks import (
    analyse_hessian,
    characteristic_length_m,
    guess_along,
    line_hessian,
)
from scanflow.matching.covariance import unknown_covariance
from scanflow.matching.field_cost import (
    MAX_LEVELS,
    MIN_POINTS,
    LevelOutcome,
    check_inputs,
    converged_step,
    moved_points,
)
from scanflow.matching.inputs import (
    require_grid_cells,
    require_in,
    require_iterations,
    require_non_negative,
    require_positive,
)
from scanflow.matching.surface import densify_scan
from scanflow.matching.trust import fit_checked

ARMIJO_C = 1e-4
GRIDS = 4  # the paper's overlapping grids
PD_FLOOR_RATIO = 1e-3
MIN_CELL_M, MAX_CELL_M = 0.01, 10.0  # the finest cell size's range
# A source point pins the pose only within this many sigmas of its cell (`surface_hessian`).
MATCHED_SIGMAS = 2.0


@dataclass(frozen=True)
class NDTEvaluation:
    """f = -score, its gradient and Hessian, the information matrix and the hit count."""

    cost: float
    gradient: NDArray[np.float64]
    hessian: NDArray[np.float64]
    information: NDArray[np.float64]
    hits: int


@njit(cache=True)
def _ndt_accumulate(index, origin, half, means, inv_covs, points, pose, with_derivatives):  # type: ignore[no-untyped-def]
    """-score, gradient, Hessian, information (summed over the 4 grids) and hits in one pass.

    A point's cells in the four grids are the 2 x 2 blocks starting at its half-cell minus
    (0 or 1, 0 or 1): see OverlappingCells.
    """
    rows, cols = index.shape
    c, s = math.cos(pose[2]), math.sin(pose[2])
    cost, hits = 0.0, 0
    grad = np.zeros(3)
    hess = np.zeros((3, 3))
    info = np.zeros((3, 3))
    jsj = np.empty((3, 3))
    for i in range(points.shape[0]):
        px, py = points[i, 0], points[i, 1]
        mx, my = c * px - s * py + pose[0], s * px + c * py + pose[1]
        jx, jy = -s * px - c * py, c * px - s * py  # d(moved)/dtheta
        hc = math.floor((mx - origin[0]) / half)
        hr = math.floor((my - origin[1]) / half)
        for g in range(4):
            row, col = hr - g // 2, hc - g % 2
            if row < 0 or col < 0 or row >= rows or col >= cols:
                continue
            k = index[row, col]
            if k < 0:
                continue
            hits += 1
            qx, qy = mx - means[k, 0], my - means[k, 1]
            a00, a01, a11 = inv_covs[k, 0, 0], inv_covs[k, 0, 1], inv_covs[k, 1, 1]
            ax, ay = a00 * qx + a01 * qy, a01 * qx + a11 * qy  # S^-1 q
            e = math.exp(-0.5 * (qx * ax + qy * ay))
            cost -= e
            if not with_derivatives:
                continue
            aj = (ax, ay, ax * jx + ay * jy)  # a^T dq/dp
            sjx, sjy = a00 * jx + a01 * jy, a01 * jx + a11 * jy  # S^-1 dq/dtheta
            jsj[0, 0], jsj[0, 1], jsj[1, 1] = a00, a01, a11
            jsj[1, 0] = a01
            jsj[0, 2] = jsj[2, 0] = sjx
            jsj[1, 2] = jsj[2, 1] = sjy
            jsj[2, 2] = jx * sjx + jy * sjy
            for a in range(3):
                grad[a] += e * aj[a]
                for b in range(3):
                    hess[a, b] += e * (jsj[a, b] - aj[a] * aj[b])
                    info[a, b] += e * jsj[a, b]
            # d2q/dtheta2 = -(R x): its term a^T d2q only touches (theta, theta).
            hess[2, 2] -= e * (ax * (mx - pose[0]) + ay * (my - pose[1]))
    return cost, grad, hess, info, hits


def _run(
    cells: OverlappingCells,
    points: NDArray[np.float64],
    pose: NDArray[np.float64],
    derivatives: bool,
) -> tuple[float, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], int]:
    return _ndt_accumulate(
        cells.index,
        np.array([cells.origin_x_m, cells.origin_y_m]),
        cells.half_size_m,
        cells.means,
        cells.inv_covs,
        points,
        np.asarray(pose, dtype=np.float64),
        derivatives,
    )


def ndt_cost(
    cells: OverlappingCells, points: NDArray[np.float64], pose: NDArray[np.float64]
) -> float:
    """-score only (for the line search)."""
    return float(_run(cells, points, pose, False)[0])


def ndt_evaluate(
    cells: OverlappingCells, points: NDArray[np.float64], pose: NDArray[np.float64]
) -> NDTEvaluation:
    """-score, analytic gradient and Hessian in (x, y, theta) at `pose`."""
    cost, grad, hess, info, hits = _run(cells, points, pose, True)
    return NDTEvaluation(float(cost), grad, hess, info / GRIDS, int(hits))


def surface_hessian(
    cells: OverlappingCells, points: NDArray[np.float64], pose: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Point-to-line Hessian with each matched cell's normal (its tightest axis), unshifted grid,
    and which points count in it.

    NDT's own information matrix constrains motion along a wall through the cells' finite
    extent, which hides a corridor; the surface normals show what the geometry observes. A
    point counts within MATCHED_SIGMAS of its cell's Gaussian: a far end wall's points 20 cm
    off still land in its cells, but do not pin the pose along the corridor.
    """
    moved = moved_points(points, pose)
    k = cells.lookup(moved)[:, 0]
    hit = k >= 0
    q = moved[hit] - cells.means[k[hit]]
    hit[hit] = np.einsum("ni,nij,nj->n", q, cells.inv_covs[k[hit]], q) <= MATCHED_SIGMAS**2
    inv = cells.inv_covs[k[hit]]
    # The tightest axis is the inverse covariance's major axis: closed form for 2 x 2.
    phi = 0.5 * np.arctan2(2.0 * inv[:, 0, 1], inv[:, 0, 0] - inv[:, 1, 1])
    hessian = line_hessian(moved[hit] - pose[:2], np.column_stack((np.cos(phi), np.sin(phi))))
    return hessian, hit


@njit(cache=True)
def _floored(hessian, ratio):  # type: ignore[no-untyped-def]
    """(ok, H with eigenvalues floored at ratio * max |eigenvalue|): see positive_definite."""
    out = np.zeros((3, 3))
    if not np.all(np.isfinite(hessian)):
        return False, out
    vals, vecs = np.linalg.eigh(0.5 * (hessian + hessian.T))
    top = np.max(np.abs(vals))
    if top <= 0.0:
        return False, out
    for k in range(3):
        v = max(vals[k], ratio * top)
        for a in range(3):
            for b in range(3):
                out[a, b] += vecs[a, k] * v * vecs[b, k]
    return True, out


def positive_definite(hessian: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """H with its eigenvalues floored at a fraction of the largest |eigenvalue|; None if H = 0."""
    ok, floored = _floored(np.asarray(hessian, dtype=np.float64), PD_FLOOR_RATIO)
    return floored if ok else None


def newton_level(
    cells: OverlappingCells,
    points: NDArray[np.float64],
    pose: NDArray[np.float64],
    max_iterations: int,
    translation_tol_m: float,
    rotation_tol_rad: float,
    reach_m: float,
) -> LevelOutcome:
    """Newton iterations on one cell size until a step is small in translation and |rotation|.

    A level whose converged pose lies over `reach_m` (the coarsest cell size) from where it
    started is a STEP_LIMIT: the cells' Gaussians pull only within about a cell, so such a
    slide has left its basin for a look-alike one (the simulator's rooms, 4 m apart, drew a
    0.3 m guess 4 m away on 2 m cells, status ok). Checked at the level's end, so a path that
    swings out and comes back stands."""
    start = pose
    ev = ndt_evaluate(cells, points, pose)
    if ev.hits < MIN_POINTS:
        return LevelOutcome(pose, 0, MatchStatus.NO_OVERLAP, f"only {ev.hits} point-cell hits")
    for it in range(1, max_iterations + 1):
        h = positive_definite(ev.hessian)
        if h is None:
            return LevelOutcome(pose, it, MatchStatus.ILL_CONDITIONED, "NDT Hessian is zero")
        step = cast(NDArray[np.float64], -np.linalg.solve(h, ev.gradient))  # stub: floating[Any]
        slope = float(ev.gradient @ step)
        alpha = 1.0
        while ndt_cost(cells, points, pose + alpha * step) > ev.cost + ARMIJO_C * alpha * slope:
            alpha *= 0.5
            if converged_step(alpha * step, translation_tol_m, rotation_tol_rad):
                break
        pose = pose + alpha * step
        if converged_step(alpha * step, translation_tol_m, rotation_tol_rad):
            moved_m = math.hypot(pose[0] - start[0], pose[1] - start[1])
            if moved_m > reach_m:
                return LevelOutcome(pose, it, MatchStatus.STEP_LIMIT,
                                    f"moved {moved_m:.2f} m on {reach_m:g} m cells (at most "
                                    "the coarsest cell)")
            return LevelOutcome(pose, it, None)
        ev = ndt_evaluate(cells, points, pose)
    return LevelOutcome(
        pose,
        max_iterations,
        MatchStatus.MAX_ITERATIONS,
        f"no convergence in {max_iterations} iterations",
    )


def _target_cells(
    target: object, finest_m: float, coarsest_m: float, surface_step_m: float | None
) -> tuple[Callable[[float], OverlappingCells], NDArray[np.float64]]:
    """(overlapping cells of a given size, points whose absence means an empty target).

    A map's own cells (`overlapping_ndt_cells`) and, for emptiness, its coarsest cells' means
    (so it need not list its occupied points); else cells built from the target's points, a
    scan's filled every `surface_step_m` along its surfaces first (None: its samples only),
    within MAX_GRID_CELLS half-cells of `finest_m` (`require_grid_cells`).
    """
    kept = getattr(target, "overlapping_ndt_cells", None)
    if kept is not None:
        return kept, kept(coarsest_m).means
    points = target_points(target)
    if len(points):
        cols, rows = np.ptp(points, axis=0) / (0.5 * finest_m) + 3  # a spare half-cell a side
        require_grid_cells(rows, cols, f"cells of cell_size_m {finest_m:g}")
    if isinstance(target, np.ndarray) and surface_step_m is not None:
        points = densify_scan(points, surface_step_m, "surface_step_m")
    return (lambda size: OverlappingCells.from_points(points, size)), points


@register_method("ndt")
@fit_checked
def match_ndt(
    source: NDArray[np.float64],
    target: object,
    guess: Pose2D,
    *,
    cell_size_m: float = 0.5,
    levels: int = 3,
    max_iterations: int = 30,
    translation_tol_m: float = 1e-4,
    rotation_tol_rad: float = 1e-4,
    surface_step_m: float | None = 0.1,
) -> MatchResult:
    """Newton's method with an Armijo line search, coarse to fine (cell size doubles per level),
    the finest level also run from the guess (the lower finest cost wins).

    A map target serves its cells kept current incrementally, on its lattice anchor; a point
    set's are built per call, anchored at the origin. A point target is a scan: filled every
    `surface_step_m` along its surfaces first (None: its samples only), since the paper's cells
    need 3+ points each and beams 1 deg apart sample a wall 20 m away only every 35 cm.
    """
    require_positive(cell_size_m=cell_size_m, surface_step_m=surface_step_m)
    # Cells describe surfaces: a 1 km one allocated without end, a 1e-300 m one overflowed, a
    # 30 m one held a whole room and said ok anywhere in it (a fuzzing audit).
    require_in(MIN_CELL_M, MAX_CELL_M, cell_size_m=cell_size_m)
    require_in(1, MAX_LEVELS, levels=levels)
    require_iterations(max_iterations)
    require_non_negative(translation_tol_m=translation_tol_m, rotation_tol_rad=rotation_tol_rad)
    reach_m = cell_size_m * 2 ** (levels - 1)  # the coarsest cell size
    cells_at, held = _target_cells(target, cell_size_m, reach_m, surface_step_m)
    bad = check_inputs("ndt", source, held, guess)
    if bad is not None:
        return bad
    pose, total = guess.to_array(), 0
    for level in reversed(range(levels)):
        cells = cells_at(cell_size_m * 2**level)
        if len(cells) == 0:
            return failed(
                "ndt",
                MatchStatus.EMPTY_MAP,
                guess,
                f"no {cell_size_m * 2**level} m cell holds enough target points",
            )
        outcome = newton_level(
            cells, source, pose, max_iterations, translation_tol_m, rotation_tol_rad, reach_m
        )
        total += outcome.iterations
        if outcome.status is not None:
            return failed("ndt", outcome.status, guess, outcome.message, total)
        pose = outcome.pose
    if levels > 1:
        # Coarse cells widen the basin but also pull along a weakly observed direction: along
        # a corridor, sliding back puts more far points in 2 m cells, and the finest level
        # stayed where the slide left it (20.9 % of the simulated corridor's pairs trusted yet
        # wrong). The finest cost is the objective, so it also judges a start at the guess.
        alt = newton_level(cells, source, guess.to_array(), max_iterations, translation_tol_m,
                           rotation_tol_rad, reach_m)
        total += alt.iterations
        if alt.status is None and ndt_cost(cells, source, alt.pose) < ndt_cost(cells, source, pose):
            pose = alt.pose
    hessian, counted = surface_hessian(cells, source, pose)
    length_m = characteristic_length_m(source, counted)  # the spread of the points that count
    cond = analyse_hessian(hessian, length_m)
    status, weak = MatchStatus.OK, None
    if cond.degenerate:
        # The guess is the only information along an unobserved direction (as for the others).
        status, weak = MatchStatus.DEGENERATE, cond.weak_direction
        pose = guess_along(weak, Pose2D.from_array(pose), guess, length_m).to_array()
    ev = ndt_evaluate(cells, source, pose)
    try:
        cov = cast(NDArray[np.float64], np.linalg.inv(ev.information))  # stub: floating[Any]
    except np.linalg.LinAlgError:
        cov = unknown_covariance()
    return MatchResult(
        pose=Pose2D.from_array(pose),
        covariance=cov,
        score=-ev.cost / (len(source) * GRIDS),
        iterations=total,
        converged=True,
        status=status,
        method="ndt",
        weak_direction=weak,
        inliers=ev.hits,
        extra={} if weak is None else {"length_m": length_m},  # weak's rotation scale
    )
