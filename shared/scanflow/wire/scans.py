"""Sensor messages: raw scans, deskewed scans and wheel odometry."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import IDENTITY, Pose2D
from scanflow.scan import LaserScan, Odometry
from scanflow.wire.base import (
    Message,
    check_array,
    check_count,
    check_finite,
    check_pose,
    check_position,
    check_robot_id,
    check_text,
)
from scanflow.wire.codec import Fields
from scanflow.wire.errors import MessageError
from scanflow.wire.schema import (
    FLAG,
    INT,
    NUMBER,
    POSE,
    TEXT,
    VECTOR3,
    Schema,
    array,
    decode_fields,
    encode_fields,
    optional,
)

SCAN_WIRE: Schema = {
    "robot_id": TEXT,
    "frame_id": TEXT,
    "seq": INT,
    "stamp_s": NUMBER,
    "angle_min_rad": NUMBER,
    "angle_increment_rad": NUMBER,
    "range_min_m": NUMBER,
    "range_max_m": NUMBER,
    "scan_duration_s": NUMBER,
    "ranges_m": array("<f4"),
    "beam_time_offsets_s": optional(array("<f8")),
    "intensities": optional(array("<f4")),
    "mount": POSE,
}
ODOM_WIRE: Schema = {
    "robot_id": TEXT,
    "seq": INT,
    "stamp_s": NUMBER,
    "pose": POSE,
    "velocity": optional(VECTOR3),
}


def scan_to_fields(scan: LaserScan) -> dict[str, Any]:
    """Every LaserScan field; ranges keep their exact bits (NaN marks a masked beam)."""
    return encode_fields(SCAN_WIRE, scan)


def scan_from_fields(fields: Fields) -> LaserScan:
    """The LaserScan in `fields`; its own validation runs (a ScanError becomes a SchemaError)."""
    return LaserScan(**decode_fields(SCAN_WIRE, fields))


@dataclass(frozen=True, eq=False)
class ScanMessage(Message):
    """A raw scan as measured (`scan.seq` is the message sequence number)."""

    TYPE = "scan"
    scan: LaserScan

    def __post_init__(self) -> None:
        if not isinstance(self.scan, LaserScan):
            raise MessageError(f"scan must be a LaserScan, got {type(self.scan).__name__}")
        if not isinstance(self.scan.frame_id, str):
            raise MessageError(f"scan.frame_id must be a string, got {self.scan.frame_id!r}")
        check_robot_id(self.scan.robot_id)
        check_count("scan.seq", self.scan.seq)

    @property
    def robot_id(self) -> str:
        """The scan's robot id."""
        return self.scan.robot_id

    @property
    def seq(self) -> int:
        """The scan's `seq`: the message sequence number."""
        return int(self.scan.seq)

    def to_fields(self) -> dict[str, Any]:
        """The scan's fields (SCAN_WIRE) at the message's top level, not nested under `scan`."""
        return scan_to_fields(self.scan)

    @classmethod
    def from_fields(cls, fields: Fields) -> Self:
        """The message around the LaserScan read from `fields` (`scan_from_fields`)."""
        return cls(scan_from_fields(fields))


@dataclass(frozen=True, eq=False)
class DeskewedScanMessage(Message):
    """A scan after motion compensation: valid endpoints in the robot's frame at `stamp_s`.

    `points` travel as float64, bit for bit what the deskewer computed, so a front end fed
    from the bus sees exactly the input of the in-process pipeline (360 beams: 5.8 kB).
    `no_return_points` (float64 too, schema version 2) are the endpoints of the beams that saw
    nothing in range (`DeskewResult.no_return_points`): the map clears free space along them.
    `odom_pose` (schema version 2) is the odometry pose at `stamp_s` as the deskewer's buffer
    gives it (None when it has none), what the in-process pipeline hands its front end: the
    matcher then needs no odometry stream of its own, nor its order against the scans.

    `beam_count` is the raw scan's beam count and `dropped_count` its beams not in `points`
    (no-return and erroneous ones);
    `source_used` names the motion source the deskewer used (e.g. "odometry", "none"),
    `times_assumed` is True when beam times came from the scan duration, not the driver;
    `mount` (schema version 3) is the raw scan's sensor pose on the robot: rays start there.
    """

    TYPE = "scan_deskewed"
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        "seq": INT,
        "stamp_s": NUMBER,
        "points": array("<f8"),
        "source_used": TEXT,
        "times_assumed": FLAG,
        "beam_count": INT,
        "dropped_count": INT,
        "no_return_points": array("<f8"),
        "odom_pose": optional(POSE),
        "mount": POSE,
    }
    robot_id: str
    seq: int
    stamp_s: float
    points: NDArray[np.float64]
    source_used: str
    times_assumed: bool
    beam_count: int
    dropped_count: int
    no_return_points: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    odom_pose: Pose2D | None = None
    mount: Pose2D = IDENTITY

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        if self.odom_pose is not None:
            check_pose("odom_pose", self.odom_pose)
        check_pose("mount", self.mount)
        object.__setattr__(self, "seq", check_count("seq", self.seq))
        object.__setattr__(self, "stamp_s", check_finite("stamp_s", self.stamp_s))
        points = check_array("points", self.points, np.float64, (None, 2))
        object.__setattr__(self, "points", points)
        check_text("source_used", self.source_used, allow_empty=True)
        object.__setattr__(self, "times_assumed", bool(self.times_assumed))
        beams = check_count("beam_count", self.beam_count)
        dropped = check_count("dropped_count", self.dropped_count)
        if dropped > beams:
            raise MessageError(f"dropped_count ({dropped}) exceeds beam_count ({beams})")
        misses = check_array("no_return_points", self.no_return_points, np.float64, (None, 2))
        object.__setattr__(self, "no_return_points", misses)
        if len(points) + len(misses) > beams:
            raise MessageError(
                f"points ({len(points)} rows) and no_return_points ({len(misses)} rows) "
                f"exceed beam_count ({beams})"
            )
        if len(misses) > dropped:
            raise MessageError(
                f"no_return_points has {len(misses)} rows, more than dropped_count ({dropped})"
            )
        object.__setattr__(self, "beam_count", beams)
        object.__setattr__(self, "dropped_count", dropped)


@dataclass(frozen=True, eq=False)
class OdometryMessage(Message):
    """One wheel-odometry sample (`odom.seq` is the message sequence number)."""

    TYPE = "odom"
    odom: Odometry

    def __post_init__(self) -> None:
        if not isinstance(self.odom, Odometry):
            raise MessageError(f"odom must be an Odometry, got {type(self.odom).__name__}")
        check_robot_id(self.odom.robot_id)
        check_count("odom.seq", self.odom.seq)
        check_position("odom.pose", self.odom.pose)

    @property
    def robot_id(self) -> str:
        """The sample's robot id."""
        return self.odom.robot_id

    @property
    def seq(self) -> int:
        """The sample's `seq`: the message sequence number."""
        return int(self.odom.seq)

    def to_fields(self) -> dict[str, Any]:
        """The sample's fields (ODOM_WIRE) at the message's top level, not nested under `odom`."""
        return encode_fields(ODOM_WIRE, self.odom)

    @classmethod
    def from_fields(cls, fields: Fields) -> Self:
        """The message around the Odometry read from `fields` (ODOM_WIRE)."""
        return cls(Odometry(**decode_fields(ODOM_WIRE, fields)))
