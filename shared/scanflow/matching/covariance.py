"""Pose covariance of a least-squares match: cov = sigma^2 H^-1 with sigma^2 = SSR / (n - 3).

Shared by the least-squares matchers (svd, gn, lm, ndt): pass the Gauss-Newton
Hessian H = J^T W J of the cost in (x, y, theta) at the solution, the weighted sum of squared
residuals and the number of residuals. Returns an infinite covariance when it cannot be
estimated (fewer than 4 residuals, singular H) rather than a wrong finite one.

For ICP on sampled scans sigma^2 H^-1 is 2-3x too confident (NEES 10-40 on simulated pairs):
it ignores the target points' noise shared by many residuals; icp and plicp use
`line_fit_covariance` (Censi 2007) instead (icp adds its offset from the point-to-line
optimum), calibrated in test_plicp.py and test_icp.py.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.matching.correspondence import MAD_TO_SIGMA

POSE_DOF = 3


def unknown_covariance() -> NDArray[np.float64]:
    """The covariance of a pose nothing is known about."""
    return np.diag([np.inf, np.inf, np.inf])


def residual_variance(sum_sq_residuals: float, n_residuals: int) -> float:
    """Unbiased residual variance SSR / (n - 3); inf when n <= 3."""
    if n_residuals <= POSE_DOF:
        return float("inf")
    return float(sum_sq_residuals) / (n_residuals - POSE_DOF)


def least_squares_covariance(
    hessian: NDArray[np.float64], sum_sq_residuals: float, n_residuals: int
) -> NDArray[np.float64]:
    """3x3 covariance sigma^2 H^-1 of the pose (x, y, theta) at a least-squares optimum."""
    h = np.asarray(hessian, dtype=np.float64)
    if h.shape != (3, 3):
        raise ValueError(f"hessian must be 3x3, got shape {h.shape}")
    sigma2 = residual_variance(sum_sq_residuals, n_residuals)
    if not np.isfinite(sigma2) or not np.all(np.isfinite(h)):
        return unknown_covariance()
    try:
        h_inv = np.linalg.inv(h)
    except np.linalg.LinAlgError:
        return unknown_covariance()
    cov = sigma2 * 0.5 * (h_inv + h_inv.T)
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0.0):
        return unknown_covariance()
    return cov



@njit(cache=True)
def pose_parameter_jacobian(pose_xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """d(x, y, theta) / d(left increment): maps a covariance of T <- Exp(d) T to the pose's own
    parameters, the convention of every `MatchResult.covariance`. Compiled: `_sandwich` uses
    it on every match."""
    jacobian = np.eye(3)
    jacobian[0, 2] = -pose_xy[1]
    jacobian[1, 2] = pose_xy[0]
    return jacobian


def line_fit_covariance(
    moved: NDArray[np.float64],
    weights: NDArray[np.float64],
    residuals: NDArray[np.float64],
    normals: NDArray[np.float64],
    centres: NDArray[np.float64],
    neighbours: NDArray[np.int64],
    spread_m2: NDArray[np.float64],
    target: NDArray[np.float64],
    pose_xy: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Censi's (2007) closed-form covariance of a point-to-line fit, in (x, y, theta).

    cov = H^-1 (sum_z g_z g_z^T) H^-1 sigma^2, g_z = d(gradient)/dz, over the noise z of every
    source point AND of every target point, which enters a residual through its line (centroid
    and normal of the neighbours' fit). Target points shared by several residuals make them
    correlated, which sigma^2 H^-1 ignores (it was 2-3x too confident). Point noise is taken
    isotropic, sigma^2 from the residuals: E[r_i^2] = sigma^2 s_i (robustly, by the MAD).
    Row i: moved source point p_i, its Cauchy weight and residual n_i . (p_i - c_i), its line.
    """
    m = len(moved)
    if m <= POSE_DOF:
        return unknown_covariance()
    hessian, noise_gain, s = _censi_terms(
        np.ascontiguousarray(moved, dtype=np.float64),
        np.ascontiguousarray(weights, dtype=np.float64),
        np.ascontiguousarray(normals, dtype=np.float64),
        np.ascontiguousarray(centres, dtype=np.float64),
        np.ascontiguousarray(neighbours, dtype=np.int64),
        np.ascontiguousarray(spread_m2, dtype=np.float64),
        np.ascontiguousarray(target, dtype=np.float64),
    )
    try:
        cov, ok = _sandwich(hessian, noise_gain, np.ascontiguousarray(residuals, np.float64), s,
                            np.ascontiguousarray(pose_xy, np.float64))
    except np.linalg.LinAlgError:  # H singular, or not finite
        return unknown_covariance()
    return cov if ok else unknown_covariance()


@njit(cache=True)
def _sandwich(hessian, noise_gain, residuals, s, pose_xy):  # type: ignore[no-untyped-def]
    """(cov, ok): Censi's sigma^2 A G A^T, A = d(params)/d(increment) H^-1, in one compiled
    call; ok False when it is not a covariance (non-finite, a negative variance)."""
    # Robust (MAD) spread of the residuals normalised by their noise gain: a weighted mean of
    # r^2 would be biased low by the Cauchy weights, a plain one inflated by the outliers.
    m = len(residuals)
    sigma2 = (MAD_TO_SIGMA * np.median(np.abs(residuals) / np.sqrt(s))) ** 2 * (m / (m - POSE_DOF))
    a = pose_parameter_jacobian(pose_xy) @ np.linalg.inv(hessian)
    cov = sigma2 * (a @ noise_gain @ a.T)
    cov = 0.5 * (cov + cov.T)
    ok = np.all(np.isfinite(cov)) and np.all(np.diag(cov) >= 0.0)
    return cov, ok


@njit(cache=True)
def _censi_terms(moved, weights, normals, centres, neighbours, spread_m2, target):  # type: ignore[no-untyped-def]
    """One pass over the residuals: Hessian J^T W J, noise gain sum_z g_z g_z^T, and each
    residual's noise scale s_i = 1 + |dr_i/d(target points)|^2 (see `line_fit_covariance`).

    A residual's derivative w.r.t. a neighbour q of its line goes through the centroid
    (-n / k) and through the normal's angle (first-order eigenvector perturbation)."""
    m = moved.shape[0]
    hessian = np.zeros((3, 3))
    gain = np.zeros((3, 3))
    g_target = np.zeros((target.shape[0], 3, 2))
    s = np.ones(m)
    for i in range(m):
        n0, n1 = normals[i, 0], normals[i, 1]
        t0, t1 = n1, -n0
        px, py = moved[i, 0], moved[i, 1]
        jac = (n0, n1, n1 * px - n0 * py)
        w = weights[i]
        for a in range(3):
            for b in range(3):
                hessian[a, b] += w * jac[a] * jac[b]
                gain[a, b] += w * w * jac[a] * jac[b]
        count = 0
        for k in range(neighbours.shape[1]):
            if neighbours[i, k] >= 0:
                count += 1
        if count == 0:
            continue
        cx, cy = centres[i, 0], centres[i, 1]
        along = ((px - cx) * t0 + (py - cy) * t1) / spread_m2[i]
        acc = 0.0
        for k in range(neighbours.shape[1]):
            j = neighbours[i, k]
            if j < 0:
                continue
            qx, qy = target[j, 0] - cx, target[j, 1] - cy
            qt = qx * t0 + qy * t1
            qn = qx * n0 + qy * n1
            d0 = -n0 / count - along * (qt * n0 + qn * t0)
            d1 = -n1 / count - along * (qt * n1 + qn * t1)
            acc += d0 * d0 + d1 * d1
            for a in range(3):
                g_target[j, a, 0] += w * jac[a] * d0
                g_target[j, a, 1] += w * jac[a] * d1
        s[i] = 1.0 + acc
    for j in range(target.shape[0]):
        for a in range(3):
            for c in range(3):
                gain[a, c] += (
                    g_target[j, a, 0] * g_target[j, c, 0] + g_target[j, a, 1] * g_target[j, c, 1]
                )
    return hessian, gain, s
