"""Estimate messages: pose estimates, match requests and responses, trajectories.

Poses follow scanflow.matching.api: a match pose is T_target_source. Covariances are 3x3 over
(x, y, theta); +inf marks "no information" (a failed match) and is legal, NaN is not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Self

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan
from scanflow.wire.base import (
    Message,
    check_array,
    check_count,
    check_finite,
    check_path,
    check_pose,
    check_position,
    check_robot_id,
    check_text,
)
from scanflow.wire.codec import Fields, Scalar, clip, encode_array, short
from scanflow.wire.errors import MessageError, SchemaError
from scanflow.wire.scans import scan_from_fields, scan_to_fields
from scanflow.wire.schema import (
    FLAG,
    INT,
    NUMBER,
    PATH,
    POSE,
    TEXT,
    VECTOR3,
    FieldCodec,
    Schema,
    array,
    mapping,
    optional,
)

if TYPE_CHECKING:
    from scanflow.frontend import FrontendOutput
    from scanflow.matching.api import MatchResult

ERROR_STATUS = "error"


def _no_information() -> NDArray[np.float64]:
    return np.diag([math.inf, math.inf, math.inf])


def _check_covariance(name: str, values: Any) -> NDArray[np.float64]:
    return check_array(name, values, np.float64, (3, 3), allow_inf=True)


@dataclass(frozen=True, eq=False)
class PoseEstimateMessage(Message):
    """The tracked pose of a robot in its map frame at `stamp_s`, and how it was obtained."""

    TYPE = "pose"
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        "seq": INT,
        "stamp_s": NUMBER,
        "pose": POSE,
        "covariance": array("<f8"),
        "status": TEXT,
        "method": TEXT,
        "iterations": INT,
        "score": NUMBER,
        "message": TEXT,
        "correction": optional(POSE),
        "odom_pose": optional(POSE),
        "run": INT,
    }
    robot_id: str
    seq: int
    stamp_s: float
    pose: Pose2D
    covariance: NDArray[np.float64]
    status: str
    method: str
    iterations: int
    score: float
    message: str = ""
    # Set when the back end redrew the map at this scan: T_new_old, the map frame's change
    # (this pose is in the new frame, the ones before in the old).
    correction: Pose2D | None = None
    # The odometry pose the tracker had for this scan (None: none): a restarted tracker goes on
    # from the map server's last pose with the odometry since it (schema version 8).
    odom_pose: Pose2D | None = None
    run: int = 0  # the tracker's run (MapInsertMessage.run; 0: unknown)

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        object.__setattr__(self, "seq", check_count("seq", self.seq))
        object.__setattr__(self, "run", check_count("run", self.run))
        object.__setattr__(self, "stamp_s", check_finite("stamp_s", self.stamp_s))
        check_pose("pose", self.pose)
        object.__setattr__(self, "covariance", _check_covariance("covariance", self.covariance))
        check_text("status", self.status)
        check_text("method", self.method, allow_empty=True)
        object.__setattr__(self, "iterations", check_count("iterations", self.iterations))
        object.__setattr__(self, "score", check_finite("score", self.score))
        check_text("message", self.message, allow_empty=True)
        if self.correction is not None:
            check_pose("correction", self.correction)
        if self.odom_pose is not None:
            check_pose("odom_pose", self.odom_pose)

    @classmethod
    def from_result(
        cls, result: MatchResult | FrontendOutput, robot_id: str, seq: int, stamp_s: float,
        correction: Pose2D | None = None, odom_pose: Pose2D | None = None, run: int = 0,
    ) -> Self:
        """The estimate a tracker publishes: a match result's or a front-end output's pose,
        covariance, status, method, iterations, score and message (and the map frame's
        `correction` when the map was redrawn at this scan, the scan's `odom_pose`, the
        tracker's `run`)."""
        return cls(
            robot_id=robot_id,
            seq=seq,
            stamp_s=stamp_s,
            pose=result.pose,
            covariance=result.covariance,
            status=str(result.status),
            method=result.method,
            iterations=result.iterations,
            score=result.score,
            message=result.message,
            correction=correction,
            odom_pose=odom_pose,
            run=run,
        )


@dataclass(frozen=True, eq=False)
class InitialPoseMessage(Message):
    """Where a robot is, by an operator's word (ROS's /initialpose): its tracker matches the
    next scan from `pose` (map frame); the tracker echoes the message once it took it."""

    TYPE = "initial_pose"
    WIRE: ClassVar[Schema] = {"robot_id": TEXT, "pose": POSE}
    robot_id: str
    pose: Pose2D

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        check_position("pose", check_pose("pose", self.pose))


@dataclass(frozen=True)
class MapRef:
    """A match target that is the map the mapserver keeps for `robot_id` (scan-to-map)."""

    robot_id: str

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)


Operand = LaserScan | NDArray[np.float64]


def _check_operand(name: str, value: Any, allow_map: bool) -> Any:
    """A scan, (N, 2) finite float64 points, or (targets only) a MapRef."""
    if isinstance(value, LaserScan) or (allow_map and isinstance(value, MapRef)):
        return value
    return check_array(name, value, np.float64, (None, 2))


def _operand_to_fields(value: Operand | MapRef) -> dict[str, Any]:
    if isinstance(value, LaserScan):
        return {"kind": "scan", "scan": scan_to_fields(value)}
    if isinstance(value, MapRef):
        return {"kind": "map", "robot_id": value.robot_id}
    return {"kind": "points", "points": encode_array(value, "<f8")}


def _operand_from_fields(f: Fields, allow_map: bool) -> Operand | MapRef:
    kind = f.text("kind")
    if kind == "scan":
        return scan_from_fields(f.nested("scan"))
    if kind == "points":
        return f.array("points", "<f8")
    if kind == "map" and allow_map:
        return MapRef(f.text("robot_id"))
    allowed = "'scan', 'points' or 'map'" if allow_map else "'scan' or 'points'"
    raise SchemaError(f"{f.where}.kind: expected {allowed}, got {short(kind)}")


SOURCE = FieldCodec(
    _operand_to_fields, lambda fields, name: _operand_from_fields(fields.nested(name), False)
)
TARGET = FieldCodec(
    _operand_to_fields, lambda fields, name: _operand_from_fields(fields.nested(name), True)
)


@dataclass(frozen=True, eq=False)
class MatchRequest(Message):
    """Ask a matcher to align `source` to `target` (scan, points or a robot's map).

    `options` are the method's keyword options (str -> bool/int/float/str, no NaN);
    `initial_guess` is T_target_source or None for identity.
    """

    TYPE = "match_request"
    WIRE: ClassVar[Schema] = {
        "method": TEXT,
        "source": SOURCE,
        "target": TARGET,
        "initial_guess": optional(POSE),
        "options": mapping((bool, int, float, str), "bool/int/float/str"),
    }
    method: str
    source: Operand
    target: Operand | MapRef
    initial_guess: Pose2D | None = None
    options: dict[str, Scalar] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_text("method", self.method)
        object.__setattr__(self, "source", _check_operand("source", self.source, False))
        object.__setattr__(self, "target", _check_operand("target", self.target, True))
        if self.initial_guess is not None:
            check_pose("initial_guess", self.initial_guess)
        if not isinstance(self.options, dict):
            raise MessageError(f"options must be a dict, got {type(self.options).__name__}")
        object.__setattr__(self, "options", {k: _option(k, v) for k, v in self.options.items()})


def _option(key: Any, value: Any) -> Scalar:
    """An option value as a plain Python scalar (numpy scalars unwrapped); NaN refused."""
    if not isinstance(key, str):
        raise MessageError(f"options key {key!r} must be a string")
    if isinstance(value, np.generic):
        value = value.item()
    if type(value) not in (bool, int, float, str):
        raise MessageError(f"options[{key!r}] must be bool/int/float/str, got {value!r}")
    if isinstance(value, float) and math.isnan(value):
        raise MessageError(f"options[{key!r}] must not be NaN")
    return value


@dataclass(frozen=True, eq=False)
class MatchResponse(Message):
    """A matcher's answer: the fields of MatchResult, or a non-empty `error` (then not `ok`)."""

    TYPE = "match_response"
    WIRE: ClassVar[Schema] = {
        "pose": POSE,
        "covariance": array("<f8"),
        "score": NUMBER,
        "iterations": INT,
        "converged": FLAG,
        "status": TEXT,
        "method": TEXT,
        "message": TEXT,
        "time_s": NUMBER,
        "inliers": INT,
        "weak_direction": optional(VECTOR3),
        "error": TEXT,
    }
    pose: Pose2D
    covariance: NDArray[np.float64]
    score: float
    iterations: int
    converged: bool
    status: str
    method: str
    message: str = ""
    time_s: float = 0.0
    inliers: int = 0
    weak_direction: tuple[float, float, float] | None = None
    error: str = ""

    def __post_init__(self) -> None:
        check_pose("pose", self.pose)
        object.__setattr__(self, "covariance", _check_covariance("covariance", self.covariance))
        object.__setattr__(self, "score", check_finite("score", self.score))
        object.__setattr__(self, "iterations", check_count("iterations", self.iterations))
        object.__setattr__(self, "converged", bool(self.converged))
        check_text("status", self.status)
        check_text("method", self.method, allow_empty=True)
        check_text("message", self.message, allow_empty=True)
        time_s = check_finite("time_s", self.time_s)
        if time_s < 0:
            raise MessageError(f"time_s must be >= 0, got {time_s}")
        object.__setattr__(self, "time_s", time_s)
        object.__setattr__(self, "inliers", check_count("inliers", self.inliers))
        if self.weak_direction is not None:
            weak = check_array("weak_direction", self.weak_direction, np.float64, (3,))
            object.__setattr__(self, "weak_direction", tuple(float(v) for v in weak))
        check_text("error", self.error, allow_empty=True)

    @property
    def ok(self) -> bool:
        """True when there is no `error` and the status is "ok": the pose can be trusted."""
        return not self.error and self.status == "ok"

    @classmethod
    def from_result(cls, result: MatchResult) -> Self:
        """The response carrying `result`'s fields (all but `extra`, which is not sent)."""
        return cls(
            pose=result.pose,
            covariance=result.covariance,
            score=result.score,
            iterations=result.iterations,
            converged=result.converged,
            status=str(result.status),
            method=result.method,
            message=result.message,
            time_s=result.time_s,
            inliers=result.inliers,
            weak_direction=result.weak_direction,
        )

    @classmethod
    def from_error(cls, error: str, method: str = "") -> Self:
        """A request that could not be served (bad input, no map): identity pose, no information;
        the error text clipped (an exception's text may quote a long input)."""
        return cls(
            pose=Pose2D(),
            covariance=_no_information(),
            score=0.0,
            iterations=0,
            converged=False,
            status=ERROR_STATUS,
            method=method,
            message=clip(error),
            error=clip(error) or "unspecified error",
        )


@dataclass(frozen=True, eq=False)
class TrajectoryMessage(Message):
    """A robot's estimated path: `poses[i]` (x, y, theta) at `stamps_s[i]`, optional covariances."""

    TYPE = "trajectory"
    BULK = True
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        **PATH,
        "covariances": optional(array("<f8")),
    }
    robot_id: str
    stamps_s: NDArray[np.float64]
    poses: NDArray[np.float64]
    covariances: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        check_path(self)
        if self.covariances is not None:
            shape = (len(self.stamps_s), 3, 3)
            cov = check_array("covariances", self.covariances, np.float64, shape, allow_inf=True)
            object.__setattr__(self, "covariances", cov)
