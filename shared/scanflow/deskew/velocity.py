"""Constant-velocity motion prior from the last two estimated poses (what KISS-ICP uses).

The robot is assumed to keep the body-frame twist it had between the last two pose estimates,
so the pose at time t is `T_last * exp((t - t_last) * twist)`: an arc, exact for constant motion.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.deskew.source import DeskewError, PoseArrays, SourceName, finite_times
from scanflow.geometry import Pose2D, compose_arrays, se2_exp, se2_log


class ConstantVelocityModel:
    """Predicts poses from the twist between the last two `update` poses.

    Predictions reach at most `max_horizon_s` from the last pose: beyond that the robot has had
    time to change its motion and the prior is refused. A pose older than the last one resets the
    model (time went backwards), which then needs two new poses. A pose less than
    `min_interval_s` after the last one is not a baseline for a twist (two estimates a
    microsecond apart and 5 cm apart would be 50 km/s): it is skipped. A twist faster than
    `max_speed_mps` / `max_turn_rate_rads` is an error of the poses, not motion: the model
    resets, saying so.
    """

    name: SourceName = "constant_velocity"

    def __init__(
        self,
        max_horizon_s: float = 0.5,
        min_interval_s: float = 0.005,
        max_speed_mps: float = 50.0,
        max_turn_rate_rads: float = 4.0 * math.pi,
    ) -> None:
        for name, value in (("max_horizon_s", max_horizon_s), ("min_interval_s", min_interval_s),
                            ("max_speed_mps", max_speed_mps),
                            ("max_turn_rate_rads", max_turn_rate_rads)):
            if not (math.isfinite(value) and value > 0):
                raise DeskewError(f"{name} must be finite and > 0, got {value!r}")
        self.max_horizon_s = float(max_horizon_s)
        self.min_interval_s = float(min_interval_s)
        self.max_speed_mps = float(max_speed_mps)
        self.max_turn_rate_rads = float(max_turn_rate_rads)
        self._last: tuple[float, Pose2D] | None = None
        self._twist: NDArray[np.float64] | None = None
        self.reset_reason = ""

    @property
    def twist(self) -> NDArray[np.float64] | None:
        """Body-frame velocity (vx m/s, vy m/s, omega rad/s), or None before two poses."""
        return None if self._twist is None else self._twist.copy()

    def update(self, stamp_s: float, pose: Pose2D) -> None:
        """Record the estimated pose at `stamp_s` (normally the scan stamp it was matched at)."""
        stamp_s = float(stamp_s)
        if not math.isfinite(stamp_s):
            raise DeskewError(f"ConstantVelocityModel stamp_s must be finite, got {stamp_s!r}")
        if self._last is not None:
            last_s, last_pose = self._last
            if stamp_s < last_s:
                self.reset_reason = f"time went backwards from {last_s:.6f} s to {stamp_s:.6f} s"
                self._twist = None
            elif stamp_s - last_s < self.min_interval_s:
                return  # too short a baseline: the last pose and its twist stand
            else:
                twist = se2_log(pose.relative_to(last_pose).to_array())[0] / (stamp_s - last_s)
                speed, turn = math.hypot(twist[0], twist[1]), abs(twist[2])
                if speed > self.max_speed_mps or turn > self.max_turn_rate_rads:
                    self.reset_reason = (
                        f"the poses at {last_s:.6f} s and {stamp_s:.6f} s imply {speed:.3g} m/s, "
                        f"{turn:.3g} rad/s (max_speed_mps {self.max_speed_mps:g}, "
                        f"max_turn_rate_rads {self.max_turn_rate_rads:.3g})"
                    )
                    self._twist = None
                else:
                    self._twist, self.reset_reason = twist, ""
        self._last = (stamp_s, pose)

    def move_frame(self, correction: Pose2D) -> None:
        """Re-express the model in another world frame (T_new_old = `correction`): the last pose
        moves with it, the body-frame twist does not change."""
        if self._last is not None:
            self._last = (self._last[0], correction * self._last[1])

    def coverage_gap(self, start_s: float, end_s: float) -> str | None:
        """None when the prior can predict [start_s, end_s], else why not."""
        if self._twist is None or self._last is None:
            held = 0 if self._last is None else 1
            why = f" ({self.reset_reason})" if self.reset_reason else ""
            return f"needs two poses at different times, has {held}{why}"
        last_s = self._last[0]
        horizon_s = max(abs(start_s - last_s), abs(end_s - last_s))
        if horizon_s > self.max_horizon_s:
            return (
                f"sweep is {horizon_s:.4f} s from the last pose at {last_s:.6f} s, beyond "
                f"max_horizon_s={self.max_horizon_s}"
            )
        return None

    def poses_at(self, times_s: ArrayLike) -> PoseArrays:
        """Predicted poses (x, y, theta) at the given times (none: empty arrays); DeskewError if
        beyond the horizon or a time is not finite."""
        t = finite_times(times_s)
        if t.size == 0:
            return t, t.copy(), t.copy()
        (last_s, last_pose), twist = self._require(float(t.min()), float(t.max()))
        poses = compose_arrays(last_pose.to_array(), _motion(twist, t - last_s))
        return poses[:, 0], poses[:, 1], poses[:, 2]

    def relative_poses(self, times_s: NDArray[np.float64], reference_s: float) -> PoseArrays:
        """Poses at `times_s` in the frame of the pose at `reference_s`: exp((t - ref) * twist)."""
        _, twist = self._require(
            min(float(times_s[0]), reference_s), max(float(times_s[-1]), reference_s)
        )
        rel = _motion(twist, times_s - reference_s)
        return rel[:, 0], rel[:, 1], rel[:, 2]

    def _require(
        self, start_s: float, end_s: float
    ) -> tuple[tuple[float, Pose2D], NDArray[np.float64]]:
        """The last (stamp, pose) and the twist, when the model covers [start_s, end_s];
        else DeskewError saying why (`coverage_gap`, which needs both to be known)."""
        gap = self.coverage_gap(start_s, end_s)
        if gap is not None or self._last is None or self._twist is None:
            raise DeskewError(f"constant-velocity model cannot cover [{start_s}, {end_s}] s: {gap}")
        return self._last, self._twist


def _motion(twist: NDArray[np.float64], dt_s: NDArray[np.float64]) -> NDArray[np.float64]:
    """The body-frame motions exp(dt * twist) over the time steps `dt_s`."""
    return se2_exp(dt_s[:, None] * twist[None, :])
