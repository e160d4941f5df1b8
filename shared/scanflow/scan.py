"""Laser scans and odometry samples: the data model every other module speaks.

Conventions (the same as ROS sensor_msgs/LaserScan):
- beam i points at `angle_min_rad + i * angle_increment_rad`, counter-clockwise, in the
  sensor frame (x forward, y left);
- `stamp_s` is the time of the first beam; beam i was measured at
  `stamp_s + beam_time_offsets_s[i]`.
  When a driver gives no per-beam times, offsets are assumed uniform over `scan_duration_s`
  (and `beam_times_assumed` tells so);
- every beam is exactly one of (REP 117):
  valid: finite, positive, >= `range_min_m` and < `range_max_m`: a return, matched and mapped;
  no return: >= `range_max_m`, +inf included: the beam saw nothing in range, so it clears
  free space along its direction (up to the map's clear distance) but is never matched;
  error: NaN, -inf, zero or negative, below `range_min_m`: nothing is known, never used.
  Readers map their driver's conventions onto these (e.g. CARMEN's no-return sentinel lies
  at or above the `range_max_m` its reader sets, so those beams come out as no return);
- `mount` is the sensor's pose on the robot, T_base_sensor (ROS: the static transform
  base_link -> the scan's frame_id). Deskewing moves every beam into the robot's frame, so
  odometry, matching, maps and published poses are all the robot's; identity (the default)
  means the sensor sits at the robot's origin, facing forward. Its x and y lie within
  +-MAX_MOUNT_M of the robot's origin: one farther is a wrong transform or wrong units
  (millimetres).
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.geometry import IDENTITY, Pose2D

MAX_BEAMS = 100_000
MAX_MOUNT_M = 100.0  # the sensor's distance from the robot's origin, in x and in y
MAX_ODOM_M = 1e9  # an odometry position further out overflows its increments to inf


class ScanError(ValueError):
    """A scan or odometry sample whose fields are inconsistent; the message names the field."""


def _numbers(name: str, value: ArrayLike, dtype: type) -> NDArray:
    """`value` as an array of `dtype`; ScanError naming `name` when it holds no numbers."""
    try:
        return np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ScanError(f"{name} must be numbers: {exc}") from None


def _count(name: str, value: int) -> int:
    """A non-negative integer (numpy integers welcome; 1.7 or True refused)."""
    try:
        if isinstance(value, bool):
            raise TypeError
        value = operator.index(value)
    except TypeError:
        raise ScanError(f"{name} must be an integer, got {value!r}") from None
    if value < 0:
        raise ScanError(f"{name} must be >= 0, got {value}")
    return value


def _finite(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ScanError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value):
        raise ScanError(f"{name} must be finite, got {value!r}")
    return value


@dataclass(frozen=True, eq=False)
class LaserScan:
    """One sweep of a 2D lidar, with its validity mask and beam timing."""

    ranges_m: NDArray[np.float32]
    angle_min_rad: float
    angle_increment_rad: float
    range_min_m: float = 0.0
    range_max_m: float = math.inf
    stamp_s: float = 0.0
    scan_duration_s: float = 0.0
    beam_time_offsets_s: NDArray[np.float64] | None = None
    robot_id: str = "robot"
    frame_id: str = "laser"
    intensities: NDArray[np.float32] | None = None
    seq: int = 0
    mount: Pose2D = IDENTITY

    def __post_init__(self) -> None:
        # C-contiguous and writable (a read-only array, as decoded from the wire, is copied):
        # numba compiles each array type apart, so one type keeps a service's warm-up complete.
        ranges = np.require(_numbers("ranges_m", self.ranges_m, np.float32), None, ["C", "W"])
        if ranges.ndim != 1:
            raise ScanError(f"ranges_m must be 1-D, got shape {ranges.shape}")
        if ranges.size > MAX_BEAMS:
            raise ScanError(f"ranges_m has {ranges.size} beams, more than the limit {MAX_BEAMS}")
        object.__setattr__(self, "ranges_m", ranges)
        for name in ("angle_min_rad", "angle_increment_rad", "range_min_m", "stamp_s"):
            object.__setattr__(self, name, _finite(name, getattr(self, name)))
        if abs(self.angle_increment_rad) > 2 * math.pi:  # 0: a fixed beam sampled in time
            raise ScanError(f"angle_increment_rad must be at most a turn, got "
                            f"{self.angle_increment_rad}")
        rmax_array = _numbers("range_max_m", self.range_max_m, np.float64)
        if rmax_array.ndim != 0:
            raise ScanError(f"range_max_m must be one number, got shape {rmax_array.shape}")
        rmax = rmax_array.item()
        if math.isnan(rmax):
            raise ScanError("range_max_m must not be NaN")
        object.__setattr__(self, "range_max_m", rmax)
        if self.range_min_m < 0:
            raise ScanError(f"range_min_m must be >= 0, got {self.range_min_m}")
        if rmax <= self.range_min_m:
            raise ScanError(f"range_max_m ({rmax}) must exceed range_min_m ({self.range_min_m})")
        duration = _finite("scan_duration_s", self.scan_duration_s)
        if duration < 0:
            raise ScanError(f"scan_duration_s must be >= 0, got {duration}")
        object.__setattr__(self, "scan_duration_s", duration)
        if self.beam_time_offsets_s is not None:
            offsets = _numbers("beam_time_offsets_s", self.beam_time_offsets_s, np.float64)
            if offsets.shape != ranges.shape:
                raise ScanError(
                    f"beam_time_offsets_s has shape {offsets.shape}, ranges_m has {ranges.shape}"
                )
            if not np.all(np.isfinite(offsets)):
                raise ScanError("beam_time_offsets_s contains non-finite values")
            if offsets.size > 1 and np.any(np.diff(offsets) < 0):
                raise ScanError("beam_time_offsets_s must be non-decreasing")
            object.__setattr__(self, "beam_time_offsets_s", offsets)
        if self.intensities is not None:
            inten = _numbers("intensities", self.intensities, np.float32)
            if inten.shape != ranges.shape:
                raise ScanError(f"intensities has shape {inten.shape}, ranges_m has {ranges.shape}")
            object.__setattr__(self, "intensities", inten)
        if not self.robot_id or not isinstance(self.robot_id, str):
            raise ScanError(f"robot_id must be a non-empty string, got {self.robot_id!r}")
        object.__setattr__(self, "seq", _count("seq", self.seq))
        if not isinstance(self.mount, Pose2D):
            raise ScanError(f"mount must be a Pose2D, got {type(self.mount).__name__}")
        if max(abs(self.mount.x), abs(self.mount.y)) > MAX_MOUNT_M:
            raise ScanError(
                f"mount ({self.mount.x}, {self.mount.y}) m is beyond +-{MAX_MOUNT_M:g} m of the "
                f"robot's origin (a wrong transform, or millimetres?)"
            )

    @property
    def beam_count(self) -> int:
        """Number of beams, valid or not."""
        return int(self.ranges_m.size)

    @cached_property
    def angles_rad(self) -> NDArray[np.float64]:
        """Angle of every beam in the sensor frame."""
        beams = np.arange(self.beam_count, dtype=np.float64)
        return self.angle_min_rad + self.angle_increment_rad * beams

    @cached_property
    def valid_mask(self) -> NDArray[np.bool_]:
        """True for beams with a usable return (see the module docstring)."""
        # Comparisons with NaN are False, so NaN and -inf fail the first test without an isfinite
        # pass; +inf is a no return (+inf >= range_max_m), as is every reading past the range.
        r = self.ranges_m
        valid = (r >= self.range_min_m) if self.range_min_m > 0 else (r > 0)
        valid &= ~self.no_return_mask
        return valid

    @cached_property
    def no_return_mask(self) -> NDArray[np.bool_]:
        """True for beams that saw nothing in range: range >= range_max_m, +inf included.

        Disjoint from `valid_mask` (which excludes it); NaN, -inf, 0 and readings below
        range_min_m are errors, in neither mask (see the module docstring).
        """
        return self.ranges_m >= self.range_max_m

    @property
    def valid_count(self) -> int:
        """Beams with a usable return (`valid_mask`)."""
        return int(np.count_nonzero(self.valid_mask))

    @property
    def no_return_count(self) -> int:
        """Beams that saw nothing in range (`no_return_mask`)."""
        return int(np.count_nonzero(self.no_return_mask))

    @property
    def dropped_count(self) -> int:
        """Beams that are not valid returns (no return and errors alike)."""
        return self.beam_count - self.valid_count

    @property
    def beam_times_assumed(self) -> bool:
        """True when per-beam times are derived from the scan duration, not measured."""
        return self.beam_time_offsets_s is None

    @cached_property
    def time_offsets_s(self) -> NDArray[np.float64]:
        """Per-beam time offsets from `stamp_s`: measured, or uniform over the scan duration."""
        if self.beam_time_offsets_s is not None:
            return self.beam_time_offsets_s
        n = self.beam_count
        if n <= 1 or self.scan_duration_s == 0.0:
            return np.zeros(n)
        return np.arange(n, dtype=np.float64) * (self.scan_duration_s / n)

    @property
    def end_stamp_s(self) -> float:
        """Time of the last beam."""
        offsets = self.time_offsets_s
        return self.stamp_s + (float(offsets[-1]) if offsets.size else 0.0)

    def points(self, valid_only: bool = True) -> NDArray[np.float64]:
        """Beam endpoints as (N, 2) Cartesian points in the sensor frame (not yet `mount`ed)."""
        r = self.ranges_m.astype(np.float64)
        a = self.angles_rad
        if valid_only:
            m = self.valid_mask
            r, a = r[m], a[m]
        return np.column_stack((r * np.cos(a), r * np.sin(a)))

    def robot_points(self) -> NDArray[np.float64]:
        """Valid beam endpoints (N, 2) in the robot's frame (`mount` applied), not deskewed:
        what matching and mapping see of a scan taken standing still."""
        points = self.points()
        return points if self.mount == IDENTITY else self.mount.transform_points(points)

    def with_ranges(self, ranges_m: ArrayLike) -> LaserScan:
        """A copy with other ranges (same layout and timing)."""
        return LaserScan(
            ranges_m=np.asarray(ranges_m, dtype=np.float32),
            angle_min_rad=self.angle_min_rad,
            angle_increment_rad=self.angle_increment_rad,
            range_min_m=self.range_min_m,
            range_max_m=self.range_max_m,
            stamp_s=self.stamp_s,
            scan_duration_s=self.scan_duration_s,
            beam_time_offsets_s=self.beam_time_offsets_s,
            robot_id=self.robot_id,
            frame_id=self.frame_id,
            intensities=self.intensities,
            seq=self.seq,
            mount=self.mount,
        )


@dataclass(frozen=True)
class Odometry:
    """One wheel-odometry sample: the robot's pose in the odometry frame at `stamp_s`.

    `velocity` is (v_x m/s, v_y m/s, omega rad/s) in the robot frame, when the source gives it.
    """

    stamp_s: float
    pose: Pose2D
    velocity: tuple[float, float, float] | None = None
    robot_id: str = "robot"
    seq: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "stamp_s", _finite("stamp_s", self.stamp_s))
        if not isinstance(self.pose, Pose2D):
            raise ScanError(f"pose must be a Pose2D, got {type(self.pose).__name__}")
        if not max(abs(self.pose.x), abs(self.pose.y)) <= MAX_ODOM_M:
            raise ScanError(f"pose must lie within +-{MAX_ODOM_M:g} m, got {self.pose}")
        if self.velocity is not None:
            if not isinstance(self.velocity, tuple | list | np.ndarray) or len(self.velocity) != 3:
                raise ScanError(f"velocity must be 3 numbers (vx, vy, omega), got "
                                f"{self.velocity!r}")
            vel = tuple(_finite(f"velocity[{i}]", v) for i, v in enumerate(self.velocity))
            object.__setattr__(self, "velocity", vel)
        if not self.robot_id or not isinstance(self.robot_id, str):
            raise ScanError(f"robot_id must be a non-empty string, got {self.robot_id!r}")
        object.__setattr__(self, "seq", _count("seq", self.seq))
