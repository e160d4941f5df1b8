"""Synthetic worlds made of wall segments and a ray caster, for matcher tests with ground truth."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.geometry import Pose2D, angle_diff
from scanflow.matching import match
from scanflow.sim import (
    ConstantVelocityTrajectory,
    LidarModel,
    SimConfig,
    get_world,
    measure,
    simulate,
)

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
    r, angles = r[keep], angles[keep]  # beams that miss (r = inf) would give inf * 0 = nan
    return np.column_stack((r * np.cos(angles), r * np.sin(angles)))


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


def scan_points(world: str, pose: Pose2D, seed: int, noise_m: float = 0.01) -> NDArray[np.float64]:
    """Valid endpoints of a static 360-beam sweep from `pose` in a `scanflow.sim` world."""
    lidar = LidarModel(beams=360, fov_deg=360.0, range_noise_m=noise_m)
    still = ConstantVelocityTrajectory(pose, 0.0, 0.0)
    rng = np.random.default_rng(seed)
    return measure(lidar, still, get_world(world).segments, 0.0, rng).scan.points()


def simulated_nees(method: str, trials: int = 60, seed: int = 11) -> list[float]:
    """NEES of `method`'s pose against the truth over seeded pairs in the "rooms" world (2 cm
    range noise, up to 0.2 m and ~3 deg apart, guess off by 7 cm / 1.1 deg); failed matches
    are left out. A calibrated covariance gives a mean near 3."""
    rng = np.random.default_rng(seed)
    nees = []
    for trial in range(trials):
        base = Pose2D(rng.uniform(2, 13), rng.uniform(1.5, 6.5), rng.uniform(-math.pi, math.pi))
        moved = base * Pose2D(rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.normal(0, 0.05))
        target = scan_points("rooms", base, 2 * trial, noise_m=0.02)
        source = scan_points("rooms", moved, 2 * trial + 1, noise_m=0.02)
        truth = moved.relative_to(base)
        r = match(source, target, truth * Pose2D(0.05, -0.05, 0.02), method=method)
        if not r.ok:
            continue
        dtheta = angle_diff(r.pose.theta, truth.theta)
        v = np.array([r.pose.x - truth.x, r.pose.y - truth.y, dtheta])
        nees.append(float(v @ np.linalg.solve(r.covariance, v)))
    return nees


@pytest.fixture(scope="session")
def corridor_pairs() -> list[tuple[np.ndarray, np.ndarray, Pose2D]]:
    """(source, target, truth) of sweeps 0.5 s apart along the simulator's corridor, there and
    back (the turn at its end left out: x is the corridor's axis in every frame), exactly
    deskewed, 1 cm range noise, a 270-deg lidar: neither end is in range for most of them."""
    frames = list(simulate(SimConfig(world="corridor", duration_s=60.0, seed=0)))[20::5]
    return [(b.true_points, a.true_points, b.true_pose.relative_to(a.true_pose))
            for a, b in itertools.pairwise(frames)
            if max(abs(math.sin(a.true_pose.theta)), abs(math.sin(b.true_pose.theta))) < 0.05]


class _Map:
    """A map target: its occupied points, in the map's frame."""

    def __init__(self, points: NDArray[np.float64]) -> None:
        self.points = points

    def likelihood_field(self, level: int = 0) -> object:
        raise AssertionError("point methods use occupied_points()")

    def occupied_points(self) -> NDArray[np.float64]:
        return self.points


def assert_far_map_matches_as_near(method: str, offset_m: float) -> None:
    """The same room as a map target at the origin and `offset_m` away: same status, the same
    pose shifted (1 mm), the same covariance (5 %)."""
    segments = room_segments()
    truth = Pose2D(0.5, -0.5, 0.3)
    source = cast(segments, truth, noise_m=0.01)
    shift = Pose2D(offset_m, 0.6 * offset_m, 0.0)
    start = truth * Pose2D(0.05, -0.04, 0.02)
    near = match(source, _Map(wall_points(segments)), start, method=method)
    far = match(source, _Map(shift.transform_points(wall_points(segments))), shift * start,
                method=method)
    assert near.ok and far.status is near.status, far.message
    assert (shift * near.pose).relative_to(far.pose).translation_norm() < 1e-3
    assert np.allclose(far.covariance, near.covariance, rtol=0.05)
