"""True robot motion: exact poses and body-frame twists at any time, vectorised.

Both trajectories hold the body twist piecewise constant, so between knots the robot moves on an
exact arc (`se2_exp`) and `pose_at` is exact at every time, not a resampled approximation.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.geometry import Pose2D, compose_arrays, normalize_angle, se2_exp
from scanflow.sim.world import World


class Trajectory(Protocol):
    """The robot's true motion over time."""

    def pose_at(self, times_s: ArrayLike) -> NDArray[np.float64]:
        """True poses (N, 3) (x, y, theta) at the given times."""
        ...

    def twist_at(self, times_s: ArrayLike) -> NDArray[np.float64]:
        """Body-frame velocities (N, 3) (vx m/s, vy m/s, omega rad/s) at the given times."""
        ...


class ConstantVelocityTrajectory:
    """Motion with one constant body twist from `start` at t = 0 (a line, a circle, a spin)."""

    def __init__(self, start: Pose2D, vx_mps: float, omega_rps: float, vy_mps: float = 0.0) -> None:
        self.start = start
        self.twist = np.array([vx_mps, vy_mps, omega_rps], dtype=np.float64)

    def pose_at(self, times_s: ArrayLike) -> NDArray[np.float64]:
        """Poses (N, 3) reached from `start` after moving with the constant twist for `times_s`."""
        t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        return compose_arrays(self.start.to_array(), se2_exp(t[:, None] * self.twist[None, :]))

    def twist_at(self, times_s: ArrayLike) -> NDArray[np.float64]:
        """The constant twist (vx, vy, omega), one row per time."""
        t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        return np.tile(self.twist, (t.size, 1))


class PiecewiseTwistTrajectory:
    """Knots every `step_s` with a constant body twist between them; exact arcs in between."""

    def __init__(self, step_s: float, knot_poses: NDArray[np.float64], twists: NDArray[np.float64]):
        if knot_poses.shape != twists.shape or knot_poses.shape[1:] != (3,):
            raise ValueError(
                f"knot_poses {knot_poses.shape} and twists {twists.shape} must both be (K, 3)"
            )
        self.step_s = float(step_s)
        self.knot_poses = knot_poses
        self.twists = twists

    @property
    def duration_s(self) -> float:
        """Time the knots span: `step_s` per knot."""
        return self.step_s * self.knot_poses.shape[0]

    def _knot(self, t: NDArray[np.float64]) -> NDArray[np.intp]:
        k = np.floor(t / self.step_s).astype(np.intp)
        return np.clip(k, 0, self.knot_poses.shape[0] - 1)

    def pose_at(self, times_s: ArrayLike) -> NDArray[np.float64]:
        """Exact poses (N, 3): each time's knot moved along its twist's arc (times before 0 or
        after the last knot extend the first or last piece)."""
        t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        k = self._knot(t)
        tau = (t - k * self.step_s)[:, None]
        return compose_arrays(self.knot_poses[k], se2_exp(tau * self.twists[k]))

    def twist_at(self, times_s: ArrayLike) -> NDArray[np.float64]:
        """The body twist (N, 3) of each time's piece (times outside clamp to the end pieces)."""
        return self.twists[self._knot(np.atleast_1d(np.asarray(times_s, dtype=np.float64)))]


def tour_trajectory(
    world: World,
    duration_s: float,
    seed: int,
    max_speed_mps: float = 1.0,
    max_yaw_rate_dps: float = 90.0,
    max_accel_mps2: float = 1.0,
    max_yaw_accel_dps2: float = 360.0,
    step_s: float = 0.005,
) -> PiecewiseTwistTrajectory:
    """A smooth tour around the world's waypoints within speed, yaw-rate and acceleration limits.

    A heading controller steers at the next waypoint and slows down for sharp turns; the seed
    picks the starting waypoint and jitters the waypoints by up to 0.1 m.
    """
    if max_speed_mps <= 0 or max_yaw_rate_dps <= 0:
        raise ValueError(
            f"max_speed_mps ({max_speed_mps}) and max_yaw_rate_dps ({max_yaw_rate_dps}) must be > 0"
        )
    rng = np.random.default_rng(seed)
    waypoints = world.waypoints + rng.uniform(-0.1, 0.1, world.waypoints.shape)
    target = int(rng.integers(len(waypoints)))
    x, y = waypoints[target]
    target = (target + 1) % len(waypoints)
    theta = math.atan2(waypoints[target][1] - y, waypoints[target][0] - x)
    w_max = math.radians(max_yaw_rate_dps)
    dv_max, dw_max = max_accel_mps2 * step_s, math.radians(max_yaw_accel_dps2) * step_s
    steps = math.ceil(duration_s / step_s) + 1
    poses = np.empty((steps, 3))
    twists = np.zeros((steps, 3))
    v = w = 0.0
    for k in range(steps):
        poses[k] = (x, y, theta)
        tx, ty = waypoints[target]
        distance = math.hypot(tx - x, ty - y)
        if distance < 0.4:
            target = (target + 1) % len(waypoints)
            tx, ty = waypoints[target]
        error = normalize_angle(math.atan2(ty - y, tx - x) - theta)
        w_goal = max(-w_max, min(w_max, 3.0 * error))
        v_goal = max_speed_mps * max(0.0, math.cos(error)) ** 4
        v += max(-dv_max, min(dv_max, v_goal - v))
        w += max(-dw_max, min(dw_max, w_goal - w))
        twists[k] = (v, 0.0, w)
        # Exact arc: the chord has length v*dt*sinc(phi/2) along the mid-step heading.
        half_turn = 0.5 * w * step_s
        chord_m = v * step_s * (math.sin(half_turn) / half_turn if half_turn else 1.0)
        x += chord_m * math.cos(theta + half_turn)
        y += chord_m * math.sin(theta + half_turn)
        theta = normalize_angle(theta + 2.0 * half_turn)
    return PiecewiseTwistTrajectory(step_s, poses, twists)
