"""Per-beam motion compensation: re-express every beam in the robot's frame at one reference pose.

Beam i was measured at time t_i from the robot's pose T(t_i), by a sensor mounted at M =
`scan.mount` (T_base_sensor); its endpoint in the reference frame is
p_ref = T(t_ref)^-1 * T(t_i) * M * p_i (the seed's formula, vectorised over all beams, with the
mount the seed leaves out). With the relative pose (x_i, y_i, theta_i) = T(t_ref)^-1 T(t_i) M,
that is p_ref = (x_i + r_i cos(alpha_i + theta_i), y_i + r_i sin(alpha_i + theta_i)).
Odometry and the constant-velocity prior give the robot's motion, so a mounted sensor needs no
conversion of them, and everything downstream (matching, maps, poses) is the robot's.

Default reference: "start", the pose at `scan.stamp_s` (the first beam). It is the stamp every
other module already sees (ROS header convention), so the matcher and the frontend attach the
deskewed points to that stamp without re-stamping, and the simulator's ground truth uses it too.

No-return beams (`LaserScan.no_return_mask`) are moved the same way, as endpoints at the scan's
`range_max_m` (or NO_RETURN_RANGE_M when that is +inf): the map clears free space along them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray

from scanflow.deskew import kernels
from scanflow.deskew.source import DeskewError, PoseSource, SourceName, choose_source
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.scan import LaserScan

Reference = Literal["start", "middle", "end"]
REFERENCES: tuple[str, ...] = get_args(Reference)
DEFAULT_REFERENCE: Reference = "start"
SourceUsed = SourceName | Literal["none"]
NO_RETURN_RANGE_M = 1000.0
"""Range of a no-return endpoint when the scan's range_max_m is +inf: far beyond any clear
distance (the map clips no-return beams to its own `no_return_clear_m`), yet small enough that
float64 keeps the beam's direction to ~1e-13 m."""


@dataclass(frozen=True, eq=False)
class DeskewResult:
    """A motion-compensated scan: valid beams as points in the robot's frame at the reference
    pose, and no-return beams as `no_return_points` (at range_max_m, or NO_RETURN_RANGE_M)
    there; `mount` (the scan's) says where the sensor sits in that frame: rays start there."""

    points: NDArray[np.float64]
    no_return_points: NDArray[np.float64]
    reference: Reference
    reference_stamp_s: float
    source_used: SourceUsed
    times_assumed: bool
    message: str
    beam_count: int
    valid_count: int
    mount: Pose2D = IDENTITY

    @cached_property
    def ranges_m(self) -> NDArray[np.float64]:
        """Range of each compensated point from the sensor at the reference pose."""
        return np.hypot(self.points[:, 0] - self.mount.x, self.points[:, 1] - self.mount.y)

    @cached_property
    def angles_rad(self) -> NDArray[np.float64]:
        """Bearing of each compensated point from the sensor, in the robot's reference frame."""
        return np.arctan2(self.points[:, 1] - self.mount.y, self.points[:, 0] - self.mount.x)


def deskew(
    scan: LaserScan,
    sources: PoseSource | list[PoseSource] | tuple[PoseSource, ...] | None = None,
    reference: Reference = DEFAULT_REFERENCE,
) -> DeskewResult:
    """Compensate the scan's motion with the first source that covers its sweep.

    Falls back to no correction (source_used "none", with the reason in `message`) when no
    source covers it, the scan has zero duration, or it has no valid beams; never raises for
    a well-formed `LaserScan`. Raises DeskewError only for an unknown `reference`.
    """
    if reference not in REFERENCES:
        raise DeskewError(f"reference must be one of {REFERENCES}, got {reference!r}")
    offsets_s = _time_offsets(scan)
    start_s = scan.stamp_s
    end_s = scan.stamp_s + (float(offsets_s[-1]) if offsets_s.size else 0.0)
    reference_s = {"start": start_s, "middle": 0.5 * (start_s + end_s), "end": end_s}[reference]

    def uncorrected(message: str) -> DeskewResult:
        zeros = np.zeros(scan.beam_count)
        moved = _moved(scan, zeros, zeros, zeros)
        return _result(scan, moved, reference, reference_s, "none", message)

    nothing_to_move = motion_free_reason(scan)
    if nothing_to_move is not None:
        return uncorrected(nothing_to_move)
    source, reasons = choose_source(
        sources, min(start_s + float(offsets_s[0]), reference_s), max(end_s, reference_s)
    )
    if source is None:
        return uncorrected(f"no pose source covers the sweep: {reasons}")
    x, y, theta = source.relative_poses(scan.stamp_s + offsets_s, reference_s)
    return _result(scan, _moved(scan, x, y, theta), reference, reference_s, source.name, reasons)


def motion_free_reason(scan: LaserScan) -> str | None:
    """Why `deskew` leaves `scan` as it is whatever the pose sources say (no valid beams, or
    every beam fired at `stamp_s`), else None: a caller need not wait for poses to deskew it."""
    if not scan.valid_mask.any():
        return f"scan has no valid beams ({scan.beam_count} beams, all invalid)"
    offsets_s = _time_offsets(scan)
    if not offsets_s.size or (offsets_s[0] == 0.0 and offsets_s[-1] == 0.0):
        return "scan has zero duration: no motion within the sweep to correct"
    return None


Moved = tuple[NDArray[np.float64], NDArray[np.float64]]


def _moved(
    scan: LaserScan, x: NDArray[np.float64], y: NDArray[np.float64], theta: NDArray[np.float64]
) -> Moved:
    """(valid endpoints, no-return endpoints), each beam moved by its pose (x, y, theta)."""
    angles = _beam_angles(scan.beam_count, scan.angle_min_rad, scan.angle_increment_rad)
    far_m = scan.range_max_m if math.isfinite(scan.range_max_m) else NO_RETURN_RANGE_M
    if scan.mount != IDENTITY:
        x, y, theta = _mounted(x, y, theta, scan.mount)
    return kernels.beams_in_reference(
        scan.ranges_m, angles, scan.valid_mask, scan.no_return_mask, far_m, x, y, theta
    )


def _mounted(
    x: NDArray[np.float64], y: NDArray[np.float64], theta: NDArray[np.float64], mount: Pose2D
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Each beam's robot pose (x_i, y_i, theta_i) composed with the mount: the sensor's pose."""
    c, s = np.cos(theta), np.sin(theta)
    return x + c * mount.x - s * mount.y, y + s * mount.x + c * mount.y, theta + mount.theta


def _result(
    scan: LaserScan,
    moved: Moved,
    reference: Reference,
    reference_s: float,
    source_used: SourceUsed,
    message: str,
) -> DeskewResult:
    points, no_return_points = moved
    return DeskewResult(
        points=points,
        no_return_points=no_return_points,
        reference=reference,
        reference_stamp_s=reference_s,
        source_used=source_used,
        times_assumed=scan.beam_times_assumed,
        message=message,
        beam_count=scan.beam_count,
        valid_count=int(points.shape[0]),
        mount=scan.mount,
    )


def _time_offsets(scan: LaserScan) -> NDArray[np.float64]:
    """Measured per-beam offsets, or the cached uniform ones for this beam count and duration."""
    if scan.beam_time_offsets_s is not None:
        return scan.beam_time_offsets_s
    return _uniform_offsets(scan.beam_count, scan.scan_duration_s)


@lru_cache(maxsize=64)
def _uniform_offsets(beam_count: int, scan_duration_s: float) -> NDArray[np.float64]:
    """Beam i fires at i * duration / count, as `LaserScan.time_offsets_s` assumes."""
    offsets = (
        np.arange(beam_count, dtype=np.float64) * (scan_duration_s / beam_count)
        if beam_count
        else np.zeros(0)
    )
    offsets.flags.writeable = False
    return offsets


@lru_cache(maxsize=64)
def _beam_angles(beam_count: int, angle_min_rad: float, angle_increment_rad: float) -> NDArray:
    """Beam angles of one scan layout, computed once per layout."""
    angles = angle_min_rad + angle_increment_rad * np.arange(beam_count)
    angles.flags.writeable = False
    return angles
