"""Vectorised ray casting of many rays against all wall segments at once."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D

_PARALLEL_EPS = 1e-12
# Slack on the segment parameter u: a ray aimed at the joint of two walls finds it at u just
# past 1 on one and just below 0 on the other in floating point, and would slip out between them.
_END_EPS = 1e-9


def cast_rays(
    origins: NDArray[np.float64],
    angles_rad: NDArray[np.float64],
    segments: NDArray[np.float64],
    range_max_m: float,
) -> NDArray[np.float64]:
    """Distance (N,) from each origin (N, 2) along its world angle to the nearest segment (M, 4).

    Segments are rows (x0, y0, x1, y1). Rays that hit nothing within `range_max_m` get inf.
    Broadcasts rays x segments, fine for ~1500 rays x ~200 segments.
    """
    dx, dy = np.cos(angles_rad)[:, None], np.sin(angles_rad)[:, None]
    ox, oy = origins[:, 0:1], origins[:, 1:2]
    ax, ay = segments[None, :, 0], segments[None, :, 1]
    ex, ey = segments[None, :, 2] - ax, segments[None, :, 3] - ay
    denom = dx * ey - dy * ex
    wx, wy = ax - ox, ay - oy
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wx * ey - wy * ex) / denom
        u = (wx * dy - wy * dx) / denom
    hit = (np.abs(denom) > _PARALLEL_EPS) & (t > 0.0) & (u >= -_END_EPS) & (u <= 1.0 + _END_EPS)
    distance = np.where(hit, t, np.inf).min(axis=1)
    distance[distance > range_max_m] = np.inf
    return distance


def static_scan(
    segments: NDArray[np.float64],
    pose: Pose2D,
    angles_rad: NDArray[np.float64],
    range_max_m: float,
    noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
) -> NDArray[np.float64]:
    """Valid endpoints (N, 2), in the sensor's own frame, of a scan taken standing still at
    `pose` (world) with beams at `angles_rad`: no motion distortion, optional Gaussian range
    noise (drawn from `rng`, seed 0 by default). Rays that hit nothing are left out."""
    ranges = cast_rays(np.tile([pose.x, pose.y], (len(angles_rad), 1)), angles_rad + pose.theta,
                       segments, range_max_m)
    if noise_m > 0:
        ranges = ranges + (rng or np.random.default_rng(0)).normal(0.0, noise_m, ranges.shape)
    ok = np.isfinite(ranges)
    a = angles_rad[ok]
    return np.column_stack((ranges[ok] * np.cos(a), ranges[ok] * np.sin(a)))
