"""Pose covariance of a least-squares match: cov = sigma^2 H^-1 with sigma^2 = SSR / (n - 3).

Shared by every least-squares matcher (svd, icp, plicp, gn, lm, ndt): pass the Gauss-Newton
Hessian H = J^T W J of the cost in (x, y, theta) at the solution, the weighted sum of squared
residuals and the number of residuals. Returns an infinite covariance when it cannot be
estimated (fewer than 4 residuals, singular H) rather than a wrong finite one.

Known limit (simulated pairs, test_plicp.py): for ICP on sampled scans this is about 2-3x too
confident in standard deviation (NEES ~10-40, not 3): association and sampling bias dominate the
error and no residual-based formula sees them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

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

