"""Pose prediction for the next scan: the odometry increment composed into the map frame, or
a constant-velocity extrapolation of the last estimates when there is no (usable) odometry.

The odometry and map frames differ by the drift accumulated so far, so only odometry
*increments* are meaningful: T_map_t = T_map_(t-1) * inverse(T_odom_(t-1)) * T_odom_t
(second seed, part 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

from scanflow.deskew import ConstantVelocityModel
from scanflow.geometry import Pose2D


class PredictionSource(StrEnum):
    """Where a predicted pose came from."""

    INITIAL = "initial"
    ODOMETRY = "odometry"
    CONSTANT_VELOCITY = "constant_velocity"
    HOLD = "hold"


def compose_odometry_increment(
    last_map_pose: Pose2D, last_odom_pose: Pose2D, odom_pose: Pose2D
) -> Pose2D:
    """T_map_t = T_map_(t-1) * inverse(T_odom_(t-1)) * T_odom_t."""
    return last_map_pose * (last_odom_pose.inverse() * odom_pose)


@dataclass(frozen=True)
class Prediction:
    """A predicted map pose, the motion since the last estimate, and how it was obtained."""

    pose: Pose2D
    motion: Pose2D
    source: PredictionSource
    message: str = ""


class MotionPredictor:
    """Tracks the last estimate (map and odometry poses) and predicts the next scan's pose.

    An odometry step longer than `max_odom_step_m` or turning more than `max_odom_step_rad` is
    taken as a jump (a reset or a glitch of the odometry source) and ignored for this scan; the
    next step is measured from the jumped-to odometry pose, so one glitch costs one prediction.
    Over a longer gap since the last scan (a restarted service, a stalled link) the limits grow
    with the time: a step is a jump only beyond `max_odom_speed_mps` / `max_odom_turn_rate_rads`
    too, so the odometry still bridges the gap where nothing else could. A scan without
    odometry (a restarted deskewer's first) leaves the chain where it was: the next increment is
    measured from the last scan that had it.
    """

    def __init__(
        self, max_odom_step_m: float, max_odom_step_rad: float, cv_horizon_s: float,
        max_odom_speed_mps: float = 5.0, max_odom_turn_rate_rads: float = math.pi,
    ) -> None:
        for name, value in (
            ("max_odom_step_m", max_odom_step_m),
            ("max_odom_step_rad", max_odom_step_rad),
            ("max_odom_speed_mps", max_odom_speed_mps),
            ("max_odom_turn_rate_rads", max_odom_turn_rate_rads),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value!r}")
        self.max_odom_step_m = float(max_odom_step_m)
        self.max_odom_step_rad = float(max_odom_step_rad)
        self.max_odom_speed_mps = float(max_odom_speed_mps)
        self.max_odom_turn_rate_rads = float(max_odom_turn_rate_rads)
        self.cv_horizon_s = cv_horizon_s
        self._velocity = ConstantVelocityModel(max_horizon_s=cv_horizon_s)
        self._last_pose: Pose2D | None = None
        # (stamp, map pose, odometry pose) of the last scan with odometry: where it continues.
        self._chain: tuple[float, Pose2D, Pose2D] | None = None

    @property
    def last_pose(self) -> Pose2D | None:
        """The last recorded or placed map pose (None before any); `predict` starts from it."""
        return self._last_pose

    def predict(self, stamp_s: float, odom_pose: Pose2D | None) -> Prediction:
        """The expected map pose at `stamp_s` given the odometry pose there (None if unknown)."""
        last = self._last_pose
        if last is None:
            return Prediction(Pose2D(), Pose2D(), PredictionSource.INITIAL)
        note = ""
        if odom_pose is not None and self._chain is not None:
            chain_stamp_s, chain_pose, chain_odom = self._chain
            step = odom_pose.relative_to(chain_odom)
            gap_s = max(stamp_s - chain_stamp_s, 0.0)
            limit_m = max(self.max_odom_step_m, self.max_odom_speed_mps * gap_s)
            limit_rad = max(self.max_odom_step_rad, self.max_odom_turn_rate_rads * gap_s)
            if step.translation_norm() <= limit_m and abs(step.theta) <= limit_rad:
                pose = compose_odometry_increment(chain_pose, chain_odom, odom_pose)
                # The motion is the odometry's since the chain's scan (the last one, unless
                # scans without odometry came between: a little more, never less).
                return Prediction(pose, step, PredictionSource.ODOMETRY)
            note = (
                f"odometry jumped {step.translation_norm():.2f} m / "
                f"{math.degrees(step.theta):.1f} deg in {gap_s:.2f} s (limits {limit_m:.2f} m / "
                f"{math.degrees(limit_rad):.1f} deg): ignored"
            )
        if self._velocity.coverage_gap(stamp_s, stamp_s) is None:
            x, y, theta = self._velocity.poses_at([stamp_s])
            pose = Pose2D(float(x[0]), float(y[0]), float(theta[0]))
            return Prediction(
                pose, pose.relative_to(last), PredictionSource.CONSTANT_VELOCITY, note
            )
        held = "; ".join(m for m in (note, "no motion prior: held") if m)
        return Prediction(last, Pose2D(), PredictionSource.HOLD, held)

    def update(self, stamp_s: float, pose: Pose2D, odom_pose: Pose2D | None) -> None:
        """Record the pose estimated at `stamp_s` (matched or predicted) and its odometry pose."""
        self._velocity.update(stamp_s, pose)
        self._last_pose = pose
        if odom_pose is not None:  # without it, the chain goes on from the last that had it
            self._chain = (stamp_s, pose, odom_pose)

    def place(self, pose: Pose2D) -> None:
        """Put the robot at `pose` by decree (an operator's initial pose): velocity and the
        odometry chain are forgotten, so the next scan is predicted at `pose` itself."""
        self._velocity = ConstantVelocityModel(max_horizon_s=self.cv_horizon_s)
        self._last_pose = pose
        self._chain = None

    def move_frame(self, correction: Pose2D) -> None:
        """Re-express the estimates in another map frame (T_new_old = `correction`, a map
        redrawn after a pose-graph optimisation): the odometry chain and velocity carry on."""
        if self._last_pose is not None:
            self._last_pose = correction * self._last_pose
        if self._chain is not None:
            stamp_s, pose, odom = self._chain
            self._chain = (stamp_s, correction * pose, odom)
        self._velocity.move_frame(correction)

    def restart(self, stamp_s: float, pose: Pose2D, odom_pose: Pose2D | None) -> None:
        """Record a pose that is not a motion from the last one (found by a whole-map search):
        the velocity and the odometry chain are forgotten, so the jump is not extrapolated."""
        self._velocity = ConstantVelocityModel(max_horizon_s=self.cv_horizon_s)
        self._chain = None
        self.update(stamp_s, pose, odom_pose)
