"""Pose covariance of a least-squares match: cov = sigma^2 H^-1 with sigma^2 = SSR / (n - 3).

Shared by the least-squares matchers (svd, gn, lm, ndt): pass the Gauss-Newton
Hessian H = J^T W J of the cost in (x, y, theta) at the solution, the weighted sum of squared
residuals and the number of residuals. Returns an infinite covariance when it cannot be
estimated (fewer than 4 residuals, singular H) rather than a wrong finite one.

For ICP on sampled scans sigma^2 H^-1 is 2-3x too confident (NEES 10-40 on simulated pairs):
it ignores the target points' noise shared by many residuals; icp and plicp use
`line_fit_covariance` (Censi 2007) instead, calibrated in test_plicp.py.
"""

from __future__ import annotations

import numpy as np
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



def pose_parameter_jacobian(pose_xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """d(x, y, theta) / d(left increment): maps a covariance of T <- Exp(d) T to the pose's own
    parameters, the convention of every `MatchResult.covariance`."""
    return np.array([[1.0, 0.0, -pose_xy[1]], [0.0, 1.0, pose_xy[0]], [0.0, 0.0, 1.0]])


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
    tangents = np.column_stack((normals[:, 1], -normals[:, 0]))
    jac = np.column_stack((normals, normals[:, 1] * moved[:, 0] - normals[:, 0] * moved[:, 1]))
    wj = jac * weights[:, None]
    hessian = wj.T @ jac
    # Residual derivative w.r.t. each neighbour q of the line: through the centroid (-n / k)
    # and through the normal's angle (first-order eigenvector perturbation of the scatter).
    used = neighbours >= 0
    count = used.sum(axis=1)
    q = target[np.where(used, neighbours, 0)] - centres[:, None, :]
    along = np.sum((moved - centres) * tangents, axis=1)
    dphi = (np.sum(q * tangents[:, None, :], axis=2)[..., None] * normals[:, None, :]
            + np.sum(q * normals[:, None, :], axis=2)[..., None] * tangents[:, None, :])
    d = -normals[:, None, :] / count[:, None, None] - (along / spread_m2)[:, None, None] * dphi
    d[~used] = 0.0
    rows, slots = np.nonzero(used)
    g_target = np.zeros((len(target), POSE_DOF, 2))
    np.add.at(g_target, neighbours[rows, slots], wj[rows][:, :, None] * d[rows, slots][:, None, :])
    noise_gain = wj.T @ wj + np.einsum("mab,mcb->ac", g_target, g_target)
    s = 1.0 + np.sum(d * d, axis=(1, 2))
    # Robust (MAD) spread of the residuals normalised by their noise gain: a weighted mean of
    # r^2 would be biased low by the Cauchy weights, a plain one inflated by the outliers.
    sigma2 = (MAD_TO_SIGMA * float(np.median(np.abs(residuals) / np.sqrt(s)))) ** 2
    sigma2 *= m / (m - POSE_DOF)
    try:
        h_inv = np.linalg.inv(hessian)
    except np.linalg.LinAlgError:
        return unknown_covariance()
    a = pose_parameter_jacobian(pose_xy) @ h_inv
    cov = sigma2 * (a @ noise_gain @ a.T)
    cov = 0.5 * (cov + cov.T)
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0.0):
        return unknown_covariance()
    return cov
