"""SE(2) exponential and logarithm: motion under a constant body-frame twist.

A robot moving with constant forward/lateral speed and yaw rate follows a circular arc, not a
chord; `se2_exp` gives that arc exactly. Used by the constant-velocity model and the simulator.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.geometry import normalize_angles

_SMALL_ANGLE_RAD = 1e-6


def _arc_coefficients(
    phi_rad: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """sin(phi)/phi and (1 - cos(phi))/phi, with their Taylor series near zero."""
    small = np.abs(phi_rad) < _SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, phi_rad)
    a = np.where(small, 1.0 - phi_rad**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, phi_rad / 2.0, (1.0 - np.cos(safe)) / safe)
    return a, b


def se2_exp(twist: ArrayLike) -> NDArray[np.float64]:
    """Relative poses (N, 3) reached by integrating twists (N, 3) = (dx, dy, dtheta) over unit time.

    Row i is the pose after moving with body velocity (dx, dy) and yaw rate dtheta for one unit.
    """
    xi = np.atleast_2d(np.asarray(twist, dtype=np.float64))
    if xi.shape[-1] != 3:
        raise ValueError(f"twist must have 3 columns (dx, dy, dtheta), got shape {xi.shape}")
    a, b = _arc_coefficients(xi[:, 2])
    out = np.empty_like(xi)
    out[:, 0] = a * xi[:, 0] - b * xi[:, 1]
    out[:, 1] = b * xi[:, 0] + a * xi[:, 1]
    out[:, 2] = normalize_angles(xi[:, 2])
    return out


def se2_log(poses_xyt: ArrayLike) -> NDArray[np.float64]:
    """Twists (N, 3) whose `se2_exp` gives the relative poses (N, 3), heading on the short arc."""
    p = np.atleast_2d(np.asarray(poses_xyt, dtype=np.float64))
    if p.shape[-1] != 3:
        raise ValueError(f"poses must have 3 columns (x, y, theta), got shape {p.shape}")
    phi = normalize_angles(p[:, 2])
    a, b = _arc_coefficients(phi)
    det = a * a + b * b
    out = np.empty_like(p)
    out[:, 0] = (a * p[:, 0] + b * p[:, 1]) / det
    out[:, 1] = (-b * p[:, 0] + a * p[:, 1]) / det
    out[:, 2] = phi
    return out
