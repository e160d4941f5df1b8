"""Synthetic worlds made of wall segments and a ray caster, for matcher tests with ground truth."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.geometry import Pose2D

Segments = NDArray[np.float64]  # (S, 4): x0, y0, x1, y1


def room_segments() -> Segments:
    """An 8 m x 6 m room with an inner wall stub, a pillar and an alcove: no symmetry."""
    return np.array(
        [
            [-4, -3, 4, -3],
            [4, -3, 4, 1],
            [4, 1, 3, 1],
            [3, 1, 3, 3],
            [3, 3, -4, 3],
            [-4, 3, -4, -3],
            [-1, -3, -1, -1.5],
            [1.5, 0.5, 2.0, 0.5],
            [2.0, 0.5, 2.0, 1.0],
            [2.0, 1.0, 1.5, 1.0],
            [1.5, 1.0, 1.5, 0.5],
            [-4, 0.5, -2.5, 0.5],
        ],
        dtype=np.float64,
    )


def corridor_segments(length_m: float = 200.0, width_m: float = 2.0) -> Segments:
    """Two long parallel walls along x: x is unobservable for a short-range sensor."""
    h = width_m / 2
    return np.array([[-length_m, -h, length_m, -h], [-length_m, h, length_m, h]], dtype=np.float64)


def cast(
    segments: Segments,
    pose: Pose2D,
    beams: int = 360,
    fov_rad: float = 2 * np.pi,
    max_range_m: float = 10.0,
    noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
) -> NDArray[np.float64]:
    """Endpoints (sensor frame) of beams from `pose` hitting the nearest segment within range."""
    angles = -fov_rad / 2 + np.arange(beams) * fov_rad / beams
    d = np.column_stack((np.cos(angles + pose.theta), np.sin(angles + pose.theta)))
    a = segments[:, :2]
    e = segments[:, 2:] - a
    o = np.array([pose.x, pose.y])
    denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    w = a[None, :, :] - o
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / denom
        u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    r = np.where(hit, t, np.inf).min(axis=1)
    if noise_m > 0:
        r = r + (rng or np.random.default_rng(0)).normal(0.0, noise_m, r.shape)
    keep = np.isfinite(r) & (r < max_range_m)
    return np.column_stack((r * np.cos(angles), r * np.sin(angles)))[keep]


@pytest.fixture
def room() -> Segments:
    return room_segments()


@pytest.fixture
def corridor() -> Segments:
    return corridor_segments()


@pytest.fixture
def caster() -> Callable[..., NDArray[np.float64]]:
    return cast


def wall_points(segments: Segments, step_m: float = 0.02) -> NDArray[np.float64]:
    """Dense points along every segment (a map target in the world frame)."""
    pts = []
    for x0, y0, x1, y1 in segments:
        f = np.linspace(0, 1, max(int(np.hypot(x1 - x0, y1 - y0) / step_m), 2))
        pts.append(np.column_stack((x0 + f * (x1 - x0), y0 + f * (y1 - y0))))
    return np.vstack(pts)


@pytest.fixture
def room_map_points() -> NDArray[np.float64]:
    return wall_points(room_segments())


@pytest.fixture
def corridor_map_points() -> NDArray[np.float64]:
    """A 40 m corridor map: far longer than the sensor range."""
    return wall_points(corridor_segments(20.0))
