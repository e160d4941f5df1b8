"""Motion filter: insert a scan into the map only after the robot moved, turned or waited enough.

Inserting every scan of a robot standing still would pile evidence onto the same cells (and
let a person walking past overwrite walls); inserting too rarely leaves holes at speed.
"""

from __future__ import annotations

import math

from scanflow.geometry import Pose2D


class MotionFilter:
    """Says whether a pose is far enough (distance, heading or time) from the last insertion."""

    def __init__(self, min_distance_m: float, min_angle_rad: float, max_interval_s: float) -> None:
        for name, value in (
            ("min_distance_m", min_distance_m),
            ("min_angle_rad", min_angle_rad),
            ("max_interval_s", max_interval_s),
        ):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        self.min_distance_m = float(min_distance_m)
        self.min_angle_rad = float(min_angle_rad)
        self.max_interval_s = float(max_interval_s)
        self._last: tuple[float, Pose2D] | None = None

    def should_insert(self, stamp_s: float, pose: Pose2D) -> bool:
        """True for the first pose, or once any threshold is reached since the last insertion."""
        if self._last is None:
            return True
        last_s, last_pose = self._last
        step = pose.relative_to(last_pose)
        return (
            step.translation_norm() >= self.min_distance_m
            or abs(step.theta) >= self.min_angle_rad
            or abs(stamp_s - last_s) >= self.max_interval_s
        )

    def mark_inserted(self, stamp_s: float, pose: Pose2D) -> None:
        """Record an insertion at `stamp_s`, `pose`: the thresholds count from here on."""
        self._last = (float(stamp_s), pose)

    def move_frame(self, correction: Pose2D) -> None:
        """Re-express the last insertion in another map frame (T_new_old = `correction`)."""
        if self._last is not None:
            self._last = (self._last[0], correction * self._last[1])
