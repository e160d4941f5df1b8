"""The HTTP API contract: request and response models with limits, units and examples.

JSON cannot carry NaN or infinity: a range of `null` is a beam with no return, and a
covariance entry of `null` means "no information" (an infinite variance, e.g. a failed match).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, StrictBool, model_validator
from pydantic.config import JsonDict
from scanflow import keys
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.matching import DEFAULT_METHOD
from scanflow.scan import MAX_BEAMS, MAX_MOUNT_M, LaserScan, Odometry
from scanflow.wire import (
    MAX_COUNT,
    MAX_POSITION_M,
    MapMetaMessage,
    MatchResponse,
    PoseEstimateMessage,
)

COORD_LIMIT_M = MAX_POSITION_M
STAMP_LIMIT_S = 1e11
RobotId = Annotated[
    str, Field(pattern=r"^[A-Za-z0-9_\-.]{1,64}$", examples=["robot"], description="robot id")
]
Coord = Annotated[float, Field(ge=-COORD_LIMIT_M, le=COORD_LIMIT_M)]
Angle = Annotated[float, Field(ge=-100.0, le=100.0, description="radians")]
Stamp = Annotated[float, Field(ge=0.0, le=STAMP_LIMIT_S, description="seconds (epoch or log)")]
Seq = Annotated[int, Field(ge=0, le=MAX_COUNT, description="message sequence number")]
Range = Annotated[float, Field(ge=-COORD_LIMIT_M, le=COORD_LIMIT_M)] | None
Matrix3 = list[list[float | None]]

_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)
_EXAMPLE_SCAN: JsonDict = {
    "ranges_m": [2.0, 2.1, None, 2.3, 2.2, 2.0, 1.9, 2.0],
    "angle_min_rad": -1.57,
    "angle_increment_rad": 0.39,
    "range_min_m": 0.1,
    "range_max_m": 30.0,
    "stamp_s": 1700000000.0,
    "scan_duration_s": 0.1,
}


class PoseIn(BaseModel):
    """An SE(2) pose: position in metres, heading in radians."""

    model_config = ConfigDict(**_STRICT, json_schema_extra={"examples": [
        {"x_m": 0.1, "y_m": 0.0, "theta_rad": 0.05}
    ]})

    x_m: Coord = 0.0
    y_m: Coord = 0.0
    theta_rad: Angle = 0.0

    def to_pose(self) -> Pose2D:
        """The pose as a Pose2D."""
        return Pose2D(self.x_m, self.y_m, self.theta_rad)


class MountIn(PoseIn):
    """The lidar's pose on the robot (T_base_laser): x and y each within +-MAX_MOUNT_M of the
    robot's origin."""

    x_m: Annotated[float, Field(ge=-MAX_MOUNT_M, le=MAX_MOUNT_M)] = 0.0
    y_m: Annotated[float, Field(ge=-MAX_MOUNT_M, le=MAX_MOUNT_M)] = 0.0


class PoseValue(BaseModel):
    """An SE(2) pose in an answer: as computed, without PoseIn's input limits (a match of two
    far-away scans may lie beyond them, and an answer must never fail validation)."""

    x_m: float
    y_m: float
    theta_rad: float

    @classmethod
    def of(cls, pose: Pose2D) -> PoseValue:
        """The pose's fields under their JSON names."""
        return cls(x_m=pose.x, y_m=pose.y, theta_rad=pose.theta)


class ScanIn(BaseModel):
    """A 2D lidar scan (ROS LaserScan conventions; `stamp_s` is the first beam's time)."""

    model_config = ConfigDict(**_STRICT, json_schema_extra={"examples": [_EXAMPLE_SCAN]})

    ranges_m: list[Range] = Field(min_length=1, max_length=MAX_BEAMS)
    angle_min_rad: Angle
    angle_increment_rad: Annotated[float, Field(ge=-1.0, le=1.0)]
    range_min_m: Annotated[float, Field(ge=0.0, le=1000.0)] = 0.0
    range_max_m: Annotated[float, Field(gt=0.0, le=1000.0)] = 100.0
    stamp_s: Stamp = 0.0
    scan_duration_s: Annotated[float, Field(ge=0.0, le=10.0)] = 0.0
    beam_time_offsets_s: list[Annotated[float, Field(ge=0.0, le=10.0)]] | None = Field(
        None, max_length=MAX_BEAMS
    )
    intensities: list[Annotated[float, Field(ge=-1e9, le=1e9)]] | None = Field(
        None, max_length=MAX_BEAMS
    )
    frame_id: Annotated[str, Field(max_length=128)] = "laser"
    mount: MountIn | None = Field(
        None, description="the lidar's pose on the robot (T_base_laser); omit: at its origin"
    )
    seq: Seq | None = Field(None, description=(
        "omit to let the gateway number the scans; one at or below the robot's last is "
        "refused (409) except 0, which starts a new run (its map afresh)"))

    @model_validator(mode="after")
    def _check_layout(self) -> ScanIn:
        n = len(self.ranges_m)
        for name in ("beam_time_offsets_s", "intensities"):
            values = getattr(self, name)
            if values is not None and len(values) != n:
                raise ValueError(f"{name} has {len(values)} values, ranges_m has {n}")
        if self.range_max_m <= self.range_min_m:
            raise ValueError(
                f"range_max_m ({self.range_max_m}) must exceed range_min_m ({self.range_min_m})"
            )
        return self

    def to_scan(self, robot_id: str, seq: int) -> LaserScan:
        """The LaserScan (null ranges become NaN: masked beams); may raise ScanError."""
        ranges = np.array([math.nan if r is None else r for r in self.ranges_m], np.float32)
        offsets = self.beam_time_offsets_s
        intensities = self.intensities
        return LaserScan(
            ranges_m=ranges,
            angle_min_rad=self.angle_min_rad,
            angle_increment_rad=self.angle_increment_rad,
            range_min_m=self.range_min_m,
            range_max_m=self.range_max_m,
            stamp_s=self.stamp_s,
            scan_duration_s=self.scan_duration_s,
            beam_time_offsets_s=None if offsets is None else np.array(offsets, np.float64),
            robot_id=robot_id,
            frame_id=self.frame_id,
            intensities=None if intensities is None else np.array(intensities, np.float32),
            seq=seq,
            mount=self.mount.to_pose() if self.mount is not None else IDENTITY,
        )


class VelocityIn(BaseModel):
    """Body-frame velocity: forward and left speed (m/s), yaw rate (rad/s)."""

    model_config = _STRICT

    vx_mps: Annotated[float, Field(ge=-100.0, le=100.0)] = 0.0
    vy_mps: Annotated[float, Field(ge=-100.0, le=100.0)] = 0.0
    omega_radps: Annotated[float, Field(ge=-100.0, le=100.0)] = 0.0


class OdometryIn(BaseModel):
    """One wheel-odometry sample: the robot's pose in its odometry frame at `stamp_s`."""

    model_config = ConfigDict(**_STRICT, json_schema_extra={"examples": [
        {"stamp_s": 1700000000.0, "pose": {"x_m": 1.0, "y_m": 0.5, "theta_rad": 0.1}}
    ]})

    stamp_s: Stamp
    pose: PoseIn
    velocity: VelocityIn | None = None
    seq: Seq | None = Field(None, description=(
        "omit to let the gateway number the samples; one at or below the robot's last is "
        "refused (409) except 0, which starts a new run (its map afresh)"))

    def to_odometry(self, robot_id: str, seq: int) -> Odometry:
        """The Odometry sample of `robot_id` under `seq`; velocity (vx, vy, omega) or None."""
        v = self.velocity
        velocity = None if v is None else (v.vx_mps, v.vy_mps, v.omega_radps)
        return Odometry(self.stamp_s, self.pose.to_pose(), velocity, robot_id, seq)


class IngestAck(BaseModel):
    """Where and under which sequence number an ingested message was published."""

    robot_id: str
    seq: int
    key: str


Option = StrictBool | int | Annotated[float, Field(allow_inf_nan=False)] | str


class MatchIn(BaseModel):
    """Scan-to-scan (`source` and `target`) or scan-to-map (`source` and `robot_id`)."""

    model_config = ConfigDict(**_STRICT, json_schema_extra={"examples": [
        {"method": "icp", "source": _EXAMPLE_SCAN, "target": _EXAMPLE_SCAN,
         "initial_guess": {"x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}},
        {"method": "gn", "source": _EXAMPLE_SCAN, "robot_id": "robot"},
    ], "oneOf": [{"required": ["target"]}, {"required": ["robot_id"]}]})

    method: Annotated[str, Field(max_length=32, description="see GET /api/v1/match/methods")] = (
        DEFAULT_METHOD
    )
    source: ScanIn
    target: ScanIn | None = None
    robot_id: RobotId | None = Field(None, description="match against this robot's map")
    initial_guess: PoseIn | None = Field(None, description="T_target_source; identity if absent")
    options: dict[Annotated[str, Field(max_length=64)], Option] = Field(
        default_factory=dict, max_length=32, description="the method's keyword options"
    )

    @model_validator(mode="after")
    def _one_target(self) -> MatchIn:
        if (self.target is None) == (self.robot_id is None):
            raise ValueError("give exactly one of target (scan-to-scan) or robot_id (scan-to-map)")
        if self.robot_id is not None:
            keys.check_robot_id(self.robot_id)
        return self


def matrix_out(values: Any) -> Matrix3:
    """A 3x3 matrix for JSON: non-finite entries (no information) become null."""
    return [[float(v) if math.isfinite(v) else None for v in row] for row in np.asarray(values)]


class MatchOut(BaseModel):
    """The matcher's answer; `pose` maps source points into the target (or map) frame."""

    pose: PoseValue
    covariance: Matrix3 = Field(description="3x3 over (x, y, theta); null = no information")
    score: float
    iterations: int
    converged: bool
    status: str = Field(description="'ok' or why the match cannot be trusted")
    method: str
    message: str
    inliers: int
    weak_direction: list[float] | None
    time_s: float = Field(description="the matcher's compute time")
    round_trip_s: float = Field(description="time the gateway waited for the answer")

    @classmethod
    def from_response(cls, r: MatchResponse, round_trip_s: float) -> MatchOut:
        """The matcher's answer for JSON (non-finite covariance entries null), with the wait."""
        return cls(
            pose=PoseValue.of(r.pose),
            covariance=matrix_out(r.covariance),
            score=r.score,
            iterations=r.iterations,
            converged=r.converged,
            status=r.status,
            method=r.method,
            message=r.message,
            inliers=r.inliers,
            weak_direction=None if r.weak_direction is None else list(r.weak_direction),
            time_s=r.time_s,
            round_trip_s=round_trip_s,
        )


class MethodsOut(BaseModel):
    methods: list[str]
    default: str


class PoseOut(BaseModel):
    """A robot's pose estimate in its map frame."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "robot_id": "robot", "seq": 42, "stamp_s": 1700000004.2, "x_m": 1.5, "y_m": -0.2,
        "theta_rad": 0.3, "covariance": [[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 1e-5]],
        "status": "ok", "method": "gn", "iterations": 6, "score": 0.9, "message": "",
        "interpolated": False,
    }]})

    robot_id: str
    seq: int | None = Field(description=(
        "the scan's seq (interpolated: the estimate's before `stamp_s`); null for a pose from "
        "the map server's trajectory, which keeps no seqs"))
    stamp_s: float
    x_m: float
    y_m: float
    theta_rad: float
    covariance: Matrix3
    status: str
    method: str
    iterations: int
    score: float
    message: str
    interpolated: bool = Field(False, description="true when between two estimates")
    map_correction: PoseValue | None = Field(
        None, description="set when loop closure redrew the map at this scan: T_new_old, the "
        "map frame's change (this pose is in the new frame; the earlier path moved with it)",
    )

    @classmethod
    def from_estimate(
        cls, e: PoseEstimateMessage, pose: Pose2D | None = None, stamp_s: float | None = None
    ) -> PoseOut:
        """The estimate as is, or (with `pose`, `stamp_s`) interpolated from it."""
        p = e.pose if pose is None else pose
        return cls(
            robot_id=e.robot_id,
            seq=e.seq,
            stamp_s=e.stamp_s if stamp_s is None else stamp_s,
            x_m=p.x,
            y_m=p.y,
            theta_rad=p.theta,
            covariance=matrix_out(e.covariance),
            status=e.status,
            method=e.method,
            iterations=e.iterations,
            score=e.score,
            message=e.message,
            interpolated=pose is not None,
            map_correction=(
                None if e.correction is None or pose is not None else PoseValue.of(e.correction)
            ),
        )

    @classmethod
    def from_trajectory(
        cls, robot_id: str, pose: Pose2D, stamp_s: float, interpolated: bool = True
    ) -> PoseOut:
        """A pose from the map server's trajectory, which keeps no seq, covariance or status:
        interpolated at `stamp_s`, or (`interpolated` false) its pose there."""
        return cls(
            robot_id=robot_id,
            seq=None,
            stamp_s=stamp_s,
            x_m=pose.x,
            y_m=pose.y,
            theta_rad=pose.theta,
            covariance=[[None] * 3 for _ in range(3)],
            status="trajectory",
            method="",
            iterations=0,
            score=0.0,
            message=("interpolated from" if interpolated else "the last pose of")
            + " the map server's trajectory (no covariance kept)",
            interpolated=interpolated,
        )


class TimedPose(BaseModel):
    stamp_s: float
    x_m: float
    y_m: float
    theta_rad: float


class TrajectoryOut(BaseModel):
    """A robot's estimated path in time order."""

    robot_id: str
    source: Literal["mapserver", "cache"] = Field(
        description="the map server's full trajectory, or the gateway's bounded cache"
    )
    poses: list[TimedPose]


class MapMetaOut(BaseModel):
    """Geometry of a robot's occupancy map: cell (row, col) grows with (y, x)."""

    robot_id: str
    revision: int
    stamp_s: float
    resolution_m: float
    origin_x_m: float
    origin_y_m: float
    rows: int
    cols: int
    width_m: float
    height_m: float

    @classmethod
    def from_message(cls, m: MapMetaMessage) -> MapMetaOut:
        """The map server's metadata, with the map's size in metres (cells times resolution)."""
        return cls(
            robot_id=m.robot_id,
            revision=m.revision,
            stamp_s=m.stamp_s,
            resolution_m=m.resolution_m,
            origin_x_m=m.origin_x_m,
            origin_y_m=m.origin_y_m,
            rows=m.rows,
            cols=m.cols,
            width_m=m.cols * m.resolution_m,
            height_m=m.rows * m.resolution_m,
        )


class RobotOut(BaseModel):
    robot_id: str
    last_pose: PoseOut | None
    poses_cached: int
    last_pose_received_s: float | None = Field(description="gateway wall clock (epoch s)")
    last_scan_received_s: float | None = Field(description="gateway wall clock (epoch s)")
    scans_seen: int
    map_revision: int | None
    restarts: int = Field(description="times the pose cache started afresh: a replay, or "
                          "another run of the robot's tracker")


class ServiceOut(BaseModel):
    service: str
    instance: str


class RobotsOut(BaseModel):
    robots: list[RobotOut]
    services: list[ServiceOut] = Field(description="services whose liveliness token is present")


class DroppedOut(BaseModel):
    """What one holder of robot state let go of when the robot was retired."""

    known: bool = Field(description="it held state of the robot (false: nothing to drop)")
    dropped: dict[str, int] = Field(
        description="what went, by name: map_revision, keyframes, poses, snapshot_files "
        "(map server), map_revision, keyframes, inserts_kept (matcher), scans_pending, "
        "odometry_samples (deskew), poses_cached, scans_seen (gateway)"
    )


class RetiredServiceOut(DroppedOut):
    """One service instance's confirmation: it holds nothing of the robot now."""

    service: str
    instance: str


class RetiredOut(BaseModel):
    """A robot retired: every service that keeps robot state confirmed it dropped it."""

    robot_id: str
    services: list[RetiredServiceOut] = Field(
        description="every instance that confirmed, in the order asked (the data's): deskew, "
        "each matcher shard, the map server"
    )
    gateway: DroppedOut = Field(description="the gateway's own pose cache and seqs of it")


class ZenohOut(BaseModel):
    open: bool
    mode: str
    zid: str
    routers: list[str]
    peers: list[str]


class HealthOut(BaseModel):
    status: Literal["ok", "degraded", "down"]
    zenoh: ZenohOut
    services: list[ServiceOut]
    missing: list[str] = Field(description="expected services without a liveliness token")
    stream_clients: int
