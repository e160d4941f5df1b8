"""2D NDT scan matching (Biber & Strasser 2003; seed 2, part 3).

Maximise score(p) = sum_i sum_grids exp(-q^T S^-1 q / 2), q = T(p) x_i - mean of the cell
holding it, over the four overlapping grids. We minimise f = -score with Newton steps: the
analytic gradient and Hessian (including the second-derivative term q^T S^-1 d2q/dtheta2),
the Hessian made positive definite by flooring its eigenvalues, and a backtracking Armijo line
search.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.maps.ndt_cells import NDTCells, overlapping_cells
from scanflow.matching.api import MatchResult, MatchStatus, failed, register_method, target_points
from scanflow.matching.checks import analyse_hessian, characteristic_length_m, line_hessian
from scanflow.matching.covariance import unknown_covariance
from scanflow.matching.field_cost import (
    MIN_POINTS,
    LevelOutcome,
    check_inputs,
    converged_step,
    moved_points,
)

ARMIJO_C = 1e-4
PD_FLOOR_RATIO = 1e-3


@dataclass(frozen=True)
class NDTEvaluation:
    """f = -score, its gradient and Hessian, the information matrix and the hit count."""

    cost: float
    gradient: NDArray[np.float64]
    hessian: NDArray[np.float64]
    information: NDArray[np.float64]
    hits: int


def ndt_cost(
    grids: tuple[NDTCells, ...], points: NDArray[np.float64], pose: NDArray[np.float64]
) -> float:
    """-score only (for the line search)."""
    moved = moved_points(points, pose)
    total = 0.0
    for g in grids:
        k = g.lookup(moved)
        hit = k >= 0
        q = moved[hit] - g.means[k[hit]]
        a = np.einsum("nij,nj->ni", g.inv_covs[k[hit]], q)
        total -= float(np.exp(-0.5 * np.einsum("ni,ni->n", q, a)).sum())
    return total


def ndt_evaluate(
    grids: tuple[NDTCells, ...], points: NDArray[np.float64], pose: NDArray[np.float64]
) -> NDTEvaluation:
    """-score, analytic gradient and Hessian in (x, y, theta) at `pose`."""
    moved = moved_points(points, pose)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    jt_all = np.column_stack(
        (-s * points[:, 0] - c * points[:, 1], c * points[:, 0] - s * points[:, 1])
    )
    cost, grad, hess, info, hits = 0.0, np.zeros(3), np.zeros((3, 3)), np.zeros((3, 3)), 0
    for g in grids:
        k = g.lookup(moved)
        hit = k >= 0
        hits += int(np.count_nonzero(hit))
        inv = g.inv_covs[k[hit]]
        q = moved[hit] - g.means[k[hit]]
        jt = jt_all[hit]
        a = np.einsum("nij,nj->ni", inv, q)  # S^-1 q
        e = np.exp(-0.5 * np.einsum("ni,ni->n", q, a))
        # Columns of dq/dp: e_x, e_y, jt. a^T J:
        aj = np.column_stack((a[:, 0], a[:, 1], np.einsum("ni,ni->n", a, jt)))
        # J^T S^-1 J per point.
        sj = np.einsum("nij,nj->ni", inv, jt)
        jsj = np.empty((len(q), 3, 3))
        jsj[:, :2, :2] = inv
        jsj[:, :2, 2] = sj
        jsj[:, 2, :2] = sj
        jsj[:, 2, 2] = np.einsum("ni,ni->n", jt, sj)
        # d2q/dtheta2 = -(R x): its term a^T d2q only touches (theta, theta).
        second = np.zeros((len(q), 3, 3))
        second[:, 2, 2] = -np.einsum("ni,ni->n", a, moved[hit] - pose[:2])
        cost -= float(e.sum())
        grad += aj.T @ e
        hess += np.einsum("n,nij->ij", e, jsj - aj[:, :, None] * aj[:, None, :] + second)
        info += np.einsum("n,nij->ij", e, jsj)
    return NDTEvaluation(cost, grad, hess, info / len(grids), hits)


def surface_hessian(
    cells: NDTCells, points: NDArray[np.float64], pose: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Point-to-line Hessian with each hit cell's normal (its tightest axis).

    NDT's own information matrix constrains motion along a wall through the cells' finite
    extent, which hides a corridor; the surface normals show what the geometry observes.
    """
    moved = moved_points(points, pose)
    k = cells.lookup(moved)
    hit = k >= 0
    _, vecs = np.linalg.eigh(cells.inv_covs[k[hit]])
    return line_hessian(moved[hit] - pose[:2], vecs[:, :, 1])


def positive_definite(hessian: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """H with its eigenvalues floored at a fraction of the largest |eigenvalue|; None if H = 0."""
    vals, vecs = np.linalg.eigh(0.5 * (hessian + hessian.T))
    top = float(np.max(np.abs(vals)))
    if not math.isfinite(top) or top <= 0.0:
        return None
    vals = np.maximum(vals, PD_FLOOR_RATIO * top)
    return (vecs * vals) @ vecs.T


def newton_level(
    grids: tuple[NDTCells, ...],
    points: NDArray[np.float64],
    pose: NDArray[np.float64],
    max_iterations: int,
    translation_tol_m: float,
    rotation_tol_rad: float,
) -> LevelOutcome:
    """Newton iterations on one cell size until a step is small in translation and |rotation|."""
    ev = ndt_evaluate(grids, points, pose)
    if ev.hits < MIN_POINTS:
        return LevelOutcome(pose, 0, MatchStatus.NO_OVERLAP, f"only {ev.hits} point-cell hits")
    for it in range(1, max_iterations + 1):
        h = positive_definite(ev.hessian)
        if h is None:
            return LevelOutcome(pose, it, MatchStatus.ILL_CONDITIONED, "NDT Hessian is zero")
        step = -np.linalg.solve(h, ev.gradient)
        slope = float(ev.gradient @ step)
        alpha = 1.0
        while ndt_cost(grids, points, pose + alpha * step) > ev.cost + ARMIJO_C * alpha * slope:
            alpha *= 0.5
            if converged_step(alpha * step, translation_tol_m, rotation_tol_rad):
                break
        pose = pose + alpha * step
        if converged_step(alpha * step, translation_tol_m, rotation_tol_rad):
            return LevelOutcome(pose, it, None)
        ev = ndt_evaluate(grids, points, pose)
    return LevelOutcome(
        pose,
        max_iterations,
        MatchStatus.MAX_ITERATIONS,
        f"no convergence in {max_iterations} iterations",
    )


@register_method("ndt")
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
) -> MatchResult:
    """Newton's method with an Armijo line search, coarse to fine (cell size doubles per level)."""
    tgt = target_points(target)
    bad = check_inputs("ndt", source, tgt, guess)
    if bad is not None:
        return bad
    pose, total = guess.to_array(), 0
    for level in reversed(range(levels)):
        grids = overlapping_cells(tgt, cell_size_m * 2**level)
        if sum(len(g) for g in grids) == 0:
            return failed(
                "ndt",
                MatchStatus.EMPTY_MAP,
                guess,
                f"no {cell_size_m * 2**level} m cell holds enough target points",
            )
        outcome = newton_level(
            grids, source, pose, max_iterations, translation_tol_m, rotation_tol_rad
        )
        total += outcome.iterations
        if outcome.status is not None:
            return failed("ndt", outcome.status, guess, outcome.message, total)
        pose = outcome.pose
    ev = ndt_evaluate(grids, source, pose)
    cond = analyse_hessian(surface_hessian(grids[0], source, pose), characteristic_length_m(source))
    status, weak = (
        (MatchStatus.DEGENERATE, cond.weak_direction) if cond.degenerate else (MatchStatus.OK, None)
    )
    try:
        cov = np.linalg.inv(ev.information)
    except np.linalg.LinAlgError:
        cov = unknown_covariance()
    return MatchResult(
        pose=Pose2D.from_array(pose),
        covariance=cov,
        score=-ev.cost / (len(source) * len(grids)),
        iterations=total,
        converged=True,
        status=status,
        method="ndt",
        weak_direction=weak,
        inliers=ev.hits,
    )
