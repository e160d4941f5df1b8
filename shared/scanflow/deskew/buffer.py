"""A time-bounded buffer of odometry poses that interpolates SE(2) at any time within its span.

Interpolation is linear in translation and in the (unwrapped, so shortest-arc) heading between
consecutive samples. Against a robot that really moves on arcs, the chord differs from the arc
by at most v * omega * dt**2 / 8 (0.16 mm at 1 m/s, 180 deg/s and 50 Hz odometry), well below
odometry's own error, so the cheaper linear form is used.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.deskew import kernels
from scanflow.deskew.source import DeskewError, PoseArrays, SourceName, finite_times
from scanflow.geometry import Pose2D, normalize_angles
from scanflow.scan import Odometry

_INITIAL_CAPACITY = 256


class OdometryBuffer:
    """Odometry samples from the last `max_age_s`, kept sorted by stamp.

    Out-of-order samples are inserted in place; a sample with the stamp of one already held
    replaces it (the later arrival wins); samples older than the window are dropped and counted.
    Queries may reach `extrapolation_margin_s` beyond the held span, never further, and refuse to
    bridge two samples further apart than `max_gap_s`.
    """

    name: SourceName = "odometry"

    def __init__(
        self,
        max_age_s: float = 2.0,
        extrapolation_margin_s: float = 0.02,
        max_gap_s: float = 0.25,
    ) -> None:
        for field, value in (("max_age_s", max_age_s), ("max_gap_s", max_gap_s)):
            if not (math.isfinite(value) and value > 0):
                raise DeskewError(f"{field} must be finite and > 0, got {value!r}")
        if not (math.isfinite(extrapolation_margin_s) and extrapolation_margin_s >= 0):
            raise DeskewError(
                f"extrapolation_margin_s must be finite and >= 0, got {extrapolation_margin_s!r}"
            )
        self.max_age_s = float(max_age_s)
        self.extrapolation_margin_s = float(extrapolation_margin_s)
        self.max_gap_s = float(max_gap_s)
        # Columns: stamp_s, x, y, theta (raw, wrapped), theta (unwrapped along the buffer).
        self._data = np.empty((5, _INITIAL_CAPACITY))
        self._lo = 0
        self._hi = 0
        self.dropped_count = 0
        self.replaced_count = 0

    def __len__(self) -> int:
        return self._hi - self._lo

    @property
    def stamps_s(self) -> NDArray[np.float64]:
        """Stamps of the held samples, oldest first (a read-only view)."""
        view = self._data[0, self._lo : self._hi]
        view.flags.writeable = False
        return view

    def add_odometry(self, sample: Odometry) -> bool:
        """Add one `Odometry` sample; False when it was dropped as older than the window."""
        return self.add(sample.stamp_s, sample.pose)

    def add(self, stamp_s: float, pose: Pose2D) -> bool:
        """Add the pose at `stamp_s`; False when it was dropped as older than the window."""
        stamp_s = float(stamp_s)
        if not math.isfinite(stamp_s):
            raise DeskewError(f"odometry stamp_s must be finite, got {stamp_s!r}")
        d, lo, hi = self._data, self._lo, self._hi
        if hi > lo and stamp_s < d[0, hi - 1] - self.max_age_s:
            self.dropped_count += 1
            return False
        if hi == lo or stamp_s > d[0, hi - 1]:
            self._append(stamp_s, pose)
        else:
            i = lo + int(np.searchsorted(d[0, lo:hi], stamp_s))
            if d[0, i] == stamp_s:
                d[1:4, i] = (pose.x, pose.y, pose.theta)
                self.replaced_count += 1
            else:
                self._ensure_room()
                d, lo, hi = self._data, self._lo, self._hi
                i = lo + int(np.searchsorted(d[0, lo:hi], stamp_s))
                d[:, i + 1 : hi + 1] = d[:, i:hi]
                d[:4, i] = (stamp_s, pose.x, pose.y, pose.theta)
                self._hi += 1
            d[4, self._lo : self._hi] = np.unwrap(d[3, self._lo : self._hi])
        return True

    def _append(self, stamp_s: float, pose: Pose2D) -> None:
        self._ensure_room()
        d, hi = self._data, self._hi
        if hi > self._lo:
            previous = d[4, hi - 1]
            theta = previous + (pose.theta - previous + math.pi) % (2.0 * math.pi) - math.pi
        else:
            theta = pose.theta
        d[:, hi] = (stamp_s, pose.x, pose.y, pose.theta, theta)
        self._hi = hi + 1
        oldest_kept_s = stamp_s - self.max_age_s
        if d[0, self._lo] < oldest_kept_s:
            self._lo += int(np.searchsorted(d[0, self._lo : self._hi], oldest_kept_s))

    def _ensure_room(self) -> None:
        """Make room for one more sample: move the live samples to the front, or grow."""
        if self._hi < self._data.shape[1]:
            return
        count = self._hi - self._lo
        if count * 2 > self._data.shape[1]:
            grown = np.empty((5, self._data.shape[1] * 2))
            grown[:, :count] = self._data[:, self._lo : self._hi]
            self._data = grown
        else:
            self._data[:, :count] = self._data[:, self._lo : self._hi]
        self._lo, self._hi = 0, count

    def coverage_gap(self, start_s: float, end_s: float) -> str | None:
        """None when [start_s, end_s] can be interpolated, else the reason it cannot."""
        status, value, index = kernels.coverage(
            self._data[0],
            self._lo,
            self._hi,
            start_s,
            end_s,
            self.extrapolation_margin_s,
            self.max_gap_s,
        )
        if status == kernels.COVERED:
            return None
        margin = self.extrapolation_margin_s
        if status == kernels.TOO_FEW:
            return f"needs at least two odometry samples, has {int(value)}"
        if status == kernels.BEFORE_OLDEST:
            return (
                f"sweep starts at {start_s:.6f} s, {value:.4f} s before the oldest odometry "
                f"sample (extrapolation margin {margin} s)"
            )
        if status == kernels.AFTER_NEWEST:
            return (
                f"sweep ends at {end_s:.6f} s, {value:.4f} s after the newest odometry "
                f"sample (extrapolation margin {margin} s)"
            )
        return (
            f"odometry gap of {value:.4f} s after the sample at {self._data[0, index]:.6f} s "
            f"exceeds max_gap_s={self.max_gap_s}"
        )

    def poses_at(self, times_s: ArrayLike) -> PoseArrays:
        """Poses (x, y, theta wrapped to [-pi, pi)) at the given times (none: empty arrays);
        DeskewError if uncovered or a time is not finite."""
        t = finite_times(times_s)
        if t.size == 0:
            return t, t.copy(), t.copy()
        self._require(float(t.min()), float(t.max()))
        poses = kernels.interpolate_poses(self._data, self._lo, self._hi, t, 0.0, False)
        return poses[0], poses[1], normalize_angles(poses[2])

    def relative_poses(self, times_s: NDArray[np.float64], reference_s: float) -> PoseArrays:
        """Poses at sorted `times_s` in the frame of the pose at `reference_s` (theta unwrapped)."""
        self._require(min(float(times_s[0]), reference_s), max(float(times_s[-1]), reference_s))
        poses = kernels.interpolate_poses(
            self._data, self._lo, self._hi, times_s, float(reference_s), True
        )
        return poses[0], poses[1], poses[2]

    def _require(self, start_s: float, end_s: float) -> None:
        gap = self.coverage_gap(start_s, end_s)
        if gap is not None:
            raise DeskewError(f"odometry cannot cover [{start_s:.6f}, {end_s:.6f}] s: {gap}")
